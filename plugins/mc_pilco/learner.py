"""MC-PILCO as a harness learner: PILCO's model and controllers, policies judged by particles.

Amadio, Dalla Libera, Antonello, Nikovski, Carli, Romeres: "Model-Based Policy Search Using Monte
Carlo Gradient Estimation with Real Systems Application", IEEE T-RO 2022::

    init: random rollouts (the PILCO preset's number and scale)               -> interaction
    repeat:
        learn the GP dynamics model on all data (PILCO's GPModel and preset)   -> plugins.pilco.gp
        policy search: Adam on the particle estimate of J, with dropout        -> particles, optimise
        hand the policy over (the harness evaluates it here)                   -> yield
        apply it for one trial and record the data                             -> interaction

A third party's learner in all but location: it uses the plugin API (:mod:`harness.learner`) and
PILCO's library (GP model, controllers, presets, state layout, the transitions the GP learns), not
PILCO's learner. Its differences from ``pilco``: the policy evaluation (particles instead of moment
matching; no Gaussian approximation of the state distribution), the optimiser (Adam on a noisy
estimate instead of L-BFGS on a closed form), dropout on the RBF policy's weights during the
search, the RBF centres' initialisation (spread over the state space, as MC-PILCO's, instead of
drawn from the initial state distribution; option ``centres``), and as options MC-PILCO's random
initial weights (``target_scale``), MC-PILCO's own planning cost for the task (``cost=paper``,
:mod:`plugins.mc_pilco.costs`) and a planning cost that narrows from trial to trial
(``cost_narrowing``; the PILCO paper's remark on wider widths early).
Paper defaults: 400 particles, Adam with learning rate 0.01, dropout 0.25 reduced by 0.125 as the
search stalls, at most 1500 steps per trial (cart-pole: 2000-4000).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from harness.errors import OptionError
from harness.interaction import Interaction
from harness.learner import Learner, Policy
from harness.learner_logs import Logs, Timing
from harness.options import Option
from harness.task import Episode, TaskSpec
from harness.threads import run_threads
from plugins.pilco.gp_data import GP_DATA_OPTIONS, check_gp_data, train_dynamics
from plugins.pilco.horizon import GROW_HORIZON_ON, HorizonSchedule
from plugins.pilco.presets import GENERIC, PRESETS, preset_with

#: below this largest kernel value (of 1) between the RBF centres and the mean start state, a fresh run warns
#: that its policy starts near 0 there (the unicycle's spread centres: 0.0016 in 10 dimensions; cart-pole's 0.43)
FAR_CENTRES = 0.01

if TYPE_CHECKING:
    import torch

    from plugins.mc_pilco.costs import StateCost
    from plugins.mc_pilco.optimise import ParticleSearchResult
    from plugins.mc_pilco.particles import ParticleObjective
    from plugins.pilco.controllers import SquashedController
    from plugins.pilco.cost import CostMoments
    from plugins.pilco.gp import GPModel
    from plugins.pilco.posterior import GPPosterior


class McPilco(Learner):
    """MC-PILCO: PILCO's GP model and controllers, a particle estimate of J, Adam with dropout."""

    name = "mc-pilco"
    description = "MC-PILCO: PILCO's GP model, policy cost by particles with reparameterised gradients (Amadio et al., T-RO 2022)"
    supports_resume = True
    logs = Logs(
        shown=(("J_after", "J"),),
        timings=(Timing("model_train_seconds", "model_training", "GP training", "GP"),
                 Timing("policy_opt_seconds", "policy_search", "policy search", "policy")),
        policy_size="policy_parameters",
    )
    options = (
        Option("controller", str, None, "policy: rbf or linear (default: the PILCO task preset)", choices=(None, "rbf", "linear")),
        Option("num_centres", int, None, "RBF centres (default: the PILCO task preset)", low=1),
        Option("squash", str, "trapezoid", "squashing to the bounds", choices=("trapezoid", "sin")),
        Option("centres", str, "spread", "initial RBF centres: spread (MC-PILCO's: states uniform in +-pi per entry, angles "
               "over the circle) or initial (PILCO's reference: drawn from the initial state distribution, where they nearly "
               "coincide and the particle estimate of J is rough in the policy's parameters)", choices=("spread", "initial")),
        Option("target_scale", float, None, "with spread centres: initial RBF targets uniform in +-target_scale (the "
               "squashing's argument; MC-PILCO's random weights of +-u_max/2 are about 0.5) instead of PILCO's 0.1 randn "
               "(default)", low=0.0),
        Option("initial_rollouts", int, None, "random rollouts before learning (default: the PILCO task preset)", low=1),
        Option("random_scale", float, None, "random controls in scale * bounds (default: the PILCO task preset)", low=0.0, high=1.0),
        Option("planning_horizon", int, None, "simulated steps per particle (default: the PILCO preset's, else the task horizon)", low=1),
        Option("grow_horizon_below", float, 0.0, "double the planning horizon (up to the task's) when the rule grow_horizon_on "
               "judges the policy good over the shorter one against this threshold, cost per step (PILCO's horizon "
               "schedule, plugins.pilco.horizon; 0 = off, the default)", low=0.0),
        GROW_HORIZON_ON,
        Option("cost_width", float, None, "cost width used in planning (default: the PILCO preset's, else the task's)", low=1e-6),
        Option("cost", str, "task", "planning cost: task (the task's cost at the planning width) or paper (MC-PILCO's own "
               "for the task, plugins.mc_pilco.costs; cart-pole: 1-exp(-((|theta|-pi)/3)^2-(x/1)^2) with theta unwrapped, "
               "which also charges a pole spun past upright)", choices=("task", "paper")),
        Option("cost_narrowing", float, 1.0, "the planning width of trial t is max(task width, cost_width * cost_narrowing^(t-1)): "
               "a wide cost that gives the first searches a signal far from the target (a spinning pole) and narrows to "
               "the task's, which asks for the precise balance (1: no narrowing)", low=1e-3, high=1.0),
        Option("sparse_threshold", int, None, "FITC above this many data points (default: the PILCO task preset)", low=1),
        Option("planning_basis", int, None, "particles go through a FITC posterior on at most this many of the model's basis "
               "points (chosen greedily where they explain the kernel at the data best; same hyperparameters and data), "
               "as MC-PILCO's own subset-of-data GP keeps the search's cost down: an Adam step's cost grows with their "
               "square (default: all)", low=1),
        Option("gp_max_evals", int, 300, "GP hyperparameter L-BFGS evaluations per trial", low=0),
        *GP_DATA_OPTIONS,
        Option("gp_fitc_evals", int, 100, "FITC pseudo-input L-BFGS evaluations per trial (3x the first time)", low=0),
        Option("particles", int, 400, "particles per estimate of J (paper: 400)", low=1),
        Option("max_steps", int, 1500, "Adam steps per policy search at most (paper: 1500; cart-pole 2000-4000)", low=1),
        Option("lr", float, 0.01, "Adam learning rate at the start of each search (paper: 0.01)", low=1e-8),
        Option("dropout", float, 0.25, "dropout probability on the RBF weights at the start of each search (paper: 0.25)",
               low=0.0, high=0.9),
        Option("dropout_step", float, 0.125, "dropout reduction when the search stalls (paper: 0.125)", low=0.0, high=1.0),
        Option("lr_decay", float, 0.5, "learning-rate factor at each dropout reduction", low=0.0, high=1.0),
        Option("lr_reductions", int, 0, "stalls at dropout 0 that multiply the learning rate by lr_decay before the next one "
               "ends the search (0: the first ends it, the paper's rule)", low=0),
        Option("keep", str, "last", "the policy a search hands over: last (the last Adam step's, the paper's) or best (of the "
               "start and each window's end, the one a fixed set of particles rates lowest: a search that ends above where it "
               "started hands over its start)", choices=("last", "best")),
        Option("revert", bool, False, "with keep=best: a window whose end the fixed particles do not rate below the best so "
               "far sends the search back to the best, Adam restarted at lr * lr_decay, as one of lr_reductions; once they "
               "are used up, such a window ends the search (default off, the paper's search)"),
        Option("lr_growth", float, 1.0, "with revert: a window end the fixed particles rate below the best so far multiplies "
               "the learning rate by this, up to lr (a trust region: the rate halved by a backtrack grows again while the "
               "search descends; 1 = off, the paper's search)", low=1.0),
        Option("step_scale", str, "none", "the units Adam steps the policy's parameters in (it moves each by about the "
               "learning rate whatever its gradient): none (each in its own, the paper's) or inputs (a weight on policy input "
               "j in units of 1/std_j, an RBF centre's coordinate j in units of std_j, std_j the spread of input j over every "
               "observation recorded so far; the rest in their own): a linear policy's weight on a fast state (the unicycle's "
               "wheel rate, std ~9 rad/s) otherwise changes the control ~40x as much per step as one on an angle (~0.2 rad)",
               choices=("none", "inputs")),
        Option("window", int, 100, "steps per window of the monitoring signal (mean estimate)", low=1),
        Option("min_improvement", float, 0.01, "a window mean at least this much (relative) below the one before is progress", low=0.0),
        Option("threads", int, None, "CPU threads (default: the harness's choice; harness.threads)", low=1, execution=True),
        Option("device", str, "cpu", "where the GP is trained and the particles run: cpu, cuda (a GPU) or auto (cuda where "
               "torch sees one)", choices=("cpu", "cuda", "auto"), execution=True),
        Option("cuda_graph", bool, True, "on a GPU, capture an Adam step's J_hat and gradient as a CUDA graph (one per "
               "dropout value per search) and replay it (false: launch every operation each step)", execution=True),
    )

    def __init__(self, spec: TaskSpec, options: dict[str, Any] | None = None, seed: int = 0) -> None:
        from plugins.pilco.policy import layout_for

        super().__init__(spec, options, seed)
        o = self.options
        preset = PRESETS.get(spec.name, GENERIC)
        self.preset = preset_with(spec.name, o)
        try:
            self.layout = layout_for(spec, self.preset)
        except ValueError as exc:
            raise OptionError(f"mc-pilco on {spec.name}: {exc}") from None
        check_gp_data(o, spec)
        if o["target_scale"] is not None and (o["centres"] != "spread" or self.preset.controller != "rbf"):
            raise OptionError(f"mc-pilco on {spec.name}: target_scale sets the initial targets of an RBF policy with spread "
                              "centres; drop it, or use controller=rbf with centres=spread")
        if o["revert"] and o["keep"] != "best":
            raise OptionError("mc-pilco: revert=true goes back to the best parameters of a search, which only keep=best "
                              "tracks: add --set learner.keep=best, or drop revert")
        if o["lr_growth"] > 1.0 and not o["revert"]:
            raise OptionError("mc-pilco: lr_growth raises the learning rate after a window that set a new best, which needs "
                              "revert=true to back out of an overshoot: add --set learner.revert=true --set learner.keep=best, "
                              "or drop lr_growth")
        if o["cost"] == "paper":
            from plugins.mc_pilco.costs import PAPER_COSTS

            if spec.name not in PAPER_COSTS:
                raise OptionError(f"mc-pilco on {spec.name}: the MC-PILCO paper defines no planning cost for this task "
                                  f"(cost=paper is there for {', '.join(sorted(PAPER_COSTS))}); use cost=task")
            if o["cost_width"] is not None or o["cost_narrowing"] != 1.0:
                raise OptionError(f"mc-pilco on {spec.name}: cost_width and cost_narrowing set the width of the task's "
                                  "cost; cost=paper has its own length-scales: drop them, or use cost=task")
        self.schedule = HorizonSchedule(o["planning_horizon"] or preset.planning_horizon or spec.horizon, spec.horizon,
                                        o["grow_horizon_below"] or None, o["grow_horizon_on"])
        self.cost_width = o["cost_width"] or preset.cost_width
        from plugins.pilco.learner import resolve_device

        self.device = resolve_device(o["device"])
        self._state: dict[str, Any] = {}

    @property
    def horizon(self) -> int:
        """The current planning horizon, steps (:attr:`schedule` grows it where ``grow_horizon_below`` is set)."""
        return self.schedule.horizon

    def planning_width(self, trial: int) -> float:
        """The planning cost's width at trial ``trial`` (1, 2, ...): option ``cost_width`` (else the preset's,
        else the task's), narrowed by ``cost_narrowing`` per trial down to the task's width, never below it
        (a width set below the task's is kept as set)."""
        task_width = float(self.spec.cost.width)
        start = float(self.cost_width or task_width)
        return max(min(task_width, start), start * self.options["cost_narrowing"] ** (trial - 1))

    def planning_cost(self, trial: int) -> CostMoments | StateCost:
        """The cost trial ``trial``'s search plans with: the task's at :meth:`planning_width`, or with option
        ``cost=paper`` the MC-PILCO paper's for the task (:data:`plugins.mc_pilco.costs.PAPER_COSTS`).
        Either has ``sample(x)``: the cost at states ``(..., D)`` as a torch tensor."""
        from plugins.pilco.cost import CostMoments

        if self.options["cost"] == "paper":
            from plugins.mc_pilco.costs import PAPER_COSTS

            return PAPER_COSTS[self.spec.name]
        return CostMoments(self.spec.cost, self.planning_width(trial), self.device)

    def new_model(self) -> GPModel:
        """The GP dynamics model as this learner trains it (PILCO's, with the task preset's FITC threshold)."""
        from plugins.pilco.gp import GPModel

        o = self.options
        return GPModel(device=self.device, sparse_threshold=self.preset.sparse_threshold, num_pseudo=self.preset.sparse_threshold,
                       max_evals_full=o["gp_max_evals"], max_evals_fitc=o["gp_fitc_evals"])

    def step_scales(self, controller: SquashedController, episodes: Sequence[Episode],
                    mode: str | None = None) -> list[torch.Tensor] | None:
        """Option ``step_scale``'s units for Adam (``mode`` instead of the option, if given), one tensor per
        trainable parameter of ``controller`` (its shape, on its device), from the policy inputs of every
        observation in ``episodes``; ``None`` for ``none``. Inputs that never varied get scale 1."""
        import torch

        mode = self.options["step_scale"] if mode is None else mode
        if mode not in ("none", "inputs"):
            raise OptionError(f"step_scale {mode!r}: choose none or inputs")
        if mode == "none":
            return None
        params = [(name, p) for name, p in controller.named_parameters() if p.requires_grad]
        observations = np.concatenate([np.asarray(ep.observations, dtype=np.float64) for ep in episodes])
        inputs = self.layout.augment(torch.as_tensor(observations))[:, self.layout.policy_index]
        std = inputs.std(dim=0) if inputs.shape[0] > 1 else torch.ones(inputs.shape[1], dtype=torch.float64)
        std = torch.where(std > 1e-12, std, torch.ones_like(std))
        scales = []
        for name, p in params:
            leaf = name.rsplit(".", 1)[-1]
            if leaf == "weight":  # LinearController (F, p): u = W x + b
                scale = (1.0 / std).expand(p.shape[0], -1)
            elif leaf == "centres":  # RBFController (n_c, p)
                scale = std.expand(p.shape[0], -1)
            else:
                scale = torch.ones(p.shape, dtype=torch.float64)
            scales.append(scale.to(p.device).clone())
        return scales

    def search_trial(self, controller: SquashedController, posterior: GPPosterior, trial: int,
                     episodes: Sequence[Episode] | None = None) -> tuple[ParticleObjective, ParticleSearchResult]:
        """Trial ``trial``'s policy search: Adam on the particle estimate of J through ``posterior`` (a fixed
        model on the controller's device) with this learner's options, from ``controller``'s parameters
        (changed in place). Its random draws are seeded by ``(seed, trial)``. ``episodes``: the data so far,
        for option ``step_scale=inputs`` (required there). Returns the objective and the search's outcome."""
        import torch

        from plugins.mc_pilco.optimise import optimise_particles
        from plugins.mc_pilco.particles import ParticleObjective

        spec, o, device = self.spec, self.options, self.device
        init_mean = torch.as_tensor(np.asarray(spec.init_mean, dtype=np.float64), device=device)
        init_cov = torch.as_tensor(np.asarray(spec.init_cov, dtype=np.float64), device=device)
        cost = self.planning_cost(trial)
        objective = ParticleObjective(controller, posterior, self.layout, cost, init_mean, init_cov,
                                      self.horizon, o["particles"], cuda_graph=o["cuda_graph"])

        def shown(step: int, mean: float, dropout: float) -> None:
            where = f", J_hat {mean:.2f} (mean of the last {o['window']})" if math.isfinite(mean) else ""
            self.report_status(f"policy search: Adam step {step}/{o['max_steps']}{where}, dropout {dropout:g}")

        if o["step_scale"] != "none" and episodes is None:
            raise ValueError("search_trial: step_scale=inputs needs the episodes recorded so far (argument episodes)")
        scales = None if episodes is None else self.step_scales(controller, episodes)
        search = optimise_particles(objective, max_steps=o["max_steps"], lr=o["lr"], dropout=o["dropout"],
                                    dropout_step=o["dropout_step"], lr_decay=o["lr_decay"], window=o["window"],
                                    min_improvement=o["min_improvement"], seed=1000 * self.seed + trial, keep=o["keep"],
                                    lr_reductions=o["lr_reductions"], revert=o["revert"], lr_growth=o["lr_growth"],
                                    step_scales=scales, on_step=shown)
        return objective, search

    @classmethod
    def default_limits(cls, spec: TaskSpec) -> tuple[int | None, float | None]:
        """The PILCO task preset's number of trials."""
        return PRESETS.get(spec.name, GENERIC).max_trials, None

    def new_controller(self, generator: torch.Generator) -> SquashedController:
        """The initial controller drawn with ``generator`` (a run's is seeded by its seed): the PILCO task
        preset's, with its RBF centres spread over the state space (option ``centres``)."""
        from plugins.pilco.policy import initial_controller

        spread = math.pi if self.options["centres"] == "spread" else None
        return initial_controller(self.spec, self.preset, self.layout, self.options["squash"], generator, spread=spread,
                                  target_scale=self.options["target_scale"] if spread is not None else None)

    def start_kernel(self, controller: SquashedController) -> float | None:
        """The largest kernel value between the RBF policy's centres and the mean start state (its policy
        input), in ``[0, 1]``: near 0, every centre is far from where the runs start, so the controls and
        their gradients there start near 0. ``None`` for a linear policy."""
        import torch

        from plugins.pilco.controllers import RBFController
        from plugins.pilco.kernels import se_ard

        if not isinstance(controller.base, RBFController):
            return None
        post = controller.base.posterior()
        mean = torch.as_tensor(np.asarray(self.spec.init_mean, dtype=np.float64), device=post.inputs.device)[None]
        inputs = self.layout.augment(mean)[:, self.layout.on("policy_index", mean.device)]
        with torch.no_grad():
            k = se_ard(inputs, post.inputs, post.log_ell, post.log_alpha) / torch.exp(2.0 * post.log_alpha)[:, None, None]
        return float(k.max())

    def learn(self, interaction: Interaction) -> Iterator[Policy]:
        import torch

        from plugins.pilco.gp import GPHyperparameters
        from plugins.pilco.policy import PilcoPolicy, cpu_state_dict
        from plugins.random_learner import UniformRandomPolicy

        spec, o = self.spec, self.options
        torch.set_num_threads(o["threads"] or run_threads())
        device = self.device
        model = self.new_model()
        controller = self.new_controller(torch.Generator().manual_seed(self.seed))
        controller.to(device)
        resumed = self._resume_state
        reach = self.start_kernel(controller) if resumed is None else None
        if reach is not None and reach < FAR_CENTRES:
            warnings.warn(f"mc-pilco: the RBF policy's centres are far from the start states (largest kernel value at the "
                          f"start mean {reach:.2g} < {FAR_CENTRES}): its controls and their gradients start near 0 there; "
                          "--set learner.centres=initial draws the centres from the start distribution", stacklevel=1)
        if resumed is None:
            scale = self.preset.random_scale
            explore = UniformRandomPolicy(scale * spec.action_low, scale * spec.action_high, self.seed)
            for _ in range(self.preset.initial_rollouts):
                interaction.rollout(explore)
            hyperparameters, trial = None, 0
        else:  # continue right after the hand-over of trial `trial`
            controller.load_state_dict(resumed["controller"])  # copied onto the controller's device
            hyperparameters, trial = GPHyperparameters.from_dict(resumed["hyperparameters"]), resumed["trial"]
            self.schedule.horizon = resumed.get("planning_horizon", self.horizon)
        graph_warned = False
        while True:
            realised = None
            if trial > 0:  # apply the policy handed over last for one trial, record the data
                episode = interaction.rollout(PilcoPolicy.snapshot(controller, self.layout))
                realised = self.schedule.after_rollout(episode)  # the survival and realised rules
            trial += 1
            fit, smoothing = train_dynamics(model, interaction.episodes, self.layout, o, spec.measurement_noise_std,
                                            hyperparameters, self.report_status, seed=self.seed + trial)
            hyperparameters = model.hyperparameters
            posterior = model.posterior(max_basis=o["planning_basis"]).detach()
            objective, search = self.search_trial(controller, posterior, trial, interaction.episodes)
            self.metrics = {
                "n_data": float(fit.n_points), "gp_sparse": float(fit.sparse), "gp_nll": fit.nll,
                "model_train_seconds": fit.seconds, "J_before": search.J_before, "J_after": search.J_after,
                "J_last": search.J_last, "kept_step": float(search.kept_step),
                "policy_opt_seconds": search.seconds, "policy_steps": float(search.steps),
                "policy_skipped_steps": float(search.skipped), "dropout_reductions": float(search.reductions),
                "lr_reductions": float(search.lr_reductions), "reverts": float(search.reverts),
                "lr_growths": float(search.growths),
                "final_dropout": search.final_dropout, "planning_horizon": float(self.horizon), "planning_basis": float(posterior.inputs.shape[0]),
                "policy_parameters": float(sum(p.numel() for p in controller.parameters())),
            } | smoothing
            if o["cost"] == "task":
                self.metrics["cost_width"] = objective.cost.width
            if objective.cuda_graph and device.type == "cuda":  # replayed as a CUDA graph (1) or launched op by op (0)?
                self.metrics["cuda_graph"] = float(objective.graph_error is None)
                if objective.graph_error is not None and not graph_warned:
                    graph_warned = True
                    warnings.warn(f"mc-pilco: an Adam step could not be captured as a CUDA graph ({objective.graph_error}); "
                                  "every step launches its operations one by one (slower; metric cuda_graph = 0)", stacklevel=1)
            if not math.isfinite(search.J_after):
                self.metrics["policy_search_failed"] = 1.0
            if realised is not None:  # the previous policy's recorded episode, mean cost per step over its planned horizon
                self.metrics["rollout_cost_per_step"] = realised
            self.schedule.after_search(search)  # the prediction rule (a failed search's non-finite J: no growth)
            self._state = {"controller": cpu_state_dict(controller), "hyperparameters": hyperparameters.to("cpu").as_dict(),
                           "trial": trial, "planning_horizon": self.horizon}
            yield PilcoPolicy.snapshot(controller, self.layout)

    def state_dict(self) -> dict[str, Any]:
        """Controller parameters, GP hyperparameters (warm start, as plain tensors) and the trial; every
        random draw of a trial's search is seeded by ``(seed, trial)``, so nothing else is needed to
        continue exactly."""
        return self._state

    @classmethod
    def policy_state(cls, policy: Policy) -> dict[str, Any]:
        """PILCO's controllers, saved as PILCO saves them (:func:`~plugins.pilco.policy.pilco_policy_state`)."""
        from plugins.pilco.policy import pilco_policy_state

        return pilco_policy_state(policy)

    @classmethod
    def policy_from_state(cls, state: dict[str, Any], spec: TaskSpec) -> Policy:
        from plugins.pilco.policy import pilco_policy_from_state

        return pilco_policy_from_state(state, spec)
