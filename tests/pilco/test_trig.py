"""Sine/cosine moments and squashing (plugins.pilco.trig) against Monte Carlo (>= 1e5 samples)."""

from __future__ import annotations

import math

import pytest
import torch

from plugins.pilco.trig import _sin_forward, augment_trig, sin_moments, squash, squash_moments, trig_moments
from tests.pilco.random_gp import DT, mc_moments, random_gaussian

torch.set_num_threads(1)
NUM_SAMPLES = 200_000
SIGMAS = 5.0


def _samples(m, S, gen):
    return m + torch.randn(NUM_SAMPLES, m.shape[0], generator=gen, dtype=DT) @ torch.linalg.cholesky(S).T


def _assert_mc(mean, cov, cross, S, x, y):
    mc_mean, mean_se, mc_cov, cov_se, mc_cross, cross_se = mc_moments(y, x)
    assert torch.all((mean - mc_mean).abs() <= SIGMAS * mean_se + 1e-12), (mean, mc_mean)
    assert torch.all((cov - mc_cov).abs() <= SIGMAS * cov_se + 1e-12), (cov, mc_cov)
    assert torch.all((S @ cross - mc_cross).abs() <= SIGMAS * cross_se + 1e-12), (S @ cross, mc_cross)


def test_trig_moments_linear_map() -> None:
    """[sin(Ax), cos(Ax)] with a general A (K=2, D=3), large variances (wrapping matters)."""
    gen = torch.Generator().manual_seed(1)
    m, S = random_gaussian(3, gen, scale=1.5)
    A = torch.tensor([[1.0, 0.0, 0.5], [0.0, -1.0, 1.0]], dtype=DT)
    x = _samples(m, S, gen)
    phi = x @ A.T
    y = torch.cat([torch.sin(phi), torch.cos(phi)], dim=1)
    _assert_mc(*trig_moments(m, S, A), S, x, y)


def test_sin_moments_with_offset_and_small_variance() -> None:
    """Small variances exercise expm1 (cov ~ v): relative accuracy, not only absolute."""
    gen = torch.Generator().manual_seed(2)
    m = torch.tensor([0.3, -2.0], dtype=DT)
    S = torch.tensor([[1e-8, 5e-9], [5e-9, 2e-8]], dtype=DT)
    A = torch.eye(2, dtype=DT)
    b = torch.tensor([0.1, 1.0], dtype=DT)
    mean, cov, cross = sin_moments(m, S, A, b)
    # first-order (delta method) is exact to O(S^2) here
    g = torch.cos(m + b)
    assert torch.allclose(cov, g[:, None] * S * g[None, :], rtol=1e-6)
    assert torch.allclose(mean, torch.sin(m + b) * torch.exp(-0.5 * torch.diagonal(S)), rtol=1e-14)
    x = _samples(m, 1e6 * S, gen)
    y = torch.sin(x @ A.T + b)
    _assert_mc(*sin_moments(m, 1e6 * S, A, b), 1e6 * S, x, y)


def test_augment_trig_joint() -> None:
    """The joint of [x, sin(x_3), cos(x_3)] (the cart-pole augmentation) vs MC."""
    gen = torch.Generator().manual_seed(3)
    m, S = random_gaussian(4, gen, scale=0.8)
    A = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=DT)
    mean, cov = augment_trig(m, S, A)
    x = _samples(m, S, gen)
    a = torch.cat([x, torch.sin(x[:, 3:]), torch.cos(x[:, 3:])], dim=1)
    mc_mean, mean_se, mc_cov, cov_se, _, _ = mc_moments(a, x)
    assert torch.all((mean - mc_mean).abs() <= SIGMAS * mean_se + 1e-12)
    assert torch.all((cov - mc_cov).abs() <= SIGMAS * cov_se + 1e-12)
    assert torch.equal(cov[:4, :4], S)
    assert torch.allclose(cov, cov.T, atol=0)


def test_batched_equals_single() -> None:
    gen = torch.Generator().manual_seed(4)
    pairs = [random_gaussian(3, gen) for _ in range(4)]
    ms, Ss = torch.stack([p[0] for p in pairs]), torch.stack([p[1] for p in pairs])
    A = torch.tensor([[1.0, 2.0, 0.0]], dtype=DT)
    bm, bc = augment_trig(ms, Ss, A)
    for i, (m, S) in enumerate(pairs):
        m1, c1 = augment_trig(m, S, A)
        assert torch.allclose(bm[i], m1, atol=1e-15) and torch.allclose(bc[i], c1, atol=1e-15)


@pytest.mark.parametrize("kind", ["trapezoid", "sin"])
def test_squash_moments(kind: str) -> None:
    gen = torch.Generator().manual_seed(5)
    m = torch.tensor([0.4, -1.1], dtype=DT)
    L = torch.tensor([[0.9, 0.0], [0.5, 0.6]], dtype=DT)
    S = L @ L.T
    u_max = torch.tensor([10.0, 2.5], dtype=DT)
    z = _samples(m, S, gen)
    u = squash(z, u_max, kind)
    _assert_mc(*squash_moments(m, S, u_max, kind), S, z, u)


def test_squash_bounds_and_shape() -> None:
    u_max = torch.tensor([3.0], dtype=DT)
    z = torch.linspace(-10, 10, 20001, dtype=DT)[:, None]
    for kind in ("trapezoid", "sin"):
        u = squash(z, u_max, kind)
        assert u.abs().max() <= 3.0 + 1e-12
        assert math.isclose(float(u.max()), 3.0, rel_tol=1e-6)
    # trapezoid: (9 sin z + sin 3z)/8, flat top at z = pi/2
    top = squash(torch.tensor([[math.pi / 2]], dtype=DT), u_max, "trapezoid")
    assert torch.allclose(top, u_max)
    with pytest.raises(ValueError):
        squash(z, u_max, "tanh")


def sin_gradients(m, S, A, b, weights):
    """Gradients wrt ``(m, S)`` of ``sum(w * moment)`` over the sin moments, by the hand-derived
    backward and by autograd through the forward: ``zip(hand, autograd)`` pairs."""
    results = []
    for hand in (True, False):
        mm, SS = m.clone().requires_grad_(), S.clone().requires_grad_()
        out = sin_moments(mm, SS, A, b) if hand else _sin_forward(mm, SS, A, b)[0]
        loss = sum((o * w).sum() for o, w in zip(out, weights))
        results.append(torch.autograd.grad(loss, (mm, SS)))
    return zip(*results)


@pytest.mark.parametrize("batch", [(), (3,)])
def test_hand_derived_backward_equals_autograd(batch) -> None:
    gen = torch.Generator().manual_seed(6)
    A = torch.tensor([[1.0, 0.0, 0.5], [0.0, -1.0, 1.0], [1.0, 0.0, 0.5]], dtype=DT)
    b = torch.tensor([0.0, 0.3, 0.5 * math.pi], dtype=DT)
    L = torch.randn(*batch, 3, 3, generator=gen, dtype=DT) * 0.6
    S = L @ L.mT
    m = torch.randn(*batch, 3, generator=gen, dtype=DT)
    weights = [torch.randn(*batch, *shape, generator=gen, dtype=DT) for shape in ((3,), (3, 3), (3, 3))]
    for hand, auto in sin_gradients(m, S, A, b, weights):
        assert torch.allclose(hand, auto, rtol=1e-12, atol=1e-14)
    fn = lambda mm, SS: sin_moments(mm, SS, A, b)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (m.clone().requires_grad_(), S.clone().requires_grad_()))
