"""GP prediction at uncertain inputs (plugins.pilco.moments) against independent computations.

* Monte Carlo (>= 1e5 samples): sample x ~ N(m, S), evaluate the posterior mean and latent variance
  at every sample; E[f] = mean of means, Cov[f] = cov of means + diag(mean of variances) (without
  the variance term for mean_only), cov[x, f] = cov of (x, means). Tolerance: 5 standard errors.
* A naive transcription of the paper's eq. (22) (explicit loops over i, j on a tiny problem), to
  machine precision: checks the expanded bilinear form.
* The deterministic-input limit S -> 0.
* gradcheck of the hand-written backward pass.
"""

from __future__ import annotations

import pytest
import torch

from plugins.pilco.kernels import se_ard
from plugins.pilco.moments import MomentMatchingGP, _ExpBilinearContraction, _Workspace, predict_uncertain
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.sparse import fitc_posterior
from tests.pilco.random_gp import DT, gp_mean_var, mc_moments, random_gaussian, random_posterior

torch.set_num_threads(1)
NUM_SAMPLES = 100_000
SIGMAS = 5.0


def _mc_check(post: GPPosterior, m: torch.Tensor, S: torch.Tensor, gen: torch.Generator, chol=None) -> None:
    """Both mean_only settings against one Monte Carlo sample."""
    chol = torch.linalg.cholesky(S) if chol is None else chol
    x = m + torch.randn(NUM_SAMPLES, m.shape[0], generator=gen, dtype=DT) @ chol.T
    f, var = gp_mean_var(post, x)
    for mean_only in (False, True):
        M, V, C = predict_uncertain(post, m, S, mean_only=mean_only)
        mean, mean_se, cov, cov_se, cross, cross_se = mc_moments(f, x, None if mean_only else var)
        assert torch.all((M - mean).abs() <= SIGMAS * mean_se + 1e-12), (mean_only, M, mean)
        assert torch.all((V - cov).abs() <= SIGMAS * cov_se + 1e-12), (mean_only, V, cov)
        assert torch.all((S @ C - cross).abs() <= SIGMAS * cross_se + 1e-12), (mean_only, S @ C, cross)
        assert torch.allclose(V, V.T, atol=1e-14)


@pytest.mark.parametrize("num_outputs", [1, 2, 3, 4, 5, 6])
def test_full_gp_matches_monte_carlo(num_outputs: int) -> None:
    gen = torch.Generator().manual_seed(100 + num_outputs)
    dim = 2 + num_outputs % 4
    post = random_posterior(num_outputs, 25, dim, gen)
    m, S = random_gaussian(dim, gen)
    _mc_check(post, m, S, gen)


@pytest.mark.parametrize("num_outputs", [2, 4])
def test_fitc_shaped_posterior_matches_monte_carlo(num_outputs: int) -> None:
    """inv_k = Kmm^-1 - (Kmm + B)^-1 (not the inverse of a Gram matrix), random beta."""
    gen = torch.Generator().manual_seed(200 + num_outputs)
    post = random_posterior(num_outputs, 20, 3, gen, fitc=True)
    m, S = random_gaussian(3, gen, scale=0.8)
    _mc_check(post, m, S, gen)


def test_real_fitc_posterior_matches_monte_carlo() -> None:
    """A FITC posterior from plugins.pilco.sparse (pseudo-inputs as basis)."""
    gen = torch.Generator().manual_seed(300)
    X = torch.randn(120, 3, generator=gen, dtype=DT)
    Y = torch.stack([torch.sin(X[:, 0]) + 0.3 * X[:, 1], torch.cos(X[:, 1] * X[:, 2])], dim=1)
    Y = Y + 0.05 * torch.randn(Y.shape, generator=gen, dtype=DT)
    Z = X[:15].clone()
    log_ell = torch.log(torch.tensor([[1.0, 1.2, 0.9], [0.8, 1.0, 1.1]], dtype=DT))
    post = fitc_posterior(X, Y, Z, log_ell, torch.log(torch.tensor([1.0, 0.8], dtype=DT)), torch.log(torch.tensor([0.05, 0.05], dtype=DT)))
    m, S = random_gaussian(3, gen, scale=0.7)
    _mc_check(post, m, S, gen)


def test_singular_input_covariance() -> None:
    """Rank-deficient S (e.g. a deterministic control in the joint (x, u)) needs no S^-1."""
    gen = torch.Generator().manual_seed(400)
    post = random_posterior(3, 20, 4, gen)
    m, _ = random_gaussian(4, gen)
    L = torch.randn(4, 2, generator=gen, dtype=DT) * 0.4
    S = L @ L.T  # rank 2
    x = m + torch.randn(NUM_SAMPLES, 2, generator=gen, dtype=DT) @ L.T
    f, var = gp_mean_var(post, x)
    M, V, C = predict_uncertain(post, m, S)
    mean, mean_se, cov, cov_se, cross, cross_se = mc_moments(f, x, var)
    assert torch.all((M - mean).abs() <= SIGMAS * mean_se)
    assert torch.all((V - cov).abs() <= SIGMAS * cov_se)
    assert torch.all((S @ C - cross).abs() <= SIGMAS * cross_se + 1e-12)


def test_naive_eq22_transcription() -> None:
    """Q_ij from eq. (22) with explicit loops (z_ij, R, |R| as written) vs the expanded form."""
    gen = torch.Generator().manual_seed(500)
    E, n, d = 3, 6, 3
    post = random_posterior(E, n, d, gen)
    m, S = random_gaussian(d, gen)
    M, V, _ = predict_uncertain(post, m, S)
    lam_inv = torch.exp(-2 * post.log_ell)  # (E, d)
    alpha2 = torch.exp(2 * post.log_alpha)
    nu = post.inputs - m
    k_at_mean = se_ard(post.inputs, m[None], post.log_ell, post.log_alpha)[:, :, 0]  # (E, n)
    V_naive = torch.zeros(E, E, dtype=DT)
    for a in range(E):
        for b in range(E):
            R = S @ torch.diag(lam_inv[a] + lam_inv[b]) + torch.eye(d, dtype=DT)
            Q = torch.zeros(n, n, dtype=DT)
            for i in range(n):
                for j in range(n):
                    z = lam_inv[a] * nu[i] + lam_inv[b] * nu[j]
                    Q[i, j] = k_at_mean[a, i] * k_at_mean[b, j] / torch.sqrt(torch.det(R)) * torch.exp(0.5 * z @ torch.linalg.solve(R, S) @ z)
            V_naive[a, b] = post.beta[a] @ Q @ post.beta[b] - M[a] * M[b]
            if a == b:
                V_naive[a, b] += alpha2[a] - torch.trace(post.inv_k[a] @ Q)
    # mean (eq. 14-15) written out
    M_naive = torch.stack([
        alpha2[a] / torch.sqrt(torch.det(S @ torch.diag(lam_inv[a]) + torch.eye(d, dtype=DT)))
        * (post.beta[a] * torch.exp(-0.5 * ((nu @ torch.linalg.inv(S + torch.diag(1 / lam_inv[a]))) * nu).sum(-1))).sum()
        for a in range(E)
    ])
    assert torch.allclose(M, M_naive, rtol=1e-12, atol=1e-13)
    assert torch.allclose(V, V_naive, rtol=1e-10, atol=1e-12)


def test_deterministic_limit() -> None:
    """S -> 0: mean -> posterior mean at m, variance -> diag(latent variance at m); C -> gradient."""
    gen = torch.Generator().manual_seed(600)
    post = random_posterior(4, 30, 5, gen)
    m, _ = random_gaussian(5, gen)
    S = 1e-10 * torch.eye(5, dtype=DT)
    M, V, C = predict_uncertain(post, m, S)
    mean, var = gp_mean_var(post, m[None])
    assert torch.allclose(M, mean[0], atol=1e-8)
    assert torch.allclose(V, torch.diag(var[0]), atol=1e-8)
    # S^-1 cov[x, f] -> d mean / dx (Stein / first-order expansion)
    mx = m.clone().requires_grad_()
    jac = torch.autograd.functional.jacobian(lambda z: gp_mean_var(post, z[None])[0][0], mx)  # (E, d)
    assert torch.allclose(C, jac.T, atol=1e-6)
    M0, V0, _ = predict_uncertain(post, m, S, mean_only=True)
    assert torch.allclose(V0, torch.zeros_like(V0), atol=1e-8)


def test_mean_only_drops_exactly_the_model_uncertainty() -> None:
    gen = torch.Generator().manual_seed(700)
    post = random_posterior(3, 25, 3, gen)
    m, S = random_gaussian(3, gen)
    gp = MomentMatchingGP(post)
    M1, V1, C1 = gp.predict(m, S)
    M0, V0, C0 = gp.predict(m, S, mean_only=True)
    assert torch.equal(M1, M0) and torch.equal(C1, C0)
    diff = V1 - V0
    assert torch.allclose(diff, torch.diag(torch.diagonal(diff)), atol=1e-14)
    assert torch.all(torch.diagonal(diff) > 0)


def test_contraction_backward_gradcheck() -> None:
    gen = torch.Generator().manual_seed(800)
    P, n, k, e = 3, 5, 4, 2
    left = (0.3 * torch.randn(P, n, k, generator=gen, dtype=DT)).requires_grad_()
    right = (0.3 * torch.randn(P, n, k, generator=gen, dtype=DT)).requires_grad_()
    wl = torch.randn(P, n, generator=gen, dtype=DT).requires_grad_()
    wr = torch.randn(P, n, generator=gen, dtype=DT).requires_grad_()
    A = torch.randn(e, n, n, generator=gen, dtype=DT)
    inv_k = (A + A.mT).requires_grad_()
    workspace = _Workspace()
    fn = lambda *args: _ExpBilinearContraction.apply(*args, workspace)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (left, right, wl, wr, inv_k))


def test_backward_recomputes_q_after_the_workspace_is_reused() -> None:
    """Several predictions share one workspace before any backward pass (as a rollout does):
    each backward recomputes its own Q, so the gradients equal those of separate evaluations."""
    gen = torch.Generator().manual_seed(801)
    post = random_posterior(2, 8, 3, gen)
    gp = MomentMatchingGP(post)
    m, S = random_gaussian(3, gen)
    m.requires_grad_()
    _, V1, _ = gp.predict(m, S)
    _, V2, _ = gp.predict(m + 0.1, 0.5 * S)
    g1, g2 = torch.autograd.grad(V1.sum(), m), torch.autograd.grad(V2.sum(), m)
    f1 = torch.autograd.grad(MomentMatchingGP(post).predict(m, S)[1].sum(), m)
    f2 = torch.autograd.grad(MomentMatchingGP(post).predict(m + 0.1, 0.5 * S)[1].sum(), m)
    assert torch.equal(g1[0], f1[0]) and torch.equal(g2[0], f2[0])
    assert not torch.allclose(g1[0], g2[0])


@pytest.mark.parametrize("mean_only", [False, True])
def test_predict_gradcheck(mean_only: bool) -> None:
    """Gradients wrt m, S, basis inputs, beta, length-scales and signal variances."""
    gen = torch.Generator().manual_seed(900)
    post = random_posterior(2, 6, 3, gen)
    m, S = random_gaussian(3, gen)

    def fn(m, S, X, beta, log_ell, log_alpha):
        p = GPPosterior(X, beta, post.inv_k, log_ell, log_alpha, post.log_sigma)
        return predict_uncertain(p, m, 0.5 * (S + S.T), mean_only=mean_only)

    args = [t.clone().requires_grad_() for t in (m, S, post.inputs, post.beta, post.log_ell, post.log_alpha)]
    assert torch.autograd.gradcheck(fn, args)


@pytest.mark.parametrize("num_outputs,mean_only", [(1, False), (1, True), (3, False), (4, True), (5, False)])
@pytest.mark.parametrize("posterior_grad", [False, True])
def test_hand_derived_backward_equals_autograd(num_outputs: int, mean_only: bool, posterior_grad: bool) -> None:
    """The hand-derived backward equals autograd through the same forward, for gradients wrt
    (m, S) and (with posterior_grad) wrt the posterior's inputs, beta, inv_k and hyperparameters."""
    gen = torch.Generator().manual_seed(1000 + num_outputs)
    post = random_posterior(num_outputs, 20, 4, gen, fitc=num_outputs == 3)
    m, S = random_gaussian(4, gen)
    weights = (
        torch.randn(num_outputs, generator=gen, dtype=DT),
        torch.randn(num_outputs, num_outputs, generator=gen, dtype=DT),
        torch.randn(4, num_outputs, generator=gen, dtype=DT),
    )
    results = []
    for hand in (True, False):
        leaves = [t.clone().requires_grad_() for t in (m, S)]
        tensors = (post.inputs, post.beta, post.inv_k, post.log_ell, post.log_alpha)
        if posterior_grad:
            tensors = tuple(t.clone().requires_grad_() for t in tensors)
            leaves += list(tensors)
        gp = MomentMatchingGP(GPPosterior(*tensors, post.log_sigma))
        assert gp.has_grad == posterior_grad
        out = gp.predict(*leaves[:2], mean_only) if hand else gp._forward(*leaves[:2], mean_only, None)[0]
        loss = sum((o * w).sum() for o, w in zip(out, weights))
        grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        grads = [torch.zeros_like(x) if g is None else g for g, x in zip(grads, leaves)]  # unused inv_k if mean_only
        results.append(grads + [o.detach() for o in out])
    for hand, auto in zip(*results):
        assert torch.allclose(hand, auto, rtol=1e-11, atol=1e-13)


def test_hand_derived_backward_gradcheck() -> None:
    gen = torch.Generator().manual_seed(1100)
    gp = MomentMatchingGP(random_posterior(3, 8, 3, gen))
    m, S = random_gaussian(3, gen)
    fn = lambda m, S: gp.predict(m, 0.5 * (S + S.T))  # noqa: E731
    assert torch.autograd.gradcheck(fn, (m.clone().requires_grad_(), S.clone().requires_grad_()))


@pytest.mark.parametrize("posterior_grad", [False, True])
def test_no_host_copy_on_a_device(posterior_grad: bool) -> None:
    """On a device, building the moment-matching GP and its forward and backward passes copy nothing to or
    from the host: a copy inside J breaks the CUDA graph's capture (the policy's GP is built inside J), and
    CPU tests would not see it. The meta device (shapes, no data) refuses every such copy."""
    E, n, d = 3, 7, 4
    meta = dict(dtype=DT, device="meta")
    fields = dict(inputs=(n, d), beta=(E, n), inv_k=(E, n, n), log_ell=(E, d), log_alpha=(E,), log_sigma=(E,))
    posterior = GPPosterior(**{k: torch.empty(shape, **meta, requires_grad=posterior_grad and k != "inv_k")
                               for k, shape in fields.items()})
    gp = MomentMatchingGP(posterior, kernel="torch")
    m, S = torch.empty(d, **meta, requires_grad=True), torch.empty(d, d, **meta, requires_grad=True)
    M, V, C = gp.predict(m, S)
    assert (M.shape, V.shape, C.shape) == ((E,), (E, E), (d, E))
    (M.sum() + V.sum() + C.sum()).backward()
    assert m.grad.shape == (d,) and S.grad.shape == (d, d)
    if posterior_grad:
        assert posterior.beta.grad.shape == (E, n) and posterior.inputs.grad.shape == (n, d)
