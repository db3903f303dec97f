"""The store layer: the one place that reads MLflow, the names runs get, both sweep layouts."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from harness.cli import main
from harness.configuration import bench_group_of
from harness.runner import RunConfig, run
from harness.store import Store, layout
from harness.sweep import SweepSpec, pools, run_sweep
from harness.tracking import MlflowTracker
from tests.harness import sweep_site
from tests.harness.sweep_site import plugin_paths, plugins  # noqa: F401 (fixtures)

REPO = Path(__file__).resolve().parents[2]

#: what reading or writing MLflow looks like in code
MLFLOW_CALLS = re.compile(r"\bMlflowClient\b|^\s*(import mlflow|from mlflow)|\bclient\.[a-z_]+\(", re.MULTILINE)


def test_only_the_store_and_the_writer_call_mlflow():
    """Report, sweep, eval, saved runs and the benchmarks read and write through harness.store; only it
    and the tracker (a run's own records) talk to MLflow."""
    allowed = {REPO / "harness" / "tracking.py", *(REPO / "harness" / "store").glob("*.py")}
    offenders = [f"{path.relative_to(REPO)}: {match.group(0).strip()}"
                 for folder in ("harness", "plugins", "benchmarks") for path in sorted((REPO / folder).rglob("*.py"))
                 if path not in allowed for match in MLFLOW_CALLS.finditer(path.read_text())]
    assert offenders == []
    assert MLFLOW_CALLS.search((REPO / "harness" / "store" / "client.py").read_text())  # the pattern does find calls


def test_a_bench_run_is_named_and_tagged_by_its_configuration(mlflow_uri):
    result = run(RunConfig("random", "cartpole", seed=4, learner_options={"scale": "0.5"}, task_options={"horizon": "12"},
                           max_trials=1, eval_episodes=1), tracker=MlflowTracker(mlflow_uri))
    stored = Store(mlflow_uri).run(result.run_id)
    assert stored.name == "random · cartpole [scale=0.5, horizon=12] · s4"
    assert stored.tags[layout.CONFIG_LABEL_TAG] == "random [scale=0.5, horizon=12]"
    assert stored.tags[layout.CONFIG_HASH_TAG] == bench_group_of(stored.params)[1]  # the report's group id
    assert Store(mlflow_uri).experiments()[stored.experiment_id] == "cartpole"
    # an option at its default is not in the name: the run of the defaults is named by learner, task and seed
    plain = run(RunConfig("random", "cartpole", seed=4, max_trials=1, eval_episodes=1), tracker=MlflowTracker(mlflow_uri))
    assert Store(mlflow_uri).run(plain.run_id).name == "random · cartpole · s4"


def test_a_legacy_sweep_goes_on_in_its_experiment_and_the_report_reads_both_layouts(plugins, tmp_path, monkeypatch):
    """A sweep begun before the per-task layout (its parent in the experiment `sweeps`) continues there;
    a new sweep has a parent in its task's experiment; `harness report` finds the cells of both."""
    monkeypatch.setattr(pools, "LocalPool", sweep_site.InlinePool)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    store = Store(uri)
    old = SweepSpec(("sweep-steps",), ("sweep-toy",), (2, 3), max_trials=2, eval_episodes=1)
    legacy = store.ensure_experiment(layout.LEGACY_SWEEP_EXPERIMENT)
    parent = store.create_run(legacy, f"sweep-{old.sweep_id}", {layout.SWEEP_TAG: old.sweep_id, layout.ROLE_TAG: "sweep"},
                              {"learners": "sweep-steps", "tasks": "sweep-toy", "seeds": "2-3", "command": old.command()})
    continued = run_sweep(old, uri)
    assert continued.parents == {"sweep-toy": (legacy, parent)}
    assert {r.experiment_id for r in store.children(parent, legacy)} == {legacy} and len(store.children(parent, legacy)) == 2

    new = SweepSpec(("sweep-steps",), ("sweep-toy",), (2, 3), max_trials=3, eval_episodes=1)
    fresh = run_sweep(new, uri)
    (experiment_id, new_parent), = fresh.parents.values()
    assert experiment_id == store.experiment_id("sweep-toy") and store.run(new_parent).tags[layout.TASK_TAG] == "sweep-toy"

    out = tmp_path / "out"
    report = CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--out", str(out), "--no-publish"])
    assert report.exit_code == 0, report.output
    comparison = (out / "comparison_sweep-toy.md").read_text()
    assert "| sweep-steps [max_trials=2] | 2/2 |" in comparison and "| sweep-steps [max_trials=3] | 2/2 |" in comparison
    notes = (out / "sweeps.md").read_text()
    assert f"- sweep `{old.sweep_id}` (parent run `{parent}`, status FINISHED):" in notes
    assert f"- sweep `{new.sweep_id}` (parent runs `{new_parent}` (sweep-toy, FINISHED)):" in notes

    # a bench run as runs were made before they were named and tagged: the published report names and tags it
    experiment = store.experiment_id("sweep-toy")
    old_run = store.create_run(experiment, "sweep-steps-sweep-toy-s9", {"learner": "sweep-steps", "task": "sweep-toy", "seed": "9"},
                               {"learner": "sweep-steps", "task": "sweep-toy", "seed": 9, "max_trials": 4, "budget_seconds": None,
                                "eval_episodes": 1})
    (tmp_path / "ckpt_trial002.pkl").write_bytes(b"state")
    store.log_artifact(old_run, tmp_path / "ckpt_trial002.pkl", layout.CHECKPOINTS)
    store.log_metrics(old_run, {"interaction_seconds": 8.0}, step=2)
    store.set_status(old_run, "KILLED")
    published = CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--out", str(out), "--include-bench", "--publish"])
    assert published.exit_code == 0, published.output
    renamed = store.run(old_run)
    assert renamed.name == "sweep-steps · sweep-toy · s9" and renamed.tags[layout.RESUMABLE_TAG] == "true"
    assert renamed.tags[layout.CONFIG_LABEL_TAG] == "sweep-steps" and renamed.tags[layout.CONFIG_HASH_TAG] == bench_group_of(renamed.params)[1]
    assert renamed.tags[layout.ROW_TAG] == "sweep-steps [max_trials=4]"


def test_bench_resume_finds_the_bench_run_not_a_sweep_cell(plugins, mlflow_uri, monkeypatch):
    """Sweep cells now live in their task's experiment beside the bench runs; `--resume` without an id
    continues an unfinished bench run only."""
    monkeypatch.setattr(pools, "LocalPool", sweep_site.InlinePool)
    result = run_sweep(SweepSpec(("sweep-steps",), ("sweep-toy",), (21,), max_trials=2, eval_episodes=1), mlflow_uri)
    store = Store(mlflow_uri)
    store.set_status(result.outcomes[0].run_id, "KILLED")
    tracker = MlflowTracker(mlflow_uri)
    assert tracker.find_resumable("sweep-toy", "sweep-steps", 21) is None
    bench = run(RunConfig("sweep-steps", "sweep-toy", 21, max_trials=1, eval_episodes=1), tracker=MlflowTracker(mlflow_uri))
    store.set_status(bench.run_id, "KILLED")
    assert tracker.find_resumable("sweep-toy", "sweep-steps", 21) == bench.run_id


def test_a_missing_artifact_is_named_with_the_run(mlflow_uri):
    from harness.errors import CheckpointError

    result = run(RunConfig("random", "cartpole", seed=8, max_trials=1, eval_episodes=1), tracker=MlflowTracker(mlflow_uri))
    stored = Store(mlflow_uri).run(result.run_id)
    assert stored.policy_trials() == [1] and stored.policy() == "policies/policy_trial001.policy"
    assert [a.path for a in stored.all_artifacts()] == ["episodes/interaction_episodes.npz", "policies/policy_trial001.policy", "result.json"]
    with pytest.raises(CheckpointError, match=f"run {result.run_id} has no artifact 'policies/policy_trial009.policy'"):
        stored.file("policies/policy_trial009.policy")
    with pytest.raises(CheckpointError, match="has no policy of trial 9; it has policy_trial001.policy"):
        stored.policy(9)


def test_a_run_without_its_episodes_file_gives_those_of_its_newest_checkpoint_that_loads(mlflow_uri):
    """A run stopped before its end (SIGUSR1, a crash) has no episodes file yet: the reader takes the
    episodes from the newest checkpoint, skips one cut short, and names what is missing where neither is there."""
    import numpy as np

    from harness.errors import CheckpointError

    result = run(RunConfig("random", "cartpole", seed=9, max_trials=3, eval_episodes=1), tracker=MlflowTracker(mlflow_uri))
    stored = Store(mlflow_uri).run(result.run_id)
    full = stored.episodes()
    assert [a.path for a in stored.artifacts(layout.CHECKPOINTS)] == ["checkpoints/ckpt_trial001.ckpt", "checkpoints/ckpt_trial002.ckpt"]
    stored.file(layout.EPISODES).unlink()

    def same(a, b) -> bool:
        return all(np.array_equal(x.states, y.states) and np.array_equal(x.actions, y.actions) for x, y in zip(a, b, strict=True))

    newest = stored.newest_checkpoint()
    assert newest.trial == 2 and same(stored.episodes(), full[:len(newest.interaction["episodes"])])
    ckpt2 = stored.file("checkpoints/ckpt_trial002.ckpt")
    ckpt2.write_bytes(ckpt2.read_bytes()[:100])  # cut short, as by a crash while writing
    first = stored.newest_checkpoint()
    assert first.trial == 1 and same(stored.episodes(), full[:len(first.interaction["episodes"])])
    assert len(first.interaction["episodes"]) < len(newest.interaction["episodes"])
    stored.file("checkpoints/ckpt_trial001.ckpt").unlink()
    ckpt2.unlink()
    with pytest.raises(CheckpointError, match=r"has no artifact 'episodes/interaction_episodes.npz' .*; nor a checkpoint to read"):
        stored.episodes()
