"""What the dynamics GP is trained on, for any learner built on the PILCO core: the options and one training step.

``gp_data=observations`` (the reference) trains the GP on the recorded transitions as they are.
``gp_data=smoothed`` then smooths every episode through that GP and trains it again on the state
estimates, ``smooth_rounds`` times (:func:`plugins.pilco.smoothing.smooth_and_refit`): the measurement
noise, in the inputs and with the opposite sign in the difference targets, otherwise teaches the GP a
pull back to its data (``results/findings_unicycle.md``).

A learner declares :data:`GP_DATA_OPTIONS` among its options, checks them against its task with
:func:`check_gp_data` when it is built, and calls :func:`train_dynamics` once per trial; ``pilco`` and
``mc-pilco`` do. This module imports torch only when it trains (``harness list``
reads the options without it).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from harness.errors import OptionError
from harness.options import Option
from harness.task import Episode, TaskSpec

if TYPE_CHECKING:
    from plugins.pilco.gp import FitReport, GPHyperparameters, GPModel
    from plugins.pilco.propagate import StateLayout

GP_DATA_OPTIONS = (
    Option("gp_data", str, "observations", "what the dynamics GP is trained on: the recorded observations (the "
           "reference), or smoothed: state estimates, each episode smoothed through the GP trained on the observations "
           "and the GP trained again on them (smooth_rounds times; plugins.pilco.smoothing): the measurement noise, "
           "in the inputs and with the opposite sign in the difference targets, otherwise teaches the GP a pull back to "
           "its data (results/findings_unicycle.md)", choices=("observations", "smoothed")),
    Option("smooth_rounds", int, 2, "gp_data=smoothed: rounds of smoothing the episodes and training the GP again", low=1),
    Option("smooth_process_std", float, 1.0, "gp_data=smoothed: the smoother's allowance for the GP's error per step "
           "beyond its own variance, as a multiple of the task's measurement noise std (0: the GP's variance only, which "
           "sent the unicycle's first policy search on 10 random rollouts to a saturated policy: results/findings_unicycle.md)",
           low=0.0),
)


def check_gp_data(options: Mapping[str, Any], spec: TaskSpec) -> None:
    """Raise :class:`~harness.errors.OptionError` when ``options`` ask for smoothed states on a task whose
    observations are not noisy in every entry: the smoother weighs each entry by its noise std, and there is
    no noise to take out (at construction, instead of a ``ValueError`` after the first trial's fit)."""
    noise = np.asarray(spec.measurement_noise_std, dtype=float)
    if options["gp_data"] == "smoothed" and not bool((noise > 0).all()):
        raise OptionError(f"gp_data=smoothed on {spec.name}: the task's measurement noise std is {noise.tolist()}, and "
                          "smoothing needs noise on every state entry (set task.measurement_noise > 0, or gp_data=observations)")


def train_dynamics(
    model: GPModel,
    episodes: Sequence[Episode],
    layout: StateLayout,
    options: Mapping[str, Any],
    noise_std: np.ndarray,
    warm_start: GPHyperparameters | None,
    status: Callable[[str], None] = lambda message: None,
    **fit_kwargs: Any,
) -> tuple[FitReport, dict[str, float]]:
    """Train ``model`` on ``episodes`` as ``options`` (:data:`GP_DATA_OPTIONS`) say; ``fit_kwargs`` (e.g.
    ``seed``, ``restarts``) go to every :meth:`~plugins.pilco.gp.GPModel.fit`, the first warm-started from
    ``warm_start``, each refit from the fit before. ``noise_std`` ``(D,)``: the task's measurement noise std.

    Returns the last fit's report (its ``seconds`` those of every fit and smoothing) and the smoothing's
    metrics (none with ``gp_data=observations``): ``smoothing_obs_rms`` (rms of estimate - observation over
    the noise std, all entries; 1 if the estimates were the true states,
    :class:`~plugins.pilco.smoothing.SmoothingResult`), ``smoothing_residual_rms`` (rms of the dynamics
    residuals over their allowed std) and ``smoothing_seconds`` (wall seconds of the smoothing itself, the
    refits not included)."""
    from plugins.pilco.policy import transitions

    x, y = transitions(episodes, layout)
    status(f"GP training on {x.shape[0]} transitions")
    fit = model.fit(x, y, warm_start=warm_start, **fit_kwargs)
    if options["gp_data"] == "observations":
        return fit, {}
    from plugins.pilco.smoothing import smooth_and_refit

    status(f"smoothing {len(episodes)} episodes through the GP ({options['smooth_rounds']} rounds)")
    t0, fits = time.perf_counter(), []

    def refit(inputs: np.ndarray, targets: np.ndarray) -> GPModel:
        fits.append(model.fit(inputs, targets, warm_start=model.hyperparameters, **fit_kwargs))
        return model

    _, rounds = smooth_and_refit(model, refit, layout, episodes, noise_std, options["smooth_rounds"],
                                 (options["smooth_process_std"] * np.asarray(noise_std)) ** 2)
    seconds = time.perf_counter() - t0
    metrics = {"smoothing_obs_rms": float(np.sqrt(np.mean(rounds[-1].observation_rms ** 2))),
               "smoothing_residual_rms": float(np.sqrt(np.mean(rounds[-1].residual_rms ** 2))),
               "smoothing_seconds": seconds - sum(f.seconds for f in fits)}
    return replace(fits[-1], seconds=fit.seconds + seconds), metrics
