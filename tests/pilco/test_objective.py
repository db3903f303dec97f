"""J(theta) and dJ/dtheta (plugins.pilco.objective): central finite differences, consistency, L-BFGS-B."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
import torch

from harness.task import SaturatingCost
from plugins.pilco.controllers import LinearController, RBFController, SquashedController
from plugins.pilco.cost import CostMoments
from plugins.pilco.objective import PolicyObjective
from plugins.pilco.propagate import StateLayout, rollout
from tests.pilco.random_gp import DT, pendulum_posterior

torch.set_num_threads(1)
LENGTH = 1.0


def pendulum_cost() -> SaturatingCost:
    """Tip of a 1 m pendulum (state [thetadot, theta]) from its hanging position (0, -l): a regulator
    task whose cost is not saturated near the initial state, so that gradients are informative."""
    return SaturatingCost(np.array([[0.0, 1.0]]), np.array([[0, 0, LENGTH, 0], [0, 0, 0, -LENGTH]]), np.array([0.0, -LENGTH]), 0.5)


def _objective(kind: str, mean_only: bool = False, horizon: int = 10) -> PolicyObjective:
    gen = torch.Generator().manual_seed(11)
    post = pendulum_posterior(80, gen)
    layout = StateLayout.with_trig(2, [1])
    if kind == "rbf":
        base = RBFController.initial(torch.tensor([0.0, 0.0, 1.0], dtype=DT), 0.2 * torch.eye(3, dtype=DT), 5, 1, torch.ones(3, dtype=DT), gen)
        with torch.no_grad():
            base.targets.mul_(5.0)
    else:
        base = LinearController(torch.tensor([[0.8, -1.5, 0.4]], dtype=DT), torch.tensor([0.3], dtype=DT))
    ctrl = SquashedController(base, [2.0])
    return PolicyObjective(ctrl, post, layout, pendulum_cost(), [0.0, 0.8], np.diag([0.2, 0.2]) ** 2, horizon, mean_only=mean_only)


def _central_differences(obj: PolicyObjective, theta: np.ndarray, eps: float) -> np.ndarray:
    grad = np.zeros_like(theta)
    for i in range(theta.size):
        step = np.zeros_like(theta)
        step[i] = eps
        obj.set_flat(theta + step)
        with torch.no_grad():
            jp = float(obj.value())
        obj.set_flat(theta - step)
        with torch.no_grad():
            jm = float(obj.value())
        grad[i] = (jp - jm) / (2 * eps)
    obj.set_flat(theta)
    return grad


@pytest.mark.parametrize("kind,mean_only", [("rbf", False), ("linear", False), ("rbf", True)])
def test_gradient_matches_central_differences(kind: str, mean_only: bool) -> None:
    obj = _objective(kind, mean_only)
    theta = obj.get_flat()
    J, grad = obj(theta)
    fd = _central_differences(obj, theta, eps=1e-6)
    rel = np.linalg.norm(grad - fd) / np.linalg.norm(fd)
    assert rel < 1e-5, rel
    # per coordinate, relative to the largest entry
    assert np.max(np.abs(grad - fd)) < 1e-5 * np.max(np.abs(fd))
    assert np.all(np.isfinite(grad)) and 0 < J < obj.horizon


def test_flat_roundtrip_and_parameter_order() -> None:
    obj = _objective("rbf")
    theta = obj.get_flat()
    assert theta.shape == (5 * 3 + 5 + 3,) == (obj.num_params,)
    obj.set_flat(theta + 1.0)
    assert np.allclose(obj.get_flat(), theta + 1.0)
    ctrl = obj.controller
    assert np.allclose(ctrl.base.centres.detach().numpy().ravel(), theta[:15] + 1.0)
    with pytest.raises(ValueError):
        obj.set_flat(theta[:-1])


def test_value_is_sum_of_predicted_costs() -> None:
    """J = sum_{t=1..H} E[c(x_t)] from the rollout's distributions (x_0 not costed)."""
    obj = _objective("linear", horizon=8)
    mean, std = obj.predicted_costs()
    assert mean.shape == std.shape == (8,)
    with torch.no_grad():
        J = float(obj.value())
        means, covs = rollout(obj.init_mean, obj.init_cov, 8, obj.posterior, obj.controller, obj.layout)
        e, v = CostMoments(pendulum_cost())(means, covs)
    assert abs(J - mean.sum()) < 1e-12
    assert np.allclose(mean, e[1:].numpy(), atol=1e-14) and np.allclose(std, v[1:].sqrt().numpy(), atol=1e-14)
    assert np.all((mean > 0) & (mean < 1) & (std >= 0))


def test_lbfgsb_improves_the_policy() -> None:
    obj = _objective("rbf", horizon=10)
    theta0 = obj.get_flat()
    J0, _ = obj(theta0)
    result = scipy.optimize.minimize(obj, theta0, jac=True, method="L-BFGS-B", options={"maxiter": 15})
    assert result.fun < J0 - 0.05
    assert np.allclose(obj.get_flat(), result.x) or obj(result.x)[0] == pytest.approx(result.fun)


def test_model_posterior_is_detached() -> None:
    gen = torch.Generator().manual_seed(12)
    post = pendulum_posterior(30, gen)
    post.beta.requires_grad_(True)
    ctrl = SquashedController(LinearController.initial(3, 1, generator=gen), [2.0])
    obj = PolicyObjective(ctrl, post, StateLayout.with_trig(2, [1]), pendulum_cost(), [0.0, 0.0], 0.01 * np.eye(2), 5)
    assert not obj.posterior.beta.requires_grad
    J, grad = obj(obj.get_flat())
    assert post.beta.grad is None and grad.shape == (4,)
