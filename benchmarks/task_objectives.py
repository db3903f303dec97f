"""PILCO objectives J(theta) at the sizes of the real tasks, for timing (no sys.path changes here).

:func:`task_objective` builds the objective the ``pilco`` learner optimises on a task: the task's
preset controller (RBF or linear, fresh from its seed), state layout, cost, ``N(mu0, Sigma0)`` and a
planning horizon, with a dynamics GP on ``n`` transitions from uniformly random rollouts of the
real task. The GP's hyperparameters are set from the data's scales instead of being fitted
(length-scale = input std, signal std = target std, noise = signal / 100): they do not change the
cost of an evaluation, and both sides of a before/after comparison get the same model whatever
their GP-fitting code.

The packages under test (``harness``, ``plugins``, ``tasks``) are imported from wherever
``sys.path`` finds them first, so ``benchmarks/compare_objective.py`` can load this file by path in
a subprocess whose ``PYTHONPATH`` is another checkout.
"""

from __future__ import annotations

import numpy as np
import torch

#: name -> (task, options, basis points n, planning horizon): the learner's largest settings
#: (FITC with 300 / 400 pseudo-inputs: moment matching then works on n basis points)
TASK_CONFIGS: dict[str, tuple[str, dict[str, str], int, int]] = {
    "unicycle n=300 H=40": ("unicycle", {"init": "code"}, 300, 40),
    "double-pendulum n=400 H=60": ("double-pendulum", {"horizon": "60"}, 400, 60),
}


def task_objective(task_name: str, options: dict[str, str], n: int, horizon: int, seed: int = 0):
    """The ``pilco`` learner's :class:`~plugins.pilco.objective.PolicyObjective` on ``task_name``
    with a full GP on ``n`` random-rollout transitions and a ``horizon``-step J."""
    from harness.discovery import load_task
    from plugins.pilco.gp import full_posterior
    from plugins.pilco.learner import Pilco
    from plugins.pilco.objective import PolicyObjective

    task = load_task(task_name)(**options)
    spec = task.spec
    learner = Pilco(spec, {}, seed)
    X, Y, log_ell, log_alpha, log_sigma = random_rollout_data(task, learner.layout, n, seed)
    posterior = full_posterior(X, Y, log_ell, log_alpha, log_sigma)
    new_controller = getattr(learner, "new_controller", None) or learner._new_controller  # private before c2cb20b
    controller = new_controller(torch.Generator().manual_seed(seed))
    return PolicyObjective(controller, posterior, learner.layout, spec.cost, spec.init_mean, spec.init_cov, horizon)


def random_rollout_data(task, layout, n: int, seed: int = 0):
    """``X (n, d)``, ``Y (n, E)`` from uniformly random rollouts of ``task`` (the GP's inputs and targets
    under ``layout``), and log-hyperparameters from the data's scales: ``log_ell (E, d)`` (input std),
    ``log_alpha (E,)`` (target std), ``log_sigma = log_alpha - log 100``."""
    from harness.interaction import Interaction
    try:
        from plugins.pilco.policy import transitions
    except ImportError:  # checkouts before bd21f51 (the round's start, ea6efdd) kept it in the learner module
        from plugins.pilco.learner import transitions
    from plugins.random_learner import UniformRandomPolicy

    spec = task.spec
    interaction = Interaction(task.make_env(), spec, seed=seed)
    explore = UniformRandomPolicy(spec.action_low, spec.action_high, seed)
    x = np.zeros((0, 1))
    while x.shape[0] < n:
        interaction.rollout(explore)
        x, y = transitions(interaction.episodes, layout)
    X, Y = torch.as_tensor(x[:n]), torch.as_tensor(y[:n])
    e = Y.shape[1]
    log_ell = torch.log(X.std(0).clamp_min(1e-3)).expand(e, X.shape[1]).clone()
    log_alpha = torch.log(Y.std(0).clamp_min(1e-6))
    return X, Y, log_ell, log_alpha, log_alpha - np.log(100.0)
