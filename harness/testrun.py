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

from harness.datafile import LegacyFormatError, is_legacy, legacy_message
from harness.discovery import load_learner, load_task
from harness.evaluation import Evaluator
from harness.learner_logs import save_figure


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
    save_figure(fig, path)
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
    from harness.store import Store, layout

    store = Store(tracking_uri)
    run = store.run(run_id)
    params = run.params
    task = load_task(params["task"])(**task_options(params))
    artifact = run.policy(trial)
    out_dir = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="harness-eval-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    if is_legacy(artifact):
        raise LegacyFormatError(legacy_message(Path(artifact).name, "policy", run_id))
    policy = load_learner(params["learner"]).load_policy(run.file(artifact), task.spec)

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
            f"success {100 * result.success_rate:.1f}%", out_dir / layout.TEST_HISTOGRAM,
        )
    summary = {
        "run_id": run_id, "task": params["task"], "learner": params["learner"], "policy": artifact,
        "episodes": episodes, "seed": seed, "success_rate": result.success_rate, "mean_cost": result.mean_cost,
        "final_distance_median": float(np.nanmedian(distances)) if np.isfinite(distances).any() else None,
    }
    summary_path = out_dir / "test_summary.json"
    summary_path.write_text(json.dumps(summary, indent=2))
    np.save(out_dir / "test_final_distances.npy", distances)
    store.log_metrics(run_id, {layout.TEST_SUCCESS_RATE: result.success_rate, layout.TEST_EPISODES: float(episodes)})
    for path in (summary_path, out_dir / "test_final_distances.npy", histogram):
        if path is not None:
            store.log_artifact(run_id, path, layout.TEST)
    return PolicyTestReport(run_id, params["task"], artifact, episodes, result.success_rate, distances, result.mean_cost, histogram, summary_path)
