"""State estimates for the dynamics GP's training data: recorded episodes smoothed through a dynamics model.

PILCO trains its GP on pairs ``(x~_t, x~_{t+1} - x~_t)`` of noisy observations ``x~_t = x_t + e_t``. The
noise ``e_t`` sits in the input and, with the opposite sign, in the target, so the regression learns a
spurious pull back towards its data: ``E[x~_{t+1} - x~_t | x~_t]`` holds ``E[x_t | x~_t] - x~_t``, a
shrinkage of the state towards the data's mean at every step, which a rollout applies again and again
(on the unicycle it makes the model's rides fall several times less often than the real ones:
``results/findings_unicycle.md``). With the true states in place of the observations the bias is gone;
this module estimates them.

:func:`smoothed_states` is a maximum-a-posteriori smoother of each episode's states ``X (T+1, D)``
given its observations ``Y`` and actions ``U`` (known exactly: the policy's own outputs), under a model
of the dynamics (a trained GP posterior of the state changes)::

    L(X) = 1/2 sum_t |(Y_t - X_t) / sigma|^2 + 1/2 sum_t |(X_{t+1} - X_t - m(a(X_t), U_t)) / s_t|^2

``sigma`` the measurement noise std ``(D,)``, ``m`` the GP's predictive mean of the change, ``s_t^2`` its
latent variance at the observations (held fixed while ``X`` moves) plus ``process_var`` (the model's error allowance; the systems
here are deterministic, so it is not a noise of the system). Minimised by L-BFGS over all episodes at
once (``m`` by :func:`predictive_mean`, differentiated by autograd). :func:`smooth_and_refit`
alternates it with refitting the GP on the estimates (a few rounds of an EM-like scheme: the GP that
smooths the first round was itself trained on the observations).

The last transition of a terminated episode (a fall: the GP has no data there, :func:`transitions` drops
it) links nothing; its last observation is kept as it is.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from harness.task import Episode
from plugins.pilco.gp import DTYPE, GPModel, predict_latent
from plugins.pilco.kernels import se_ard
from plugins.pilco.policy import linked_steps, transitions
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.propagate import StateLayout


@dataclass(frozen=True)
class SmoothingResult:
    """Smoothed episodes (their ``observations`` replaced by the state estimates) and how far the
    estimates moved: per state entry the rms of ``X - Y`` over ``sigma`` (1 if the estimates were the true
    states and the noise as the task says; 0.4-0.5 on the unicycle, whose estimates keep about 2/3 of the
    noise's error) and the rms dynamics residual over ``s``."""

    episodes: list[Episode]
    observation_rms: np.ndarray
    residual_rms: np.ndarray
    loss: float


#: test inputs per block of :func:`predictive_mean`: the block's ``(E, n, CHUNK)`` kernel values stay in cache
#: (one unicycle smoothing step, 2,037 inputs on 300 basis points: 2.5x less CPU than in one block)
CHUNK = 128


def predictive_mean(posterior: GPPosterior, inputs: torch.Tensor) -> torch.Tensor:
    """The GP's predictive mean ``(m, E)`` at ``inputs (m, d)``, differentiable by autograd, in blocks of
    :data:`CHUNK` inputs (no variance: the smoother's objective needs only the mean at the estimates)."""
    blocks = [torch.einsum("an,anm->ma", posterior.beta, se_ard(posterior.inputs, inputs[i:i + CHUNK], posterior.log_ell,
                                                                  posterior.log_alpha))
              for i in range(0, inputs.shape[0], CHUNK)]
    return torch.cat(blocks) if blocks else inputs.new_zeros((0, posterior.beta.shape[0]))


def smoothed_states(
    posterior: GPPosterior,
    layout: StateLayout,
    episodes: Sequence[Episode],
    noise_std: np.ndarray,
    process_var: float | np.ndarray = 0.0,
    max_iter: int = 100,
) -> SmoothingResult:
    """MAP estimates of every episode's states under the dynamics ``posterior`` (module docstring).

    Args:
        posterior: a GP of the state changes ``(D,)`` from inputs ``[a(x)[model_index], u]``.
        layout: the state layout the GP's inputs are built with.
        episodes: recorded episodes (observations ``(T+1, D)``, actions ``(T, F)``).
        noise_std: the measurement noise std ``(D,)`` (> 0).
        process_var: added to the GP's latent variance of each change, ``()`` or ``(D,)``, in the
            state's units squared.
        max_iter: L-BFGS iterations (on a unicycle run's 46 episodes 100 reach the loss of 300 to 1e-5 relative).

    Returns:
        A :class:`SmoothingResult`; episodes with no transition are returned unchanged.
    """
    device = posterior.inputs.device  # the GP's (a GPU's where the learner trains there)
    sigma = torch.as_tensor(np.asarray(noise_std, dtype=float), dtype=DTYPE, device=device)
    if sigma.ndim != 1 or bool((sigma <= 0).any()):
        raise ValueError(f"noise_std must be a positive (D,) vector, got {np.asarray(noise_std)!r}")
    q = torch.as_tensor(np.broadcast_to(np.asarray(process_var, dtype=float), sigma.shape).copy(), dtype=DTYPE, device=device)
    used = [i for i, ep in enumerate(episodes) if linked_steps(ep) > 0]
    lengths = [linked_steps(episodes[i]) for i in used]
    Y = torch.cat([torch.as_tensor(episodes[i].observations[:n + 1], dtype=DTYPE, device=device) for i, n in zip(used, lengths)])
    U = torch.cat([torch.as_tensor(episodes[i].actions[:n], dtype=DTYPE, device=device) for i, n in zip(used, lengths)])
    # rows of the stacked states that start / end a linked transition
    starts, ends, offset = [], [], 0
    for n in lengths:
        starts.append(torch.arange(offset, offset + n, device=device))
        ends.append(torch.arange(offset + 1, offset + n + 1, device=device))
        offset += n + 1
    start, end = torch.cat(starts), torch.cat(ends)

    def inputs(X: torch.Tensor) -> torch.Tensor:
        return torch.cat([layout.augment(X[start])[:, layout.model_index], U], dim=1)

    with torch.no_grad():
        s = (predict_latent(posterior, inputs(Y))[1].clamp_min(0.0) + q).sqrt()  # fixed at the observations' inputs

    def scaled(X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The objective's two kinds of residual, each over its std: observation, dynamics."""
        return (Y - X) / sigma, (X[end] - X[start] - predictive_mean(posterior, inputs(X))) / s

    def loss_of(observation: torch.Tensor, dynamics: torch.Tensor) -> torch.Tensor:
        return 0.5 * (observation ** 2).sum() + 0.5 * (dynamics ** 2).sum()

    X = Y.clone().requires_grad_(True)
    optimiser = torch.optim.LBFGS([X], lr=1.0, max_iter=max_iter, history_size=20, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-9, tolerance_change=1e-12)

    def closure() -> torch.Tensor:
        optimiser.zero_grad()
        loss = loss_of(*scaled(X))
        loss.backward()
        return loss

    optimiser.step(closure)
    with torch.no_grad():
        X = X.detach()
        observation, dynamics = scaled(X)
        loss = float(loss_of(observation, dynamics))
        observation_rms = (observation ** 2).mean(0).sqrt().cpu().numpy()
        residual_rms = (dynamics ** 2).mean(0).sqrt().cpu().numpy()
        X = X.cpu()
    out = list(episodes)
    offset = 0
    for i, n in zip(used, lengths):
        obs = episodes[i].observations.copy()
        obs[:n + 1] = X[offset:offset + n + 1].numpy()
        out[i] = replace(episodes[i], observations=obs)
        offset += n + 1
    return SmoothingResult(out, observation_rms, residual_rms, loss)


def smooth_and_refit(
    model: GPModel,
    refit: Callable[[np.ndarray, np.ndarray], GPModel],
    layout: StateLayout,
    episodes: Sequence[Episode],
    noise_std: np.ndarray,
    rounds: int = 2,
    process_var: float | np.ndarray = 0.0,
    max_iter: int = 100,
) -> tuple[GPModel, list[SmoothingResult]]:
    """``rounds`` of: smooth ``episodes`` through the current GP (starting from ``model``, trained on the
    observations), then ``refit(inputs, targets)`` a GP on the smoothed transitions. Returns the last GP
    and each round's :class:`SmoothingResult` (every round smooths the original observations)."""
    results = []
    for _ in range(rounds):
        result = smoothed_states(model.posterior(), layout, episodes, noise_std, process_var, max_iter)
        results.append(result)
        model = refit(*transitions(result.episodes, layout))
    return model, results
