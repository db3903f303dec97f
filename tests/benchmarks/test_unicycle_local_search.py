"""benchmarks/unicycle_local_search.py: its start is PILCO's initial linear policy, the end of its segment the
riding LQR as PILCO's controller, and a short run writes one row per start and search."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.unicycle_cmaes_ceiling import ControllerClass, policy_of
from benchmarks.unicycle_local_search import LQR_SPEED, lqr_theta, main, pilco_start
from harness.evaluation import Evaluator
from plugins.pilco.policy import initial_controller, layout_for, linear_policy_from_gain
from plugins.pilco.presets import PRESETS
from tasks.unicycle import Unicycle
from tasks.unicycle_lqr import riding_lqr


@pytest.fixture(scope="module")
def task() -> Unicycle:
    return Unicycle(init="code")


def test_the_start_is_pilcos_initial_policy_and_the_segment_ends_at_the_riding_lqr(task):
    import torch

    theta = pilco_start(3, task)
    assert theta.shape == (22,) and np.all(theta[-2:] == 0) and 0.003 < theta[:-2].std() < 0.03
    preset = PRESETS["unicycle"]
    pilco = initial_controller(task.spec, preset, layout_for(task.spec, preset), "trapezoid", torch.Generator().manual_seed(3))
    assert np.array_equal(theta, np.concatenate([pilco.base.weight.detach().numpy().ravel(), pilco.base.bias.detach().numpy()]))
    x = np.random.default_rng(0).normal(scale=0.3, size=task.spec.state_dim)
    assert np.all(np.abs(policy_of(task, theta)(x)) <= np.asarray(task.spec.action_high))

    u_max = np.asarray(task.spec.action_high, dtype=np.float64)
    family = ControllerClass(u_max, task.spec.state_dim, np.zeros((0, task.spec.state_dim)), np.ones(task.spec.state_dim))
    lqr = linear_policy_from_gain(task.spec, *riding_lqr(task, LQR_SPEED))
    ours = Evaluator(task, n_episodes=3, seed=11)(family.controller(lqr_theta(task)))
    reference = Evaluator(task, n_episodes=3, seed=11)(lqr)
    assert ours.mean_cost == pytest.approx(reference.mean_cost, rel=1e-9) and ours.success_rate == reference.success_rate


def test_a_short_run_writes_a_row_per_start_and_search(tmp_path):
    out = tmp_path / "search.md"
    main(["--starts", "2", "--episodes", "2", "--iterations", "1", "--generations", "1", "--segment", "3",
          "--held-out", "2", "--out", str(out)])
    text = out.read_text()
    assert sum(line.startswith("| 0 | ") or line.startswith("| 1 | ") for line in text.splitlines()) == 4
    assert "| 0.5 |" in text and "| 1.0 |" in text and "riding LQR" in text
