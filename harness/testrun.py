"""Testing a finished run's saved policy on many fresh episodes (the paper's Fig. 4b for the unicycle).

``harness eval RUN_ID --episodes 1000`` loads the run's task (with its recorded variant options)
and its last saved policy from the tracking store, runs the episodes on a new environment, and
writes the success rate and a histogram of the final distance from the goal (e.g. the top of the
unicycle's frame from upright). Test episodes are not interaction: nothing is added to the run's
interaction counters; the results are logged to the run as ``test_*`` metrics and artifacts.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.datafile import LegacyFormatError, is_legacy, legacy_message, trial_files
from harness.discovery import load_learner, load_task
from harness.errors import CheckpointError
from harness.evaluation import Evaluator
from harness.learner import POLICY_PREFIX


@dataclass
class PolicyTestReport:
    """Outcome of :func:`evaluate_saved_policy`."""

    run_id: str
    task: str
    policy_artifact: str
    episodes: int
    success_rate: float
    final_distances: np.ndarray  # (episodes,), NaN where the task defines no distance
    mean_cost: float
    histogram: Path | None
    summary_path: Path


def task_options(params: dict[str, str]) -> dict[str, str]:
    """The task variant options a run recorded (its ``task.*`` params, unset ones left out)."""
    return {k[len("task."):]: v for k, v in params.items() if k.startswith("task.") and v != "None"}


def _latest_policy(client, run_id: str, trial: int | None) -> str:
    """The artifact name of the run's last (or ``trial``'s) policy; a trial's data-format file over an older one."""
    files = trial_files((a.path for a in client.list_artifacts(run_id, "policies")), POLICY_PREFIX)
    if not files:
        raise CheckpointError(f"run {run_id} has no saved policy (no artifacts under 'policies/')")
    if trial is None:
        return files[max(files)]
    if trial not in files:
        raise CheckpointError(f"run {run_id} has no policy of trial {trial}; it has {', '.join(Path(f).name for f in files.values())}")
    return files[trial]


def plot_distance_histogram(distances: np.ndarray, threshold: float | None, title: str, path: Path) -> Path:
    """Histogram of final goal distances, with the success threshold marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.4), dpi=110)
    finite = distances[np.isfinite(distances)]
    ax.hist(finite, bins=40, color="tab:blue", alpha=0.8)
    if threshold is not None:
        ax.axvline(threshold, color="tab:red", ls="--", label=f"success radius {threshold:g} m")
        ax.legend(fontsize=8)
    ax.set(xlabel="final distance from the goal [m]", ylabel="test episodes", title=title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def evaluate_saved_policy(
    run_id: str,
    episodes: int = 1000,
    seed: int = 12345,
    tracking_uri: str | None = None,
    out_dir: Path | None = None,
    trial: int | None = None,
) -> PolicyTestReport:
    """Run ``episodes`` test episodes of the run's last (or ``trial``'s) policy; log and return the outcome."""
    from harness.tracking import get_run, open_client, resolve_tracking_uri

    uri = resolve_tracking_uri(tracking_uri)
    client = open_client(uri)
    run = get_run(client, run_id, uri)
    params = run.data.params
    task = load_task(params["task"])(**task_options(params))
    artifact = _latest_policy(client, run_id, trial)
    out_dir = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="harness-eval-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    if is_legacy(artifact):
        raise LegacyFormatError(legacy_message(Path(artifact).name, "policy", run_id))
    local = Path(client.download_artifacts(run_id, artifact, str(out_dir)))
    policy = load_learner(params["learner"]).load_policy(local, task.spec)

    evaluator = Evaluator(task, n_episodes=episodes, seed=seed)
    try:
        result = evaluator(policy)
    finally:
        evaluator.close()
    distances = np.array([np.nan if (d := task.goal_distance(ep.states[-1])) is None else d for ep in result.episodes])
    threshold = getattr(task, "success_radius", None)
    histogram = None
    if np.isfinite(distances).any():
        histogram = plot_distance_histogram(
            distances, threshold, f"{params['learner']} on {params['task']}: {episodes} test episodes, "
            f"success {100 * result.success_rate:.1f}%", out_dir / "test_final_distance.png",
        )
    summary = {
        "run_id": run_id, "task": params["task"], "learner": params["learner"], "policy": artifact,
        "episodes": episodes, "seed": seed, "success_rate": result.success_rate, "mean_cost": result.mean_cost,
        "final_distance_median": float(np.nanmedian(distances)) if np.isfinite(distances).any() else None,
    }
    summary_path = out_dir / "test_summary.json"
    summary_path.write_text(json.dumps(summary, indent=2))
    np.save(out_dir / "test_final_distances.npy", distances)
    client.log_metric(run_id, "test_success_rate", result.success_rate)
    client.log_metric(run_id, "test_episodes", float(episodes))
    for path in (summary_path, out_dir / "test_final_distances.npy", histogram):
        if path is not None:
            client.log_artifact(run_id, str(path), "test")
    return PolicyTestReport(run_id, params["task"], artifact, episodes, result.success_rate, distances, result.mean_cost, histogram, summary_path)
