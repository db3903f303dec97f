"""The state smoother of the GP's training data (:mod:`plugins.pilco.smoothing`), on a damped pendulum whose
GP is trained on its true transitions: the estimates are the minimiser of the smoother's objective (checked
against scipy's least-squares solver on the same residuals), they are nearer the true states than the
observations are, and a round of smoothing and refitting gives a GP whose data are those estimates."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares

from harness.task import Episode
from plugins.pilco.gp import GPModel, predict_latent
from plugins.pilco.kernels import se_ard
from plugins.pilco.policy import linked_steps, transitions
from plugins.pilco.propagate import StateLayout
from plugins.pilco.smoothing import smooth_and_refit, smoothed_states

DT = 0.1
NOISE = np.array([0.05, 0.02])  # std of the measurements of [theta_dot, theta]
LAYOUT = StateLayout.with_trig(2, [1])


def step(x: np.ndarray, u: float) -> np.ndarray:
    """A damped pendulum (theta = 0 down), one explicit step of dt."""
    theta_dot, theta = x
    return np.array([theta_dot + DT * (-9.8 * np.sin(theta) - 0.5 * theta_dot + u), theta + DT * theta_dot])


def episode(rng: np.random.Generator, steps: int, terminated: bool = False) -> Episode:
    states = [rng.normal(0.0, [0.5, 0.8])]
    actions = rng.uniform(-2.0, 2.0, size=(steps, 1))
    for u in actions[:, 0]:
        states.append(step(states[-1], u))
    states = np.array(states)
    return Episode(observations=states + rng.normal(0.0, NOISE, size=states.shape), states=states, actions=actions,
                   costs=np.zeros(steps), terminated=terminated)


@pytest.fixture(scope="module")
def pendulum():
    rng = np.random.default_rng(3)
    train = [episode(rng, 30) for _ in range(8)]
    truth = [Episode(ep.states, ep.states, ep.actions, ep.costs) for ep in train]
    model = GPModel()
    model.fit(*transitions(truth, LAYOUT), seed=0)  # a model of the true dynamics
    return model, [episode(rng, 12), episode(rng, 9, terminated=True)]


def test_the_estimates_minimise_the_objective_as_scipy_finds_it(pendulum):
    model, episodes = pendulum
    posterior = model.posterior()
    q = (0.3 * NOISE) ** 2
    result = smoothed_states(posterior, LAYOUT, episodes, NOISE, q)

    # the same objective as residuals, minimised by scipy from the observations
    lengths = [linked_steps(ep) for ep in episodes]
    Y = np.concatenate([ep.observations[:n + 1] for ep, n in zip(episodes, lengths)])
    U = np.concatenate([ep.actions[:n] for ep, n in zip(episodes, lengths)])
    start = np.concatenate([np.arange(o, o + n) for o, n in zip(np.cumsum([0] + [n + 1 for n in lengths])[:-1], lengths)])

    def gp_inputs(X):
        x = torch.as_tensor(X[start])
        return torch.cat([LAYOUT.augment(x)[:, LAYOUT.model_index], torch.as_tensor(U)], dim=1)

    with torch.no_grad():
        s2 = predict_latent(posterior, gp_inputs(Y))[1].numpy() + q

    def residuals(flat):
        X = flat.reshape(Y.shape)
        with torch.no_grad():
            mean = predict_latent(posterior, gp_inputs(X))[0].numpy()
        return np.concatenate([((Y - X) / NOISE).ravel(), ((X[start + 1] - X[start] - mean) / np.sqrt(s2)).ravel()])

    reference = least_squares(residuals, Y.ravel(), xtol=1e-13, ftol=1e-13, gtol=1e-13).x.reshape(Y.shape)
    estimates = np.concatenate([ep.observations[:n + 1] for ep, n in zip(result.episodes, lengths)])
    assert np.abs(estimates - reference).max() < 1e-4 * NOISE.min()
    reference_loss = 0.5 * (residuals(reference.ravel()) ** 2).sum()
    assert result.loss == pytest.approx(reference_loss, rel=1e-6) and result.loss < reference_loss * (1 + 1e-9)
    # a fall's last observation links nothing and stays as it was; the true states and actions are untouched
    assert np.array_equal(result.episodes[1].observations[-1], episodes[1].observations[-1])
    for got, ep in zip(result.episodes, episodes):
        assert got.states is ep.states and got.actions is ep.actions


def test_the_estimates_are_nearer_the_true_states_than_the_observations(pendulum):
    model, episodes = pendulum
    result = smoothed_states(model.posterior(), LAYOUT, episodes, NOISE, (0.1 * NOISE) ** 2)
    truth = np.concatenate([ep.states for ep in episodes])
    observed = np.sqrt(((np.concatenate([ep.observations for ep in episodes]) - truth) ** 2).mean(0))
    estimated = np.sqrt(((np.concatenate([ep.observations for ep in result.episodes]) - truth) ** 2).mean(0))
    assert np.all(estimated < 0.7 * observed), (estimated, observed)
    assert result.observation_rms.shape == (2,) and np.all(result.observation_rms < 1.5)


def test_smooth_and_refit_trains_the_last_gp_on_the_last_estimates(pendulum):
    model, episodes = pendulum
    seen = []

    def refit(x, y):
        seen.append((x, y))
        gp = GPModel()
        gp.fit(x, y, warm_start=model.hyperparameters, seed=0)
        return gp

    final, rounds = smooth_and_refit(model, refit, LAYOUT, episodes, NOISE, rounds=2, process_var=(0.3 * NOISE) ** 2)
    assert len(rounds) == len(seen) == 2
    x, y = transitions(rounds[-1].episodes, LAYOUT)
    assert np.array_equal(seen[-1][0], x) and np.array_equal(seen[-1][1], y)
    assert final.predict(x)[0].shape == y.shape


def test_bad_noise_is_refused(pendulum):
    model, episodes = pendulum
    with pytest.raises(ValueError, match="noise_std must be a positive"):
        smoothed_states(model.posterior(), LAYOUT, episodes, np.array([0.05, 0.0]))


def test_the_blocked_predictive_mean_is_the_gps_mean(pendulum):
    from plugins.pilco.smoothing import CHUNK, predictive_mean

    model, _ = pendulum
    posterior = model.posterior()
    x = torch.as_tensor(np.random.default_rng(0).normal(size=(2 * CHUNK + 5, posterior.inputs.shape[1])))
    # both sum n terms beta_an k_an(x) whose sizes (beta up to ~4e4 here, the noise std ~1e-4) far exceed the
    # means' (~1): each result may carry the round-off of its own summation order, n eps (sum of |terms|) at
    # most (Higham, Accuracy and Stability of Numerical Algorithms, Sec. 3.1), which on some CPUs is above 1e-12
    # of the mean itself; a wrong block would be off by the whole mean
    n, eps = posterior.inputs.shape[0], torch.finfo(x.dtype).eps
    with torch.no_grad():
        k = se_ard(posterior.inputs, x, posterior.log_ell, posterior.log_alpha)  # (E, n, m)
        terms = torch.einsum("an,anm->ma", posterior.beta.abs(), k)
        diff = x[None, :, None, :] - posterior.inputs[None, None]  # (1, m, n, d)
        inv_ell2 = torch.exp(-2 * posterior.log_ell)[:, None, None, :]  # (E, 1, 1, d)
        grad_terms = (posterior.beta.abs()[:, None, :, None] * k.transpose(1, 2)[..., None] * diff.abs() * inv_ell2).sum((0, 2))
        mean_error = (predictive_mean(posterior, x) - predict_latent(posterior, x)[0]).abs()
    assert torch.all(mean_error <= 2 * n * eps * terms)
    assert (2 * n * eps * terms).max() < 1e-6  # and the bound is far below the means (~1): not vacuous
    a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    predictive_mean(posterior, a).sum().backward()
    predict_latent(posterior, b)[0].sum().backward()  # its gradient in closed form
    # the gradient's terms are products of three rounded factors (beta k, the difference, 1 / ell^2) before their sum: 4 n eps
    assert torch.all((a.grad - b.grad).abs() <= 4 * n * eps * grad_terms)
    assert (4 * n * eps * grad_terms).max() < 1e-5 * b.grad.abs().max()


def test_the_smoother_keeps_to_the_gps_device(pendulum):
    """With torch's default device a meta device (no data), a tensor the smoother made without the GP's device would
    fail the first operation with the CPU's: every tensor it makes is on the GP's device (a GPU's, where the learner
    trains there)."""
    from tests.devices import default_device

    model, episodes = pendulum
    posterior = model.posterior()
    expected = smoothed_states(posterior, LAYOUT, episodes, NOISE, NOISE ** 2, max_iter=5)
    with default_device("meta"):
        got = smoothed_states(posterior, LAYOUT, episodes, NOISE, NOISE ** 2, max_iter=5)
    for a, b in zip(got.episodes, expected.episodes):
        np.testing.assert_array_equal(a.observations, b.observations)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here: the CUDA path is not exercised")
def test_the_smoother_on_a_gpu_gives_the_cpus_estimates(pendulum):
    model, episodes = pendulum
    cpu = model.posterior()
    gpu = type(cpu)(**{f: getattr(cpu, f).cuda() if torch.is_tensor(getattr(cpu, f)) else getattr(cpu, f)
                       for f in cpu.__dataclass_fields__})
    a = smoothed_states(cpu, LAYOUT, episodes, NOISE, NOISE ** 2)
    b = smoothed_states(gpu, LAYOUT, episodes, NOISE, NOISE ** 2)
    for x, y in zip(a.episodes, b.episodes):
        np.testing.assert_allclose(x.observations, y.observations, atol=1e-6 * NOISE.min())
