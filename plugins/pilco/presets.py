"""PILCO's per-task settings (reference ``settings_*.m``): plain data, no torch.

A learner built on PILCO's library (``pilco``, ``pilco-mean``, ``mc-pilco``) starts from the task's
:class:`Preset` (:data:`PRESETS`, else :data:`GENERIC`) and overrides entries with its options
(:func:`preset_with`). Kept free of heavy imports: ``harness list`` loads the learners that read it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any


@dataclass(frozen=True)
class Preset:
    """Per-task PILCO settings (reference ``settings_*.m`` unless noted).

    ``model_exclude``/``policy_exclude``: augmented-state indices hidden from the GP / policy
    (the raw angles are always replaced by their sin/cos). ``planning_horizon`` (steps; ``None``:
    the task's horizon) and ``cost_width`` (metres; ``None``: the task's) set what J is computed
    over; the task's own cost and horizon still score every evaluation. ``fresh_start_tol``: the
    default of the learner option of that name (``None``: off); ``restart_tol`` likewise.

    ``horizon_schedule`` (``pilco`` only; ``None``: off): ``(first horizon in steps, threshold)``, the
    defaults of its options ``planning_horizon`` and ``grow_horizon_below`` (start planning over the
    first horizon, double it when the rule ``grow_horizon_on`` finds a mean cost per step below the
    threshold). ``grow_horizon_on`` and ``plan_with_noise`` (``pilco`` only): the defaults of its
    options of those names. Other learners on PILCO's library (``mc-pilco``) plan over
    ``planning_horizon`` and ignore all three.
    """

    controller: str = "rbf"
    num_centres: int = 50
    initial_rollouts: int = 1
    random_scale: float = 1.0
    sparse_threshold: int = 300
    max_trials: int = 15
    policy_max_iterations: int = 150
    policy_max_evaluations: int = 300
    model_exclude: tuple[int, ...] = ()
    policy_exclude: tuple[int, ...] = ()
    planning_horizon: int | None = None
    cost_width: float | None = None
    fresh_start_tol: float | None = None
    restart_tol: float | None = None
    horizon_schedule: tuple[int, float] | None = None
    grow_horizon_on: str = "prediction"
    plan_with_noise: bool = False


PRESETS: dict[str, Preset] = {
    # settings_cp.m; 50 centres as the paper's R^305 policy (V0.9 code: 10). Not the reference's: restarts near a stalled
    # policy (restart_tol=0.05), chosen on tuning seeds 120-139 side by side with the default on one machine, where a
    # seed's two runs part only where a restart is kept (results/findings_cartpole.md): 20/20 solved against 19/20 (seed
    # 132, stuck at J 25-31 for 15 trials without, solved at 24 s with), median 16 s both
    "cartpole": Preset(controller="rbf", num_centres=50, initial_rollouts=1, sparse_threshold=300, max_trials=15, restart_tol=0.05),
    # settings_cdp.m: 200 centres, FITC with 400 pseudo-inputs, 40 policy iterations
    "double-pendulum": Preset(controller="rbf", num_centres=200, initial_rollouts=1, sparse_threshold=400, max_trials=40),
    # settings_unicycle.m: linear policy, 10 random rollouts at u_max/5; the GP does not see the yaw
    # (dyni drops phi, observation index 8); the policy sees all 10 states
    # policy search: at most 150 J evaluations in all (settings_unicycle.m: opt.length = -150)
    # Not the reference's: PILCO plans over 20 steps (3 s), doubled to 40 and then 67 after a trial whose real
    # episode cost less than 0.2 per planned step (a fall holding its last cost), and feeds the policy the
    # measurement noise in planning (results/findings_unicycle.md). Over the whole 67 steps J stays at 55-56 of
    # 67 and no run solved (the true cost is flat from PILCO's start to within ~70 % of the way to a riding
    # controller, results/benchmarks/unicycle_local_search.md). Growing on the search's predicted J/h < 0.05
    # (the preset until 2026-11-29) solved 2 of 3 tuning seeds (100-102) and 0 of the 3 reported seeds run
    # to 40 trials (sweep e9ef9eab261a); the real-cost rule's threshold 0.2 was chosen between seeds 102's
    # and 104's values, then run on fresh tuning seeds 105-108: 3 of 4 solved (30.8, 114, 132 s)
    "unicycle": Preset(controller="linear", initial_rollouts=10, random_scale=0.2, sparse_threshold=300, max_trials=40,
                       policy_max_evaluations=150, model_exclude=(8,), horizon_schedule=(20, 0.2), grow_horizon_on="realised",
                       plan_with_noise=True),
    # dm_control: the observation already carries cos/sin of the pole angle. Not in the paper; chosen
    # by measurement (results/benchmarks/pilco_dmc_settings.md): J over the whole 10 s episode never
    # solved (seeds 0, 1: 150 s), J over 4 s (the V0.9 cart-pole horizon) solved seed 0 at trial 4;
    # the task's 0.25 m width on this 1 m pole leaves J exactly flat at the bottom (seed 1: 2 J
    # evaluations per trial, no change in 15 trials), so planning uses the paper's cart-pole
    # width-to-pole ratio, 0.25 m / 0.6 m x 1 m = 0.42 m
    # fresh_start_tol=0.05 chosen on tuning seeds 100-104 (results/findings_dmc-cartpole.md): with it 5 of 5
    # solved (seed 103 at trial 6, after the fresh search was kept at trial 5); without it seed 103 was
    # unsolved after 15 trials (J 34.8 -> 30.5 by trial 8), the other seeds identical
    "dmc-cartpole": Preset(controller="rbf", num_centres=50, initial_rollouts=1, sparse_threshold=300, max_trials=15,
                           planning_horizon=40, cost_width=0.42, fresh_start_tol=0.05),
}
GENERIC = Preset()


def preset_with(task: str, options: dict[str, Any]) -> Preset:
    """The task's preset (:data:`PRESETS`, else :data:`GENERIC`) with the options that override its
    entries and are set (not ``None``): ``controller``, ``num_centres``, ``initial_rollouts``,
    ``random_scale``, ``sparse_threshold``, ``policy_max_iterations``, ``policy_max_evaluations``
    (a learner without some of these options keeps the preset's)."""
    preset = PRESETS.get(task, GENERIC)
    fields = ("controller", "num_centres", "initial_rollouts", "random_scale", "sparse_threshold",
              "policy_max_iterations", "policy_max_evaluations")
    return replace(preset, **{k: options[k] for k in fields if options.get(k) is not None})
