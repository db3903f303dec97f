"""Tests of the GP dynamics model (full GP and FITC) against independent computations."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch

from harness.errors import NumericalError
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.gp import (
    CURB_LOG_LS,
    CURB_LOG_SNR,
    GPHyperparameters,
    GPModel,
    full_posterior,
    hyp_curb_penalty,
    input_scale,
    negative_log_marginal_likelihood,
    penalised_nll,
    predict_latent,
)
from plugins.pilco.kernels import se_ard
from plugins.pilco.sparse import (
    fitc_factors,
    fitc_negative_log_likelihood,
    fitc_nll_and_pseudo_gradient,
    fitc_nll_of_pseudo_inputs,
    fitc_posterior,
    reduced_posterior,
    select_basis,
)

DT = torch.float64
torch.set_num_threads(1)


def gp_sample(n, d, ells, alphas, sigma, seed, low=-3.0, high=3.0):
    """Inputs uniform in [low, high]^d and targets drawn from E independent SE-ARD GP priors + noise."""
    g = torch.Generator().manual_seed(seed)
    x = low + (high - low) * torch.rand(n, d, generator=g, dtype=DT)
    e = len(alphas)
    log_ell = torch.log(torch.tensor(ells, dtype=DT)).reshape(e, d)
    log_alpha = torch.log(torch.tensor(alphas, dtype=DT))
    chol = torch.linalg.cholesky(se_ard(x, x, log_ell, log_alpha) + 1e-10 * torch.eye(n, dtype=DT))
    f = (chol @ torch.randn(e, n, 1, generator=g, dtype=DT))[..., 0].T
    return x, f + sigma * torch.randn(n, e, generator=g, dtype=DT)


def central_differences(f, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Gradient of the scalar ``f`` at ``x`` (any shape) by central differences, entry by entry."""
    fd = torch.zeros_like(x)
    with torch.no_grad():
        for index in np.ndindex(*x.shape):
            step = torch.zeros_like(x)
            step[index] = eps
            fd[index] = (float(f(x + step)) - float(f(x - step))) / (2 * eps)
    return fd


def random_hyp(e, d, gen):
    return GPHyperparameters(
        log_ell=torch.log(0.5 + torch.rand(e, d, generator=gen, dtype=DT)),
        log_alpha=torch.log(0.5 + torch.rand(e, generator=gen, dtype=DT)),
        log_sigma=torch.log(0.05 + 0.2 * torch.rand(e, generator=gen, dtype=DT)),
    )


def explicit_kernel(a, b, log_ell, log_alpha):
    """One output's SE-ARD Gram matrix with explicit loops over the points (numpy, independent)."""
    ell, alpha2 = np.exp(log_ell), math.exp(2 * log_alpha)
    out = np.empty((a.shape[0], b.shape[0]))
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            r = (a[i] - b[j]) / ell
            out[i, j] = alpha2 * math.exp(-0.5 * float(r @ r))
    return out


# ----------------------------------------------------------------------------- full GP maths


def test_nll_matches_multivariate_normal_log_density():
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(25, 2, generator=gen, dtype=DT)
    y = torch.randn(25, 3, generator=gen, dtype=DT)
    h = random_hyp(3, 2, gen)
    nll = negative_log_marginal_likelihood(x, y, h.log_ell, h.log_alpha, h.log_sigma)
    for a in range(3):
        cov = explicit_kernel(x.numpy(), x.numpy(), h.log_ell[a].numpy(), float(h.log_alpha[a]))
        cov += math.exp(2 * float(h.log_sigma[a])) * np.eye(25)
        dist = torch.distributions.MultivariateNormal(torch.zeros(25, dtype=DT), torch.tensor(cov))
        assert float(nll[a]) == pytest.approx(-float(dist.log_prob(y[:, a])), rel=1e-10)


def test_hyp_curb_penalty_formula():
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(30, 3, generator=gen, dtype=DT) * torch.tensor([0.1, 1.0, 5.0], dtype=DT)
    s = x.numpy().std(0, ddof=1)
    h = random_hyp(2, 3, gen)
    h.log_ell[0, 0] = math.log(s[0] * 300.0)  # outside the box: large
    h.log_sigma[1] = h.log_alpha[1] - math.log(2000.0)
    pen = hyp_curb_penalty(h.log_ell, h.log_alpha, h.log_sigma, input_scale(x))
    for a in range(2):
        want = sum(((float(h.log_ell[a, i]) - math.log(s[i])) / math.log(100)) ** 30 for i in range(3))
        want += ((float(h.log_alpha[a]) - float(h.log_sigma[a])) / math.log(1000)) ** 30
        assert float(pen[a]) == pytest.approx(want, rel=1e-10)
    assert float(pen[0]) > 100 and float(pen[1]) > 10  # (log 300/log 100)^30, (log 2000/log 1000)^30


def test_penalised_nll_gradient_matches_central_differences():
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(20, 2, generator=gen, dtype=DT)
    y = torch.sin(x[:, :1] * 2) + 0.1 * torch.randn(20, 2, generator=gen, dtype=DT)
    s = input_scale(x)
    h = random_hyp(2, 2, gen)
    h.log_ell[1, 0] = torch.log(s[0]) + 1.1 * CURB_LOG_LS  # length-scale penalty gradient is active here
    flat = torch.cat([h.log_ell.reshape(-1), h.log_alpha, h.log_sigma]).requires_grad_(True)

    def f(v):
        hh = GPHyperparameters(v[:4].reshape(2, 2), v[4:6], v[6:8])
        return penalised_nll(x, y, hh).sum()

    (grad,) = torch.autograd.grad(f(flat), flat)
    eps = 1e-6
    fd = torch.zeros_like(grad)
    with torch.no_grad():
        for i in range(flat.numel()):
            step = torch.zeros_like(flat)
            step[i] = eps
            fd[i] = (f(flat + step) - f(flat - step)) / (2 * eps)
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=1e-6)
    assert float(grad.abs().max()) > 100.0  # a non-trivial gradient


def test_analytic_nll_gradient_matches_central_differences():
    """The NLL's hand-written backward (no penalty), three outputs on 3-D inputs."""
    gen = torch.Generator().manual_seed(16)
    x = torch.randn(25, 3, generator=gen, dtype=DT)
    y = torch.randn(25, 3, generator=gen, dtype=DT)
    h = random_hyp(3, 3, gen)
    params = [t.clone().requires_grad_(True) for t in (h.log_ell, h.log_alpha, h.log_sigma)]
    weights = torch.tensor([1.0, -0.5, 2.0], dtype=DT)  # a non-uniform upstream gradient
    grads = torch.autograd.grad((negative_log_marginal_likelihood(x, y, *params) * weights).sum(), params)
    eps = 1e-6
    with torch.no_grad():
        for p, g in zip(params, grads):
            flat = p.view(-1)
            for i in range(flat.numel()):
                old = float(flat[i])
                flat[i] = old + eps
                up = float((negative_log_marginal_likelihood(x, y, *params) * weights).sum())
                flat[i] = old - eps
                down = float((negative_log_marginal_likelihood(x, y, *params) * weights).sum())
                flat[i] = old
                assert float(g.view(-1)[i]) == pytest.approx((up - down) / (2 * eps), rel=1e-6, abs=1e-7)


def test_snr_penalty_gradient_matches_central_differences():
    """Beyond SNR 1000 the NLL itself is ill-conditioned, so the SNR term is checked on its own."""
    log_ell = torch.zeros(1, 1, dtype=DT)
    s = torch.ones(1, dtype=DT)
    v = torch.tensor([0.3, 0.3 - 1.07 * CURB_LOG_SNR], dtype=DT, requires_grad=True)

    def f(w):
        return hyp_curb_penalty(log_ell, w[:1], w[1:], s).sum()

    (grad,) = torch.autograd.grad(f(v), v)
    eps = 1e-6
    with torch.no_grad():
        fd = torch.stack([(f(v + eps * e) - f(v - eps * e)) / (2 * eps) for e in torch.eye(2, dtype=DT)])
    torch.testing.assert_close(grad, fd, rtol=1e-7, atol=1e-9)
    assert float(grad[0]) > 10.0 and float(grad[1]) == pytest.approx(-float(grad[0]))


def test_predictions_match_paper_equations_7_8():
    gen = torch.Generator().manual_seed(4)
    x = torch.randn(30, 2, generator=gen, dtype=DT)
    y = torch.randn(30, 2, generator=gen, dtype=DT)
    xs = torch.randn(7, 2, generator=gen, dtype=DT)
    h = random_hyp(2, 2, gen)
    mean, var = predict_latent(full_posterior(x, y, h.log_ell, h.log_alpha, h.log_sigma), xs)
    for a in range(2):
        k = explicit_kernel(x.numpy(), x.numpy(), h.log_ell[a].numpy(), float(h.log_alpha[a]))
        k += math.exp(2 * float(h.log_sigma[a])) * np.eye(30)
        ks = explicit_kernel(x.numpy(), xs.numpy(), h.log_ell[a].numpy(), float(h.log_alpha[a]))
        m_want = ks.T @ np.linalg.solve(k, y[:, a].numpy())
        v_want = math.exp(2 * float(h.log_alpha[a])) - np.einsum("ij,ij->j", ks, np.linalg.solve(k, ks))
        np.testing.assert_allclose(mean[:, a].numpy(), m_want, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(var[:, a].numpy(), v_want, rtol=1e-7, atol=1e-10)


def test_fixed_model_prediction_and_its_input_gradient_equal_the_autograd_composition():
    """``predict_latent`` on a fixed model (the fused pass with its closed-form gradient) against the same
    model with its tensors requiring grad (the torch composition, differentiated by autograd): mean and
    variance to rounding, their gradient wrt the test inputs to 1e-10 relative; and that gradient against
    central differences."""
    gen = torch.Generator().manual_seed(12)
    x = torch.randn(40, 3, generator=gen, dtype=DT)
    y = torch.randn(40, 2, generator=gen, dtype=DT)
    h = random_hyp(2, 3, gen)
    fixed = full_posterior(x, y, h.log_ell, h.log_alpha, h.log_sigma).detach()
    free = GPPosterior(*(t.clone().requires_grad_(True) for t in (fixed.inputs, fixed.beta, fixed.inv_k, fixed.log_ell,
                                                                  fixed.log_alpha, fixed.log_sigma)))
    xs = torch.randn(9, 3, generator=gen, dtype=DT)
    xs[0] = x[5]  # a test input on a basis point (squared distance 0 up to rounding)
    g_mean, g_var = torch.randn(9, 2, generator=gen, dtype=DT), torch.randn(9, 2, generator=gen, dtype=DT)
    results = []
    for post in (fixed, free):
        inputs = xs.clone().requires_grad_(True)
        mean, var = predict_latent(post, inputs)
        grad, = torch.autograd.grad((mean * g_mean).sum() + (var * g_var).sum(), inputs)
        results.append((mean.detach(), var.detach(), grad))
    (m1, v1, g1), (m2, v2, g2) = results
    torch.testing.assert_close(m1, m2, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(v1, v2, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(g1, g2, rtol=1e-10, atol=1e-12)

    def f(inputs):
        mean, var = predict_latent(fixed, inputs)
        return float((mean * g_mean).sum() + (var * g_var).sum())

    torch.testing.assert_close(g1, central_differences(f, xs), rtol=1e-6, atol=1e-8)


# ----------------------------------------------------------------------------- training


def test_recovers_lengthscale_and_noise_1d():
    """Targets drawn from GP priors with ell = 0.7 / 1.5 and noise std 0.05 (n = 200).

    Tolerance: length-scales within 20 %, noise within 25 % (5 seeds give ell 0.62-0.68, 1.41-1.67
    and noise 0.045-0.054).
    """
    x, y = gp_sample(200, 1, [0.7, 1.5], [1.0, 2.0], 0.05, seed=0)
    report = GPModel().fit(x, y)
    ell = report.hyperparameters.log_ell.exp()[:, 0]
    sigma = report.hyperparameters.log_sigma.exp()
    np.testing.assert_allclose(ell.numpy(), [0.7, 1.5], rtol=0.20)
    np.testing.assert_allclose(sigma.numpy(), [0.05, 0.05], rtol=0.25)
    assert not report.sparse and report.n_points == 200


def test_recovers_lengthscales_and_noise_3d():
    """Two outputs on 3-D inputs with ell = (0.5, 1, 2) and (2, 1, 0.7), noise 0.05, n = 300."""
    ells = [[0.5, 1.0, 2.0], [2.0, 1.0, 0.7]]
    x, y = gp_sample(300, 3, sum(ells, []), [1.0, 1.0], 0.05, seed=0)
    report = GPModel().fit(x, y)
    np.testing.assert_allclose(report.hyperparameters.log_ell.exp().numpy(), ells, rtol=0.20)
    np.testing.assert_allclose(report.hyperparameters.log_sigma.exp().numpy(), [0.05, 0.05], rtol=0.25)


def test_curb_keeps_lengthscale_and_snr_in_the_box():
    """An irrelevant input drives its length-scale to the optimiser's edge and noise-free targets drive
    the noise to its floor without hypCurb; with it, both stay (softly) inside the box."""
    gen = torch.Generator().manual_seed(5)
    x = torch.rand(60, 2, generator=gen, dtype=DT) * 4 - 2
    y = torch.sin(2 * x[:, :1])  # noise free, second input irrelevant
    s = input_scale(x)
    loose = GPModel(curb=False).fit(x, y).hyperparameters
    tight = GPModel(curb=True).fit(x, y).hyperparameters
    loose_ls = float((loose.log_ell[0, 1] - torch.log(s[1])) / CURB_LOG_LS)
    tight_ls = float((tight.log_ell[0, 1] - torch.log(s[1])) / CURB_LOG_LS)
    loose_snr = float((loose.log_alpha[0] - loose.log_sigma[0]) / CURB_LOG_SNR)
    tight_snr = float((tight.log_alpha[0] - tight.log_sigma[0]) / CURB_LOG_SNR)
    assert loose_ls > 1.2 and loose_snr > 1.2  # the data really push out of the box
    assert tight_ls < 1.1 and tight_snr < 1.1


def test_degenerate_data_train_and_predict_finite():
    """Constant non-zero target, all-zero target, triplicated inputs and a constant input column."""
    gen = torch.Generator().manual_seed(6)
    base = torch.rand(15, 2, generator=gen, dtype=DT)
    x = torch.cat([base, base, base])
    x = torch.cat([x, torch.full((45, 1), 0.3, dtype=DT)], dim=1)
    y = torch.stack([torch.full((45,), 3.0, dtype=DT), torch.zeros(45, dtype=DT)], dim=1)
    model = GPModel()
    report = model.fit(x, y, restarts=1)
    h = report.hyperparameters
    assert all(bool(torch.isfinite(t).all()) for t in (h.log_ell, h.log_alpha, h.log_sigma))
    xs = torch.cat([x[:5], torch.randn(5, 3, generator=gen, dtype=DT) * 10])
    mean, var = model.predict(xs)
    assert bool(torch.isfinite(mean).all()) and bool(torch.isfinite(var).all())
    np.testing.assert_allclose(mean[:5].numpy(), [[3.0, 0.0]] * 5, atol=1e-2)
    assert float(var.min()) > -1e-8

    # the same data through FITC: pseudo-inputs start on duplicated points (singular K_mm)
    sparse = GPModel(sparse_threshold=20, num_pseudo=12, max_evals_full=100, max_evals_fitc=30)
    report = sparse.fit(x, y, seed=1)
    assert report.sparse and math.isfinite(report.fitc_nll)
    mean, var = sparse.predict(xs)
    assert bool(torch.isfinite(mean).all()) and bool(torch.isfinite(var).all())
    np.testing.assert_allclose(mean[:5].numpy(), [[3.0, 0.0]] * 5, atol=5e-2)


def test_non_finite_data_raise_numerical_error():
    x = torch.randn(10, 2, dtype=DT)
    y = torch.randn(10, 1, dtype=DT)
    y[3, 0] = float("nan")
    with pytest.raises(NumericalError):
        GPModel().fit(x, y)


def test_cholesky_failures_during_training(monkeypatch):
    """A failure at the start is a NumericalError; a failure at a later trial point stops the run
    with the best point evaluated so far."""
    import plugins.pilco.gp as gp_module

    x, y = gp_sample(40, 1, [0.8], [1.0], 0.05, seed=17)
    calls = [0]
    real = gp_module.cholesky

    def failing_from(first, last):
        def chol(matrix, what="matrix"):
            calls[0] += 1
            if first <= calls[0] <= last:
                raise NumericalError(f"injected failure of the {what}")
            return real(matrix, what)

        return chol

    monkeypatch.setattr(gp_module, "cholesky", failing_from(1, 10**9))
    with pytest.raises(NumericalError, match="injected"):
        GPModel().fit(x, y)

    calls[0] = 0
    monkeypatch.setattr(gp_module, "cholesky", failing_from(6, 6))
    report = GPModel().fit(x, y)
    assert calls[0] > 6 and "STOPPED" in report.messages[0]
    assert report.evaluations == 6
    monkeypatch.setattr(gp_module, "cholesky", real)
    with torch.no_grad():
        start = penalised_nll(x, y, gp_module.initial_hyperparameters(x, y))
        got = penalised_nll(x, y, report.hyperparameters)
    assert math.isfinite(report.nll) and float(got.sum()) == pytest.approx(report.nll, rel=1e-12)
    assert report.nll < float(start.sum()) - 1.0  # the five good evaluations were not wasted


def test_restarts_keep_the_best_run_per_output():
    """Few noisy points of wiggly functions: the optimum reached depends on the start."""
    gen = torch.Generator().manual_seed(4)
    x = torch.rand(15, 1, generator=gen, dtype=DT) * 6 - 3
    y = torch.cat([torch.sin(4 * x), torch.sin(x) * x], 1) + 0.3 * torch.randn(15, 2, generator=gen, dtype=DT)
    report = GPModel().fit(x, y, restarts=5, seed=0)
    runs = report.restart_nlls
    assert runs.shape == (6, 2)
    assert runs[0, 1] > runs[:, 1].min() + 1.0  # the unperturbed run is not the best for output 1
    with torch.no_grad():
        got = penalised_nll(x, y, report.hyperparameters).numpy()
    np.testing.assert_allclose(got, runs.min(0), rtol=1e-10)
    np.testing.assert_allclose(report.nll_per_output, runs.min(0), rtol=1e-12)
    # run 0 is the reference initialisation without perturbation
    plain = GPModel().fit(x, y)
    np.testing.assert_allclose(runs[0], plain.nll_per_output, rtol=1e-10)
    assert np.all(got <= plain.nll_per_output + 1e-9)


def test_warm_start_reaches_the_same_optimum_faster():
    x, y = gp_sample(80, 2, [0.8, 1.2], [1.0], 0.05, seed=8)
    model = GPModel()
    first = model.fit(x, y)
    second = model.fit(x, y, warm_start=model.hyperparameters)
    assert second.evaluations < first.evaluations
    assert second.nll == pytest.approx(first.nll, abs=1e-4)


# ----------------------------------------------------------------------------- FITC


def fitc_setup(seed, n=40, m=10, d=2, e=2):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, d, generator=gen, dtype=DT)
    y = torch.sin(x @ torch.randn(d, e, generator=gen, dtype=DT)) + 0.1 * torch.randn(n, e, generator=gen, dtype=DT)
    z = torch.randn(m, d, generator=gen, dtype=DT)
    return x, y, z, random_hyp(e, d, gen)


def textbook_fitc(x, y, z, log_ell, log_alpha, log_sigma, xs, ridge=1e-6):
    """FITC with explicit n x n matrices (numpy): NLML, predictive mean and latent variance."""
    xn, zn, xsn = x.numpy(), z.numpy(), xs.numpy()
    a2 = math.exp(2 * log_alpha)
    kmm = explicit_kernel(zn, zn, log_ell, log_alpha) + ridge * a2 * np.eye(len(zn))
    kmn = explicit_kernel(zn, xn, log_ell, log_alpha)
    kms = explicit_kernel(zn, xsn, log_ell, log_alpha)
    qnn = kmn.T @ np.linalg.solve(kmm, kmn)
    lam = np.diag(a2 - np.diag(qnn) + math.exp(2 * log_sigma))
    cov = qnn + lam
    _, logdet = np.linalg.slogdet(cov)
    nll = 0.5 * (y @ np.linalg.solve(cov, y) + logdet + len(y) * math.log(2 * math.pi))
    qsn = kms.T @ np.linalg.solve(kmm, kmn)
    mean = qsn @ np.linalg.solve(cov, y)
    var = a2 - np.einsum("ij,ji->i", qsn, np.linalg.solve(cov, qsn.T))
    return nll, mean, var


def test_fitc_nll_and_posterior_match_textbook_formulas():
    x, y, z, h = fitc_setup(9)
    xs = torch.randn(6, 2, generator=torch.Generator().manual_seed(10), dtype=DT)
    nll = fitc_negative_log_likelihood(x, y, z, h.log_ell, h.log_alpha, h.log_sigma)
    post = fitc_posterior(x, y, z, h.log_ell, h.log_alpha, h.log_sigma)
    assert post.inputs.shape == (10, 2) and post.beta.shape == (2, 10) and post.inv_k.shape == (2, 10, 10)
    mean, var = predict_latent(post, xs)
    for a in range(2):
        args = (h.log_ell[a].numpy(), float(h.log_alpha[a]), float(h.log_sigma[a]))
        nll_w, mean_w, var_w = textbook_fitc(x, y[:, a].numpy(), z, *args, xs)
        assert float(nll[a]) == pytest.approx(nll_w, rel=1e-9)
        np.testing.assert_allclose(mean[:, a].numpy(), mean_w, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(var[:, a].numpy(), var_w, rtol=1e-6, atol=1e-8)


def test_fitc_nll_gradient_wrt_pseudo_inputs_matches_central_differences():
    x, y, z, h = fitc_setup(11, m=6)
    zz = z.clone().requires_grad_(True)

    def f(v):
        return fitc_negative_log_likelihood(x, y, v, h.log_ell, h.log_alpha, h.log_sigma).sum()

    (grad,) = torch.autograd.grad(f(zz), zz)
    torch.testing.assert_close(grad, central_differences(f, z), rtol=1e-5, atol=1e-6)


def test_hand_derived_fitc_pseudo_gradient_matches_autograd_and_differences():
    """sparse.fitc_nll_and_pseudo_gradient: the NLL of fitc_negative_log_likelihood, and per output
    the gradient autograd takes through it (1e-9) and central differences (1e-5)."""
    x, y, z, h = fitc_setup(21, m=7)
    args = (h.log_ell, h.log_alpha, h.log_sigma)
    nll, grad = fitc_nll_and_pseudo_gradient(x, y, z, *args)
    zz = z.clone().requires_grad_(True)
    ref = fitc_negative_log_likelihood(x, y, zz, *args)
    torch.testing.assert_close(nll, ref.detach(), rtol=1e-12, atol=0)
    for a in range(ref.shape[0]):
        (g_ref,) = torch.autograd.grad(ref[a], zz, retain_graph=True)
        torch.testing.assert_close(grad[a], g_ref, rtol=1e-9, atol=1e-12)
    eps = 1e-6
    with torch.no_grad():
        for i, j in [(0, 0), (3, 1), (6, 0)]:
            step = torch.zeros_like(z)
            step[i, j] = eps
            fd = (fitc_negative_log_likelihood(x, y, z + step, *args) - fitc_negative_log_likelihood(x, y, z - step, *args)) / (2 * eps)
            torch.testing.assert_close(grad[:, i, j], fd, rtol=1e-5, atol=1e-7)
    # the autograd Function the optimiser uses routes the summed gradient
    zz = z.clone().requires_grad_(True)
    (g_sum,) = torch.autograd.grad(fitc_nll_of_pseudo_inputs(x, y, zz, *args).sum(), zz)
    torch.testing.assert_close(g_sum, grad.sum(0), rtol=1e-14, atol=0)


def test_hand_derived_fitc_gradient_where_lambda_is_clamped():
    """Pseudo-inputs at training inputs without ridge: K_nn - Q_nn rounds below 0 for some points and
    Lambda is clamped to sigma^2 there; the hand-derived gradient still equals autograd's (which
    has no gradient through the clamp either)."""
    x, y, _, h = fitc_setup(21, m=7)
    z = x[:7].clone()
    args = (h.log_ell, h.log_alpha, h.log_sigma, 0.0)
    f = fitc_factors(x, y, z, *args)
    assert bool((f.lam <= torch.exp(2 * h.log_sigma)[:, None]).any())  # not vacuous
    nll, grad = fitc_nll_and_pseudo_gradient(x, y, z, *args)
    zz = z.clone().requires_grad_(True)
    ref = fitc_negative_log_likelihood(x, y, zz, *args)
    (g_ref,) = torch.autograd.grad(ref.sum(), zz)
    torch.testing.assert_close(nll, ref.detach(), rtol=1e-10, atol=0)
    torch.testing.assert_close(grad.sum(0), g_ref, rtol=1e-6, atol=1e-8)


def test_fitc_with_pseudo_inputs_at_training_inputs_equals_full_gp():
    x, y, _, h = fitc_setup(12, n=30)
    xs = torch.randn(8, 2, generator=torch.Generator().manual_seed(13), dtype=DT)
    args = (h.log_ell, h.log_alpha, h.log_sigma)
    full = negative_log_marginal_likelihood(x, y, *args)
    sparse = fitc_negative_log_likelihood(x, y, x, *args, ridge=1e-10)
    torch.testing.assert_close(sparse, full, rtol=1e-6, atol=1e-6)
    m_full, v_full = predict_latent(full_posterior(x, y, *args), xs)
    m_fitc, v_fitc = predict_latent(fitc_posterior(x, y, x, *args, ridge=1e-10), xs)
    torch.testing.assert_close(m_fitc, m_full, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(v_fitc, v_full, rtol=1e-4, atol=1e-6)
    # the default ridge (1e-6 alpha^2) changes predictions slightly (the gap is linear in the ridge)
    m_def, v_def = predict_latent(fitc_posterior(x, y, x, *args), xs)
    torch.testing.assert_close(m_def, m_full, rtol=0, atol=1e-2)
    torch.testing.assert_close(v_def, v_full, rtol=0, atol=1e-3)


def test_sparse_takes_over_above_threshold_and_optimises_pseudo_inputs():
    gen = torch.Generator().manual_seed(14)
    x = torch.rand(100, 1, generator=gen, dtype=DT) * 6 - 3
    y = torch.sin(2 * x) + 0.05 * torch.randn(100, 1, generator=gen, dtype=DT)
    opts = dict(sparse_threshold=60, num_pseudo=12, max_evals_full=200, max_evals_fitc=200)

    small = GPModel(**opts).fit(x[:50], y[:50])
    assert not small.sparse and small.hyperparameters.pseudo_inputs is None

    model = GPModel(**opts)
    report = model.fit(x, y, seed=1)
    assert report.sparse and report.n_points == 100 and report.n_hyper_points == 60
    assert model.posterior().inputs.shape == (12, 1)
    # same seed, no pseudo-input optimisation: the initial random subset
    unoptimised = GPModel(**{**opts, "max_evals_fitc": 0}).fit(x, y, seed=1)
    assert report.fitc_nll < unoptimised.fitc_nll - 1.0
    # the sparse model predicts the function
    xs = torch.linspace(-2.8, 2.8, 50, dtype=DT)[:, None]
    mean, var = model.predict(xs)
    assert float((mean - torch.sin(2 * xs)).abs().max()) < 0.1
    assert float(var.min()) > -1e-8

    # a warm start keeps the previous pseudo-inputs (budget 0 => unchanged)
    again = GPModel(**{**opts, "max_evals_fitc": 0}).fit(x, y, warm_start=report.hyperparameters, seed=2)
    torch.testing.assert_close(again.hyperparameters.pseudo_inputs, report.hyperparameters.pseudo_inputs)
    # refresh_pseudo ignores them: the random subset of seed 2, as without a warm start
    fresh = GPModel(**{**opts, "max_evals_fitc": 0}, refresh_pseudo=True).fit(x, y, warm_start=report.hyperparameters, seed=2)
    scratch = GPModel(**{**opts, "max_evals_fitc": 0}).fit(x, y, seed=2)
    torch.testing.assert_close(fresh.hyperparameters.pseudo_inputs, scratch.hyperparameters.pseudo_inputs)
    assert not torch.equal(fresh.hyperparameters.pseudo_inputs, report.hyperparameters.pseudo_inputs)


def test_pseudo_inputs_train_on_a_random_subset_and_the_model_uses_all_points(monkeypatch):
    """pseudo_subset=K: the pseudo-input optimisation sees K distinct training points (its cost grows with them);
    the posterior and the reported FITC NLL are FITC's on all n points with the optimised pseudo-inputs; at or above n
    it changes nothing (no extra random draw); below num_pseudo it is refused."""
    import plugins.pilco.gp as gp_module

    gen = torch.Generator().manual_seed(14)
    x = torch.rand(100, 1, generator=gen, dtype=DT) * 6 - 3
    y = torch.sin(2 * x) + 0.05 * torch.randn(100, 1, generator=gen, dtype=DT)
    opts = dict(sparse_threshold=60, num_pseudo=12, max_evals_full=200, max_evals_fitc=60)
    seen, seen_targets = [], []
    original = gp_module.optimise_pseudo_inputs

    def recording(inputs, targets, *args, **kwargs):
        seen.append(inputs.clone())
        seen_targets.append(targets.clone())
        return original(inputs, targets, *args, **kwargs)

    monkeypatch.setattr(gp_module, "optimise_pseudo_inputs", recording)
    model = GPModel(**opts, pseudo_subset=40)
    report = model.fit(x, y, seed=1)
    assert seen[-1].shape == (40, 1) and torch.unique(seen[-1]).numel() == 40
    assert all(bool((x == row).all(1).any()) for row in seen[-1])  # rows of the data
    h = report.hyperparameters
    args = (h.log_ell, h.log_alpha, h.log_sigma)
    full = fitc_posterior(x, y, h.pseudo_inputs, *args)
    torch.testing.assert_close(model.posterior().beta, full.beta, rtol=1e-12, atol=1e-12)
    assert report.fitc_nll == pytest.approx(float(fitc_negative_log_likelihood(x, y, h.pseudo_inputs, *args).sum()), rel=1e-12)
    on_subset = float(fitc_negative_log_likelihood(seen[-1], seen_targets[-1], h.pseudo_inputs, *args).sum())
    assert report.fitc_nll < on_subset - 10.0  # not vacuous: 100 points' NLL, not the 40's (each point adds ~ -1.5 nats)

    plain = GPModel(**opts).fit(x, y, seed=1)
    assert seen[-1].shape == (100, 1)
    at_n = GPModel(**opts, pseudo_subset=100).fit(x, y, seed=1)
    assert seen[-1].shape == (100, 1)
    torch.testing.assert_close(at_n.hyperparameters.pseudo_inputs, plain.hyperparameters.pseudo_inputs, rtol=0, atol=0)
    assert not torch.equal(report.hyperparameters.pseudo_inputs, plain.hyperparameters.pseudo_inputs)
    with pytest.raises(ValueError, match="pseudo_subset=8 is below num_pseudo=12"):
        GPModel(**opts, pseudo_subset=8)


@pytest.mark.parametrize("sparse", [False, True])
def test_state_dict_round_trip(sparse):
    x, y = gp_sample(70, 2, [0.8, 1.2, 1.0, 0.5], [1.0, 0.5], 0.05, seed=15)
    model = GPModel(sparse_threshold=50 if sparse else 300, num_pseudo=10, max_evals_full=60, max_evals_fitc=60)
    model.fit(x, y)
    buffer = io.BytesIO()
    torch.save(model.state_dict(), buffer)
    buffer.seek(0)
    restored = GPModel(num_pseudo=10)
    restored.load_state_dict(torch.load(buffer, weights_only=True))
    assert restored.sparse == sparse
    # the hyperparameters alone (the learner's warm start) also survive a weights-only checkpoint
    buffer = io.BytesIO()
    torch.save(model.hyperparameters.as_dict(), buffer)
    buffer.seek(0)
    hyp = GPHyperparameters.from_dict(torch.load(buffer, weights_only=True))
    assert (hyp.pseudo_inputs is not None) == sparse
    for name in ("log_ell", "log_alpha", "log_sigma", "pseudo_inputs"):
        want = getattr(model.hyperparameters, name)
        if want is not None:
            torch.testing.assert_close(getattr(hyp, name), want, rtol=0, atol=0)
    xs = torch.randn(5, 2, dtype=DT)
    for got, want in zip(restored.predict(xs), model.predict(xs)):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------------- planning on fewer basis points


def test_select_basis_takes_the_point_that_explains_most_prior_variance_at_the_data():
    """Each greedy step against the explained variance computed directly for every candidate,
    sum_a sum_i [K_iS K_SS^-1 K_Si]_a (unit signal variance), by explicit solves."""
    gen = torch.Generator().manual_seed(31)
    z = torch.randn(25, 3, generator=gen, dtype=DT)
    z[7] = z[3]  # a duplicate adds nothing once its twin is taken
    x = torch.randn(40, 3, generator=gen, dtype=DT) * 0.7 + 0.5  # data off-centre: the choice must follow them
    h = random_hyp(2, 3, gen)
    keep = select_basis(z, x, h.log_ell, 24).tolist()
    assert len(set(keep)) == 24 and not {3, 7} <= set(keep)
    unit = torch.zeros(2, dtype=DT)
    k_zz = se_ard(z, z, h.log_ell, unit).numpy()
    k_xz = se_ard(x, z, h.log_ell, unit).numpy()

    def explained(subset):
        return sum(np.trace(k_xz[a][:, subset] @ np.linalg.solve(k_zz[a][np.ix_(subset, subset)] + 1e-9 * np.eye(len(subset)),
                                                                     k_xz[a][:, subset].T))
                   for a in range(2))

    taken = []
    for nxt in keep[:10]:
        rest = [i for i in range(25) if i not in taken]
        assert rest[int(np.argmax([explained(taken + [i]) for i in rest]))] == nxt
        taken.append(nxt)
    with pytest.raises(ValueError, match="between 1 and the 25"):
        select_basis(z, x, h.log_ell, 26)
    # exact and 1e-9-close copies: every distinct location is taken before any second copy, all finite
    copies = torch.cat([z[:10], z[:10], z[:10] + 1e-9, z[10:]])  # z[:10] x 3 (z[7] = z[3]), then 15 more
    order = select_basis(copies, x, h.log_ell, 45).tolist()
    assert sorted(order) == list(range(45))
    locations = [((3 if i % 10 == 7 else i % 10) if i < 30 else i) for i in order[:24]]  # 24 distinct locations
    assert len(set(locations)) == 24


def test_planning_posterior_on_fewer_points_is_fitc_on_the_selected_ones():
    """GPModel.posterior(max_basis=m): the model itself for m >= its basis; else FITC with m of its basis inputs,
    the same hyperparameters and data; for a full GP on all its inputs FITC is the exact GP (textbook identity)."""
    x, y = gp_sample(60, 2, [0.8, 1.2, 1.0, 0.5], [1.0, 0.5], 0.05, seed=16)
    xs = torch.randn(7, 2, dtype=DT)
    full = GPModel(sparse_threshold=300, max_evals_full=60)
    full.fit(x, y)
    assert full.posterior(max_basis=60) is full.posterior() and full.posterior(max_basis=500) is full.posterior()
    h = full.hyperparameters
    as_fitc = reduced_posterior(full.state_dict()["inputs"], full.state_dict()["targets"], full.state_dict()["inputs"],
                                h.log_ell, h.log_alpha, h.log_sigma, 60, ridge=1e-10)
    for got, want in zip(predict_latent(as_fitc, xs), predict_latent(full.posterior(), xs)):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)
    fewer = full.posterior(max_basis=15)
    assert fewer.inputs.shape == (15, 2)
    inputs = full.state_dict()["inputs"]
    keep = select_basis(inputs, inputs, h.log_ell, 15)
    torch.testing.assert_close(fewer.inputs, inputs[keep], rtol=0, atol=0)
    textbook = [textbook_fitc(inputs, y[:, a].numpy(), inputs[keep], h.log_ell[a].numpy(), float(h.log_alpha[a]),
                              float(h.log_sigma[a]), xs) for a in range(2)]
    mean, var = predict_latent(fewer, xs)
    np.testing.assert_allclose(mean.numpy(), np.stack([t[1] for t in textbook], 1), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(var.numpy(), np.stack([t[2] for t in textbook], 1), rtol=1e-6, atol=1e-8)
    sparse = GPModel(sparse_threshold=40, num_pseudo=20, max_evals_full=60, max_evals_fitc=20)
    sparse.fit(x, y)
    assert sparse.posterior(max_basis=20) is sparse.posterior()
    assert sparse.posterior(max_basis=8).inputs.shape == (8, 2)
    with pytest.raises(ValueError, match="at least 1"):
        sparse.posterior(max_basis=0)
