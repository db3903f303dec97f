"""benchmarks/planning_basis_check.py reads a PILCO run's checkpoint back into the model and the policy the run
had (the J it reports for the whole model is the run's own J_after) and scores every reduced basis."""

from __future__ import annotations

import pytest

from benchmarks.planning_basis_check import CheckpointedRun, main
from harness.runner import RunConfig, run
from harness.tracking import MemoryTracker

OPTIONS = {"num_centres": "5", "policy_max_evaluations": "15", "gp_max_evals": "40", "plots": "false", "sample_particles": "0",
           "sparse_threshold": "20", "num_pseudo": "12", "gp_fitc_evals": "5"}


def test_planning_basis_check_on_a_tiny_sparse_run(tmp_path):
    tracker = MemoryTracker()
    run(RunConfig("pilco", "cartpole", seed=0, learner_options=OPTIONS, task_options={"horizon": 15}, max_trials=3,
                  eval_episodes=1), tracker=tracker)
    checkpoint = tracker.root / "checkpoints" / "ckpt_trial002.ckpt"
    loaded = CheckpointedRun(checkpoint)
    assert loaded.trial == 2 and len(loaded.episodes) == 2 and loaded.model.sparse  # 30 points > 20: FITC on 12
    out = tmp_path / "check.md"
    main(["--checkpoints", str(checkpoint), "--test", f"{checkpoint}:0-1", "--basis", "8", "30", "--episodes", "2",
          "--refine", "3", "--search", "3", "--out", str(out)])
    rows = [line for line in out.read_text().splitlines() if line.startswith("| `")]
    assert [row.split(" | ")[4] for row in rows] == ["all 12 (the model)", "8, greedy", "8, greedy + 3 FITC evaluations",
                                                     "8, random"]
    J_whole = float(rows[0].split(" | ")[7])
    assert J_whole == pytest.approx(dict(tracker.metrics["J_after"])[2], abs=0.005)  # the run's own J of that policy
