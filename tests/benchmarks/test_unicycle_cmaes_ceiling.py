"""benchmarks/unicycle_cmaes_ceiling.py: the numpy controller its search applies is PILCO's linear policy (to
rounding) and, with its bumps at 0, exactly the linear policy it starts from; the linear search writes the
parameters the linear+RBF search starts from."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import unicycle_falls
from benchmarks.unicycle_cmaes_ceiling import ControllerClass, bumps_around, main, policy_of, theta_of
from harness.evaluation import Evaluator
from plugins.pilco.policy import linear_policy_from_gain
from tasks.unicycle import Unicycle
from tasks.unicycle_lqr import riding_lqr


@pytest.fixture(scope="module")
def task() -> Unicycle:
    return Unicycle(init="paper")


def test_the_numpy_controller_is_pilcos_linear_policy_and_its_bumps_add_to_it(task):
    theta = theta_of(linear_policy_from_gain(task.spec, *riding_lqr(task, 1.5)))
    rng = np.random.default_rng(1)
    observations = rng.normal(scale=0.5, size=(50, task.spec.state_dim))
    u_max = np.asarray(task.spec.action_high, dtype=np.float64)
    linear = ControllerClass(u_max, task.spec.state_dim, np.zeros((0, task.spec.state_dim)), np.ones(task.spec.state_dim))
    torch_policy = policy_of(task, theta)
    for x in observations:
        np.testing.assert_allclose(linear.controller(theta)(x), torch_policy(x), rtol=1e-12, atol=1e-12)
        assert np.all(np.abs(linear.controller(theta)(x)) <= u_max)

    centres, inv_length = bumps_around(task, theta, 7, 1.0)
    assert centres.shape == (7, task.spec.state_dim) and np.all(inv_length > 0)
    bumps = ControllerClass(u_max, task.spec.state_dim, centres, inv_length)
    assert bumps.size == theta.size + 14
    at_zero = bumps.controller(np.concatenate([theta, np.zeros(14)]))
    for x in observations[:5]:
        assert np.array_equal(at_zero(x), linear.controller(theta)(x))
    # one bump's target moves the pre-squash signal by exactly that bump's value at x (an independent sum)
    targets = np.zeros((7, 2))
    targets[3] = [0.1, -0.2]
    moved = bumps.controller(np.concatenate([theta, targets.ravel()]))
    x = centres[3] + 0.1
    z = theta[:20].reshape(2, 10) @ x + theta[20:] + targets[3] * np.exp(-0.5 * np.sum(((x - centres[3]) * inv_length) ** 2))
    np.testing.assert_allclose(moved(x), u_max * (9 * np.sin(z) + np.sin(3 * z)) / 8, rtol=1e-12)
    # and the evaluator scores the numpy controller as it scores PILCO's policy
    numpy_result = Evaluator(task, n_episodes=3, seed=7)(linear.controller(theta))
    torch_result = Evaluator(task, n_episodes=3, seed=7)(torch_policy)
    assert numpy_result.success_rate == torch_result.success_rate
    assert numpy_result.mean_cost == pytest.approx(torch_result.mean_cost, rel=1e-9)


def test_the_linear_search_writes_what_the_rbf_search_starts_from(tmp_path, capsys):
    linear_md = tmp_path / "linear.md"
    main(["--generations", "1", "--episodes", "2", "--popsize", "4", "--held-out", "3", "--out", str(linear_md)])
    saved = np.load(tmp_path / "linear.npz")
    assert saved["mean"].shape == (22,) and "| CMA-ES: final mean |" in linear_md.read_text()

    rbf_md = tmp_path / "rbf.md"
    main(["--controller", "linear+rbf", "--start", str(tmp_path / "linear.npz"), "--centres", "5", "--target-scale", "0.5", "--generations", "1",
          "--episodes", "2", "--popsize", "4", "--held-out", "3", "--out", str(rbf_md)])
    rbf = np.load(tmp_path / "rbf.npz")
    assert rbf["start"].shape == (32,) and np.array_equal(rbf["start"][:22], saved["mean"]) and not rbf["start"][22:].any()
    assert rbf["centres"].shape == (5, 10) and "5 Gaussian bumps" in rbf_md.read_text() and "targets in units of 0.5" in rbf_md.read_text()

    falls_md = tmp_path / "falls.md"
    unicycle_falls.main(["--policy", str(tmp_path / "rbf.npz"), "--episodes", "6", "--out", str(falls_md)])
    text = falls_md.read_text()
    assert "6 held-out episodes" in text and len([line for line in text.splitlines() if line.startswith("| ") and "[" in line]) == 10

    with pytest.raises(SystemExit):
        main(["--controller", "linear+rbf", "--start", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x.md")])
    assert "run the linear search first" in capsys.readouterr().err
