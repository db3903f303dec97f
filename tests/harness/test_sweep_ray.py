"""`harness sweep --executor ray`: embedded Ray gives the same runs as the local pool."""

from __future__ import annotations

import pytest

from harness.sweep import SweepSpec, run_sweep
from tests.harness.sweep_site import check_steps_cells, plugin_paths, plugins  # noqa: F401 (fixtures)


def test_ray_sweep_gives_the_same_results(plugins, mlflow_uri):
    pytest.importorskip("ray")
    spec = SweepSpec(("sweep-steps", "random"), ("sweep-toy",), (2, 3, 4), max_trials=2, eval_episodes=2)
    result = run_sweep(spec, mlflow_uri, executor="ray", workers=2)
    assert [o.status for o in result.outcomes] == ["finished"] * 6
    check_steps_cells(mlflow_uri, result)
    assert not any(o.solved for o in result.outcomes if o.cell.learner == "random")
    again = run_sweep(spec, mlflow_uri, executor="ray", workers=2)  # resumes: nothing left to run, Ray not started
    assert [o.status for o in again.outcomes] == ["skipped"] * 6 and again.parent_run_id == result.parent_run_id
