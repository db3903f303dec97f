"""The fused time step (plugins.pilco.propagate.FusedStep, hand-derived backward) against plain autograd.

The reference below recomputes a rollout with every stage written as plain differentiable torch
code (trig and squash moments through ``_sin_forward``, both GPs through ``MomentMatchingGP._forward``
with an autograd-only exp-contraction, the glue with indexing and ``cat``) and lets autograd
differentiate J. J and dJ/dtheta of :class:`PolicyObjective` (which uses the fused step) must equal
it to 1e-10 relative, for several controllers, layouts and the mean-only ablation.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from harness.task import SaturatingCost
from plugins.pilco.controllers import LinearController, RBFController, SquashedController
from plugins.pilco.cost import CostMoments
from plugins.pilco.moments import MomentMatchingGP
from plugins.pilco.objective import PolicyObjective
from plugins.pilco.propagate import FusedStep, StateLayout, rollout
from plugins.pilco.trig import _doubled, _sin_forward, squash_maps
from tests.pilco.random_gp import DT, random_posterior

torch.set_num_threads(1)


def _plain_contract(left, right, w_left, w_right, inv_k, workspace):
    """``Q = exp(left right^T)`` and its contractions, plain autograd (no custom Function)."""
    Q = torch.exp(left @ right.mT)
    q_wr = (Q @ w_right[..., None]).squeeze(-1)
    quad = (q_wr * w_left).sum(-1)
    trace = (inv_k * Q[: inv_k.shape[0]]).sum((-2, -1))
    return quad, trace, q_wr


def _gp_moments(posterior, m, S, mean_only):
    return MomentMatchingGP(posterior)._forward(m, S, mean_only, _plain_contract)[0]


def _policy_moments(ctrl, m, S):
    base = ctrl.base if isinstance(ctrl, SquashedController) else ctrl
    if isinstance(base, RBFController):
        mz, sz, cz = _gp_moments(base.posterior(), m, S, True)
    else:
        W, b = base.weight, base.bias
        mz, sz, cz = W @ m + b, W @ S @ W.T, W.T
    if not isinstance(ctrl, SquashedController) or ctrl.kind is None:
        return mz, sz, cz
    A, G = squash_maps(ctrl.u_max, ctrl.kind)
    ms, vs, cs = _sin_forward(mz, sz, A, None)[0]
    return ms @ G.T, G @ vs @ G.T, cz @ cs @ G.T


def _reference_step(m, S, post, ctrl, layout, mean_only, policy_noise=None):
    d = layout.state_dim
    if layout.num_angles:
        mt, vt, ct = _sin_forward(m, S, *_doubled(layout.angle_map))[0]
        ma = torch.cat([m, mt])
        sa = torch.cat([torch.cat([S, S @ ct], 1), torch.cat([(S @ ct).T, vt], 1)], 0)
    else:
        ma, sa = m, S
    pol, mod = layout.policy_index, layout.model_index
    sp = sa[pol][:, pol]
    mu, su, cu = _policy_moments(ctrl, ma[pol], sp if policy_noise is None else sp + policy_noise)
    s_au = sa[:, pol] @ cu
    m_in = torch.cat([ma[mod], mu])
    s_in = torch.cat([torch.cat([sa[mod][:, mod], s_au[mod]], 1), torch.cat([s_au[mod].T, su], 1)], 0)
    md, vd, cd = _gp_moments(post, m_in, s_in, mean_only)
    s_xd = torch.cat([sa[:d, mod], s_au[:d]], 1) @ cd
    s_next = S + vd + s_xd + s_xd.T
    return m + md, 0.5 * (s_next + s_next.T)


def _reference_value_and_grad(obj: PolicyObjective) -> tuple[float, np.ndarray]:
    m, S = obj.init_mean, obj.init_cov
    means, covs = [], []
    for _ in range(obj.horizon):
        m, S = _reference_step(m, S, obj.posterior, obj.controller, obj.layout, obj.mean_only, obj.policy_noise)
        means.append(m)
        covs.append(S)
    J = obj.cost(torch.stack(means), torch.stack(covs))[0].sum()
    grads = torch.autograd.grad(J, obj.params)
    return float(J.detach()), torch.cat([g.reshape(-1) for g in grads]).numpy()


def _objective(case: str) -> PolicyObjective:
    gen = torch.Generator().manual_seed(5)
    if case == "no-angles-linear":
        layout = StateLayout(3, (), (0, 1, 2), (0, 2))
        ctrl = LinearController(torch.tensor([[0.5, -0.7]], dtype=DT), torch.tensor([0.2], dtype=DT))
        cost = SaturatingCost(np.zeros((0, 3)), np.array([[1.0, 0.0, 0.5]]), np.array([0.3]), 1.0)
        post = random_posterior(3, 30, 4, gen)
        return PolicyObjective(ctrl, post, layout, cost, [0.1, -0.2, 0.3], 0.05 * np.eye(3), 12)
    if case == "no-angles-rbf-policy-noise":
        layout = StateLayout(3, (), (0, 1, 2), (0, 2))
        # centres spread enough that the policy's Gram matrix is well conditioned (cond ~ 11): with 6
        # centres in 0.2 I (cond 4.6e4) both computations agree only to ~1e-11, round-off amplified
        # by the Gram matrix, and the bound below depended on the CPU
        base = RBFController.initial(torch.tensor([0.1, 0.3], dtype=DT), 0.5 * torch.eye(2, dtype=DT), 5, 1, 0.7 * torch.ones(2, dtype=DT), gen)
        with torch.no_grad():
            base.targets.mul_(4.0)
        cost = SaturatingCost(np.zeros((0, 3)), np.array([[1.0, 0.0, 0.5]]), np.array([0.3]), 1.0)
        post = random_posterior(3, 30, 4, gen)
        return PolicyObjective(SquashedController(base, [2.0]), post, layout, cost, [0.1, -0.2, 0.3], 0.05 * np.eye(3), 12,
                               policy_noise_std=[0.3, 0.1, 0.2])
    if case == "two-angles-linear":
        layout = StateLayout.with_trig(4, [2, 3])  # inputs [x0, x1, sin x2, sin x3, cos x2, cos x3]
        cost = SaturatingCost(np.array([[0.0, 0, 1, 0], [0, 0, 0, 1]]), np.array([[0, 0, 0, 0, 1.0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 1.0]]), np.array([0.0, 1.0]), 0.7)
        ctrl = SquashedController(LinearController.initial(6, 1, 0.5, gen), [2.0])
        post = random_posterior(4, 40, 7, gen)
        return PolicyObjective(ctrl, post, layout, cost, [0.0, 0.1, 0.4, -0.3], 0.1 * np.eye(4) ** 2, 12)
    layout = StateLayout.with_trig(4, [3])
    cost = SaturatingCost(np.array([[0.0, 0, 0, 1]]), np.array([[1.0, 0, 0, 0, 0.5, 0], [0, 0, 0, 0, 0, -0.5]]), np.array([0.0, 0.5]), 0.5)
    controls = 2 if case == "rbf-two-controls" else 1
    post = random_posterior(4, 40, 5 + controls, gen, fitc=case == "rbf-fitc-mean-only")
    if case.startswith("rbf"):
        base = RBFController.initial(torch.tensor([0.0, 0, 0, 0, 1], dtype=DT), 0.3 * torch.eye(5, dtype=DT), 8, controls, torch.ones(5, dtype=DT), gen)
        with torch.no_grad():
            base.targets.mul_(5.0)
        ctrl = SquashedController(base, [3.0] * controls)
    else:
        ctrl = SquashedController(LinearController.initial(5, 1, 0.5, gen), [2.0], kind="sin")
    mean_only = case == "rbf-fitc-mean-only"
    return PolicyObjective(ctrl, post, layout, cost, [0.0, 0.1, -0.1, 0.3], 0.1 * np.eye(4) ** 2, 15, mean_only=mean_only)


@pytest.mark.parametrize("case", ["rbf", "rbf-two-controls", "rbf-fitc-mean-only", "linear-sin", "no-angles-linear", "two-angles-linear",
                                  "no-angles-rbf-policy-noise"])
def test_fused_objective_equals_plain_autograd(case: str) -> None:
    obj = _objective(case)
    theta = obj.get_flat()
    J, grad = obj(theta)
    J_ref, grad_ref = _reference_value_and_grad(obj)
    assert abs(J - J_ref) <= 1e-12 * abs(J_ref), (J, J_ref)
    rel = np.linalg.norm(grad - grad_ref) / np.linalg.norm(grad_ref)
    assert rel < 1e-10, rel
    assert np.max(np.abs(grad - grad_ref)) < 1e-10 * np.max(np.abs(grad_ref))


def test_policy_noise_changes_the_objective() -> None:
    """The noise case above is not vacuous: without the noise J and dJ differ (and the noise
    covariance lands on the policy's inputs only)."""
    obj = _objective("no-angles-rbf-policy-noise")
    torch.testing.assert_close(obj.policy_noise, torch.diag(torch.tensor([0.3, 0.2], dtype=DT) ** 2))
    J, grad = obj(obj.get_flat())
    obj.policy_noise = None
    J0, grad0 = obj(obj.get_flat())
    assert abs(J - J0) > 1e-3 * abs(J0) and np.linalg.norm(grad - grad0) > 1e-2 * np.linalg.norm(grad0)


def _graph_nodes(tensor: torch.Tensor) -> list[str]:
    """Names of all autograd nodes reachable from ``tensor``."""
    seen, stack, names = set(), [tensor.grad_fn], []
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        names.append(type(node).__name__)
        stack.extend(next_node for next_node, _ in node.next_functions)
    return names


def test_the_objective_uses_the_fused_step() -> None:
    """The comparison above is not vacuous: the rollout is one fused autograd node (and has no
    per-operator nodes of the moment computations)."""
    obj = _objective("rbf")
    means, _ = rollout(obj.init_mean, obj.init_cov, 3, obj.dynamics, obj.controller, obj.layout)
    names = _graph_nodes(means)
    assert names.count("_RolloutFunctionBackward") == 1
    assert "_MomentsFunctionBackward" not in names and "_SinMomentsBackward" not in names


def test_fused_step_without_gradients_matches() -> None:
    """The no-autograd forward gives the same states as the graph-recording one."""
    obj = _objective("rbf")
    step = FusedStep(obj.dynamics, obj.controller.moment_map(), obj.layout, False)
    m1, S1 = step(obj.init_mean, obj.init_cov)
    with torch.no_grad():
        m2, S2 = step(obj.init_mean, obj.init_cov)
    assert m1.grad_fn is not None and torch.equal(m1.detach(), m2) and torch.equal(S1.detach(), S2)


def test_gradients_wrt_the_initial_distribution() -> None:
    """d(loss)/d(m0, S0) through a fused rollout equals the plain-autograd reference."""
    obj = _objective("rbf-two-controls")
    weights = torch.randn(4, generator=torch.Generator().manual_seed(3), dtype=DT)
    results = []
    for fused in (True, False):
        m, S = obj.init_mean.clone().requires_grad_(), obj.init_cov.clone().requires_grad_()
        leaves = (m, S)
        if fused:
            means, covs = rollout(m, S, 6, obj.dynamics, obj.controller, obj.layout)
        else:
            steps = [(m, S)]
            for _ in range(6):
                steps.append(_reference_step(*steps[-1], obj.posterior, obj.controller, obj.layout, False))
            means, covs = torch.stack([s[0] for s in steps]), torch.stack([s[1] for s in steps])
        loss = (means[1:] @ weights).sum() + (covs[2:] ** 2).sum()
        results.append(torch.autograd.grad(loss, leaves))
    for fused, ref in zip(*results):
        assert torch.allclose(fused, ref, rtol=1e-10, atol=1e-13)


def test_work_buffers_are_usable_outside_inference_mode() -> None:
    """The fused rollout runs in inference mode; the GP's reused work buffers must still be
    ordinary tensors that the autograd path can write into afterwards."""
    obj = _objective("rbf")
    obj(obj.get_flat())
    m_in = torch.zeros(obj.posterior.input_dim, dtype=DT, requires_grad=True)
    _, V, _ = obj.dynamics.predict(m_in, 0.1 * torch.eye(obj.posterior.input_dim, dtype=DT))
    assert torch.isfinite(torch.autograd.grad(V.sum(), m_in)[0]).all()
