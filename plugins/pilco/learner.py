"""PILCO as a harness learner (paper Algorithm 1), and the deterministic-GP-mean ablation.

    init: J random rollouts (uniform controls in the bounds)                  -> interaction
    repeat:
        learn the GP dynamics model on all data (FITC above a threshold)      -> gp.GPModel
        policy search: L-BFGS on J(theta) = sum_t E[c(x_t)] from N(mu0, S0)   -> objective, policy_search
        hand the policy over (the harness evaluates it here)                  -> yield
        apply it for one trial and record the data                            -> interaction
    until the harness stops it (solved, trial limit, budget)

``pilco-mean`` is the same learner with ``mean_only = True``: the dynamics GP's model-uncertainty
term (alpha^2 - tr((K + sigma^2 I)^-1 Q), paper eq. 23) is dropped, everything else equal (paper
§4: "we used the posterior mean function of a GP").

Per-task defaults (controller, size, initial rollouts, sparse threshold, ...) are *presets* keyed
by task name (reference ``settings_*.m``); every entry can be overridden with ``--set``. A task
without a preset gets the generic one (RBF policy, sin/cos of the spec's angles).

The presets (:mod:`plugins.pilco.presets`) are plain data; torch and PILCO's machinery (GP,
objective, search, :mod:`plugins.pilco.policy`) are imported where they run, so loading this class
(``harness list``) stays instant.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterator
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from harness.errors import NumericalError, OptionError
from harness.interaction import Interaction
from harness.learner import Learner, Policy
from harness.learner_logs import Logs, Timing, TrialFigure, save_figure
from harness.options import Option
from harness.task import Episode, TaskSpec
from harness.threads import run_threads, torch_threads
from plugins.pilco.gp_data import GP_DATA_OPTIONS, check_gp_data, train_dynamics
from plugins.pilco.horizon import GROW_HORIZON_ON, HorizonSchedule
from plugins.pilco.presets import GENERIC, PRESETS, preset_with

if TYPE_CHECKING:
    import torch

    from plugins.pilco.controllers import SquashedController
    from plugins.pilco.gp import GPModel
    from plugins.pilco.objective import PolicyObjective
    from plugins.pilco.policy import PilcoPolicy


def resolve_device(device: str) -> torch.device:
    """``cpu``, ``cuda`` or ``auto`` (``cuda`` where torch sees a GPU) as a torch device; ``cuda``
    without a GPU raises :class:`OptionError` naming the fix."""
    import torch

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise OptionError("device=cuda: torch sees no CUDA GPU here (install a CUDA build of torch, or --set device=cpu)")
    return torch.device(device)


def stalled(J: float, previous_J: float | None, predicted: float | None, realised: float | None, tol: float | None) -> bool:
    """Whether the policy search is stuck in an optimum the model is confident about (the fresh-start rule).

    True when ``tol`` is set, the search just done ended at a ``J`` within ``tol`` (relative) of the
    previous trial's, and the last trial's realised cost over the predicted steps was within ``tol``
    (relative) of its prediction: J has stopped moving, and more data of the same policy will not
    move the model. All costs are sums over the planning horizon (dimensionless, task cost units).
    """
    if tol is None or previous_J is None or predicted is None or realised is None:
        return False
    if not all(math.isfinite(v) for v in (J, previous_J, predicted, realised)):
        return False
    return abs(J - previous_J) <= tol * abs(previous_J) and abs(realised - predicted) <= tol * abs(realised)


def _predicted_sum(predicted: tuple[np.ndarray, np.ndarray] | None) -> float | None:
    """The predicted expected cost summed over the planning horizon, or None without a prediction."""
    return None if predicted is None else float(np.sum(predicted[0]))


def _realised_sum(interaction: Interaction, predicted: tuple[np.ndarray, np.ndarray] | None) -> float | None:
    """The last episode's cost over the steps a prediction covers (its first ``len(mean)`` steps). An episode
    that ended before them (a fall) holds its last cost for the steps it did not take, as evaluations count it
    (:meth:`harness.task.Episode.horizon_cost`): the prediction, too, charges the fallen states at every step."""
    if predicted is None or not interaction.episodes:
        return None
    return interaction.episodes[-1].horizon_cost(len(predicted[0]))


# ---
class Pilco(Learner):
    """PILCO (Deisenroth & Rasmussen 2011): GP dynamics, moment matching, analytic policy gradients."""

    name = "pilco"
    description = "PILCO: GP dynamics model, exact moment matching, analytic policy gradients (ICML 2011)"
    #: the ablation switch: drop the GP's model-uncertainty term in planning
    mean_only: ClassVar[bool] = False
    supports_resume = True
    logs = Logs(
        shown=(("J_after", "J"), ("J_sampled", "J sampled"), ("predicted_cost", "predicted"), ("planning_horizon", "H", ".0f")),
        timings=(Timing("model_train_seconds", "model_training", "GP training", "GP"),
                 Timing("policy_opt_seconds", "policy_search", "policy search", "policy")),
        policy_size="policy_parameters",
        trial_figure=TrialFigure("prediction_trial*.png", "prediction"),
    )
    options = (
        Option("controller", str, None, "policy: rbf or linear (default: task preset)", choices=(None, "rbf", "linear")),
        Option("num_centres", int, None, "RBF centres (default: task preset)", low=1),
        Option("squash", str, "trapezoid", "squashing to the bounds", choices=("trapezoid", "sin")),
        Option("initial_rollouts", int, None, "random rollouts before learning (default: task preset)", low=1),
        Option("random_scale", float, None, "random controls in scale * bounds (default: task preset)", low=0.0, high=1.0),
        Option("planning_horizon", int, None, "predicted steps in J (default: the task preset's (unicycle: 20, growing), else "
               "the task horizon)", low=1),
        Option("cost_width", float, None, "cost width used in planning (default: the task preset's, else the task's)", low=1e-6),
        Option("grow_horizon_below", float, None, "double the planning horizon (up to the task's) when the rule "
               "grow_horizon_on finds a mean cost per step below this (a horizon schedule; default: the task "
               "preset's, unicycle 0.2, else off; 0 = off)", low=0.0),
        replace(GROW_HORIZON_ON, help=GROW_HORIZON_ON.help + " (default: the task preset's, unicycle realised, else prediction)"),
        Option("plan_with_noise", bool, False, "planning feeds the policy the task's measurement noise (its input "
               "N(m, S + N) as it acts on noisy observations; needs a policy on raw states, e.g. the unicycle's; "
               "default: the task preset's, on for the unicycle; else off, the policy sees the latent state as in the "
               "reference code's last version)"),
        Option("sparse_threshold", int, None, "FITC above this many data points (default: task preset)", low=1),
        Option("num_pseudo", int, None, "FITC pseudo-inputs (default: the sparse threshold)", low=1),
        Option("planning_basis", int, None, "plan (J, dJ) with at most this many of the model's basis points (FITC "
               "pseudo-inputs or training inputs, chosen greedily where they explain the kernel at the data best; same "
               "hyperparameters and data): "
               "moment matching's cost grows with their square; what it costs in model quality and in the policy found: "
               "results/findings_double-pendulum.md (default: all)", low=1),
        Option("gp_max_evals", int, 300, "GP hyperparameter L-BFGS evaluations per trial", low=0),
        Option("gp_fitc_evals", int, 100, "FITC pseudo-input L-BFGS evaluations per trial (3x the first time; "
               "the reference allows 500 line searches)", low=0),
        Option("gp_hyper_subset", int, None, "when sparse, at most this many random data points train the GP "
               "hyperparameters (default: the sparse threshold; the reference uses all points)", low=1),
        Option("gp_pseudo_subset", int, None, "when sparse, optimise the FITC pseudo-inputs on at most this many "
               "random data points (the model then uses all of them): that stage's cost grows with the points "
               "(default: all points)", low=1),
        Option("gp_refresh_pseudo", bool, False, "draw the FITC pseudo-inputs afresh from the data at every trial "
               "(default: continue from the previous trial's, as the reference does)"),
        Option("gp_restarts", int, 0, "extra GP training runs from perturbed starts (best kept)", low=0),
        *GP_DATA_OPTIONS,
        Option("fresh_start_tol", float, None, "when J moved less than this fraction since the last trial and the "
               "last trial's realised cost was within this fraction of its prediction (stuck in an optimum the model "
               "is sure of), also search from fresh initial parameters and keep the lower J (default: the task preset's, "
               "dm_control cart-pole 0.05, else off; 0 = off)", low=0.0),
        Option("restart_tol", float, None, "the fresh-start rule's test (J moved less than this fraction since the last "
               "trial, the last trial's realised cost within this fraction of its prediction) for restarts near the policy: "
               "when it holds, also search from `restarts` copies of the policy with every parameter tensor moved by "
               "restart_scale times its spread, and keep the lowest J (a basin-hopping restart: fresh starts lose what the "
               "run learned; default: the task preset's, cart-pole 0.05, else off; 0 = off)", low=0.0),
        Option("restarts", int, 2, "searches from perturbed copies of the policy when restart_tol's test holds", low=1),
        Option("restart_scale", float, 0.1, "restart_tol's perturbation, in units of each parameter tensor's spread", low=0.0),
        Option("early_starts", int, 1, "policy searches in each of the first early_start_trials trials: from the "
               "controller handed over and from K-1 fresh initial controllers (seeded by run seed, trial and start), "
               "the lowest J kept (1 = off): the first policies decide which data the model sees", low=1),
        Option("early_start_trials", int, 3, "how many of the first trials search from early_starts starts", low=1),
        Option("policy_max_iterations", int, None, "L-BFGS iterations (~line searches) per policy search (default: task preset, 150)", low=1),
        Option("policy_max_evaluations", int, None, "J+dJ evaluations per policy search (default: task preset, 300; unicycle 150)", low=1),
        Option("threads", int, None, "CPU threads (default: the harness's choice, all cores for harness bench and 1 per "
               "cell in a sweep; harness.threads)", low=1, execution=True),
        Option("kernel", str, "auto", "moment matching's Q contraction: fused (compiled passes forming Q inside their "
               "loops, extra 'fast'), numba (compiled backward pass, Q by BLAS and NumPy), torch (the reference) or auto "
               "(fused where numba is installed)", choices=("auto", "fused", "numba", "torch"), execution=True),
        Option("device", str, "cpu", "where the GP is trained and J computed: cpu, cuda (a GPU; kernel torch) or auto "
               "(cuda where torch sees one)", choices=("cpu", "cuda", "auto"), execution=True),
        Option("cuda_graph", bool, True, "on a GPU, capture J + dJ once per policy search as a CUDA graph and replay it "
               "(false: launch every operation each evaluation)", execution=True),
        Option("compile_step", bool, False, "run each rollout step of J + dJ as code made by torch.compile (fewer, fused "
               "kernels: for a GPU, where launches set the time; made at a search's first evaluation; kernel torch)",
               execution=True),
        Option("plots", bool, True, "save the predicted-vs-realised cost plot per trial"),
        Option("sample_particles", int, 500, "particles for J_sampled, the policy's cost by Monte Carlo through the same GP "
               "(checks the moment-matching J; 0 = off)", low=0),
    )

    def __init__(self, spec: TaskSpec, options: dict[str, Any] | None = None, seed: int = 0) -> None:
        from plugins.pilco.moments import resolve_kernel
        from plugins.pilco.policy import layout_for

        super().__init__(spec, options, seed)
        o = self.options
        preset = PRESETS.get(spec.name, GENERIC)
        self.preset = preset_with(spec.name, o)
        self.layout = layout_for(spec, self.preset)
        schedule = preset.horizon_schedule
        grow = o["grow_horizon_below"] if o["grow_horizon_below"] is not None else (schedule[1] if schedule else None)
        # a given option beats the preset's rule (the option's own default is the other tasks' rule)
        rule = o["grow_horizon_on"] if "grow_horizon_on" in (options or {}) else preset.grow_horizon_on
        self.schedule = HorizonSchedule(o["planning_horizon"] or preset.planning_horizon or (schedule[0] if schedule else spec.horizon),
                                        spec.horizon, grow or None, rule)  # threshold 0: off
        self.cost_width = o["cost_width"] or preset.cost_width
        self.num_pseudo = o["num_pseudo"] or self.preset.sparse_threshold
        # the stall rules' tolerances: the option if given, else the task preset's; 0 (or None): off
        self.fresh_start_tol, self.restart_tol = (
            (o[name] if o[name] is not None else getattr(preset, name)) or None for name in ("fresh_start_tol", "restart_tol"))
        # a bool option cannot say "unset": the preset's value holds unless the option was given
        noise = o["plan_with_noise"] if "plan_with_noise" in (options or {}) else preset.plan_with_noise
        self.policy_noise_std = spec.measurement_noise_std if noise else None
        if self.policy_noise_std is not None:
            try:
                self.layout.policy_noise_cov(self.policy_noise_std)
            except ValueError as exc:
                raise OptionError(f"plan_with_noise on {spec.name}: {exc} (drop --set plan_with_noise=true)") from None
        check_gp_data(o, spec)
        self.device = resolve_device(o["device"])
        try:
            self.kernel = resolve_kernel(o["kernel"], self.device)
        except ValueError as exc:
            raise OptionError(f"kernel={o['kernel']}: {exc} (or --set kernel=torch)") from None
        if o["compile_step"] and self.kernel != "torch":
            raise OptionError(f"compile_step=true needs kernel=torch, not {self.kernel} on {self.device.type} "
                              "(add --set kernel=torch, or --set device=cuda)")
        self._state: dict[str, Any] = {}  # see state_dict(); filled at every hand-over

    @property
    def horizon(self) -> int:
        """The current planning horizon, steps (:attr:`schedule` grows it where a rule is set)."""
        return self.schedule.horizon

    def options_used(self) -> dict[str, Any]:
        """The options with the task preset's values (and the harness's thread count) where they were left unset."""
        used = dict(self.options)
        preset = asdict(self.preset)
        used.update({k: preset[k] for k in ("controller", "num_centres", "initial_rollouts", "random_scale", "sparse_threshold",
                                             "policy_max_iterations", "policy_max_evaluations")})
        used.update(planning_horizon=self.horizon, cost_width=self.cost_width or self.spec.cost.width, num_pseudo=self.num_pseudo,
                    gp_hyper_subset=self.options["gp_hyper_subset"] or self.preset.sparse_threshold,
                    threads=self.options["threads"] or run_threads(), kernel=self.kernel, fresh_start_tol=self.fresh_start_tol,
                    restart_tol=self.restart_tol,
                    grow_horizon_below=self.schedule.grow_below, grow_horizon_on=self.schedule.rule,
                    plan_with_noise=self.policy_noise_std is not None)
        from plugins.pilco.moments import COMPILED_KERNELS

        if self.kernel in COMPILED_KERNELS:  # the compiled kernels' SIMD width: "512", "default" or "too late"
            from harness.vector_width import configure

            used["vector_width"] = configure()
        return used

    @classmethod
    def default_limits(cls, spec: TaskSpec) -> tuple[int | None, float | None]:
        """The task preset's number of trials (reference N), no time budget."""
        return PRESETS.get(spec.name, GENERIC).max_trials, None

    # ---- pieces --------------------------------------------------------------------------------
    def new_controller(self, generator: torch.Generator) -> SquashedController:
        """The task preset's initial controller drawn with ``generator``: what a run starts from (seeded by the
        run's seed) and what a fresh start (``fresh_start_tol``) searches from again."""
        from plugins.pilco.policy import initial_controller

        return initial_controller(self.spec, self.preset, self.layout, self.options["squash"], generator)

    def _plot_prediction(self, predicted: tuple[np.ndarray, np.ndarray], sampled: np.ndarray | None, episode: Episode,
                         path: Path, trial: int) -> Path:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        mean, std = predicted
        t_pred = np.arange(1, mean.shape[0] + 1) * self.spec.dt
        t_real = np.arange(1, episode.steps + 1) * self.spec.dt
        fig, ax = plt.subplots(figsize=(6, 3.2), dpi=110)
        ax.fill_between(t_pred, mean - 2 * std, mean + 2 * std, color="tab:blue", alpha=0.25, label="predicted ±2σ")
        ax.plot(t_pred, mean, color="tab:blue", label="predicted E[cost]")
        if sampled is not None:
            ax.plot(t_pred, sampled, "--", color="tab:green", label="same model, sampled")
        ax.plot(t_real, episode.costs, "o-", color="tab:red", ms=3, label="realised cost (trial)")
        ax.set(xlabel="time [s]", ylabel="cost", ylim=(-0.05, 1.05), title=f"{self.name} on {self.spec.name}: trial {trial}")
        ax.legend(loc="lower left", fontsize=8)
        fig.tight_layout()
        save_figure(fig, path)
        plt.close(fig)
        return path

    # ---- Algorithm 1 ---------------------------------------------------------------------------
    def learn(self, interaction: Interaction) -> Iterator[Policy]:
        import torch

        from plugins.pilco.gp import GPHyperparameters, GPModel
        from plugins.pilco.policy import PilcoPolicy, cpu_state_dict
        from plugins.pilco.sampling import sampled_costs
        from plugins.random_learner import UniformRandomPolicy

        spec, o = self.spec, self.options
        threads = o["threads"] or run_threads()
        kernel = self.kernel
        torch.set_num_threads(threads)
        workdir = Path(tempfile.mkdtemp(prefix="pilco-"))
        model = GPModel(device=self.device, sparse_threshold=self.preset.sparse_threshold, num_pseudo=self.num_pseudo, max_evals_full=o["gp_max_evals"],
                        max_evals_fitc=o["gp_fitc_evals"], hyper_subset=o["gp_hyper_subset"],
                        pseudo_subset=o["gp_pseudo_subset"], refresh_pseudo=o["gp_refresh_pseudo"])
        controller = self.new_controller(torch.Generator().manual_seed(self.seed))
        resumed = self._resume_state
        graph_warned = False
        try:
            if resumed is None:
                scale = self.preset.random_scale
                explore = UniformRandomPolicy(scale * spec.action_low, scale * spec.action_high, self.seed)
                for _ in range(self.preset.initial_rollouts):
                    interaction.rollout(explore)
                hyperparameters, trial, predicted, sampled, last_J = None, 0, None, None, None
            else:  # continue right after the hand-over of trial `trial`
                controller.load_state_dict(resumed["controller"])
                hyperparameters = GPHyperparameters.from_dict(resumed["hyperparameters"])
                trial, predicted = resumed["trial"], resumed["predicted"]
                self.schedule.horizon = resumed.get("planning_horizon", self.horizon)
                sampled = resumed.get("sampled")
                last_J = resumed.get("J_after")
            while True:
                realised = None
                if trial > 0:  # apply the policy handed over last for one trial, record the data
                    episode = interaction.rollout(PilcoPolicy.snapshot(controller, self.layout))
                    realised = self.schedule.after_rollout(episode)  # the survival and realised rules; logged below
                    if o["plots"] and predicted is not None:
                        self.artifacts.append(self._plot_prediction(predicted, sampled, episode, workdir / f"prediction_trial{trial:03d}.png", trial))
                trial += 1
                fit, smoothing = train_dynamics(model, interaction.episodes, self.layout, o, spec.measurement_noise_std,
                                                hyperparameters, self.report_status, restarts=o["gp_restarts"],
                                                seed=self.seed + trial)
                hyperparameters = model.hyperparameters

                posterior = model.posterior(max_basis=o["planning_basis"])
                objective = self.planning_objective(controller, posterior, threads)
                previous = objective.get_flat()
                try:
                    search = self.search_policy(objective, kernel, threads)
                    failed = 0.0
                except NumericalError:
                    objective.set_flat(previous)  # keep the previous policy, say so in the metrics
                    search, failed = None, 1.0
                early = {}
                if o["early_starts"] > 1 and trial <= o["early_start_trials"] and search is not None:
                    search, early = self._more_starts(objective, search, trial, kernel, threads, o["early_starts"] - 1)
                planned, realised_cost = _predicted_sum(predicted), _realised_sum(interaction, predicted)

                def stuck(tol: float | None) -> bool:  # the fresh-start rule's test, on the search as it stands now
                    return search is not None and stalled(search.J_after, last_J, planned, realised_cost, tol)

                fresh = None
                if self.fresh_start_tol is not None and stuck(self.fresh_start_tol):
                    search, fresh = self._fresh_start(objective, search, trial, kernel, threads)
                restarted = None
                if self.restart_tol is not None and stuck(self.restart_tol):
                    search, restarted = self._restarts(objective, search, trial, kernel, threads)
                try:
                    predicted = objective.predicted_costs()
                except (NumericalError, torch.linalg.LinAlgError):  # the kept policy's prediction degenerated: no plot, say so
                    predicted = None
                if o["sample_particles"]:
                    self.report_status(f"J_sampled: {o['sample_particles']} particles through the GP")
                sampled = sampled_costs(objective, o["sample_particles"], seed=1000 * self.seed + trial) if o["sample_particles"] else None
                self.metrics = self._trial_metrics(fit, search, failed, predicted, objective.num_params) | smoothing
                self.metrics.update(early)
                if self.restart_tol is not None:
                    self.metrics.update(restarted or {"restarted": 0.0})
                if self.fresh_start_tol is not None:
                    self.metrics.update(fresh_start=float(fresh is not None), fresh_start_kept=float(bool(fresh and fresh["kept"])),
                                        J_fresh_start=fresh["J"] if fresh else math.nan)
                last_J = search.J_after if search is not None else last_J
                if objective.cuda_graph:  # on a GPU: was J + dJ replayed as a CUDA graph (1) or launched op by op (0)?
                    self.metrics["cuda_graph"] = float(objective.graph_error is None)
                    if objective.graph_error is not None and not graph_warned:
                        graph_warned = True
                        warnings.warn(f"pilco: J + dJ could not be captured as a CUDA graph ({objective.graph_error}); every "
                                      "evaluation launches its operations one by one (slower; metric cuda_graph = 0)", stacklevel=1)
                if realised is not None:  # the previous policy's recorded episode, mean cost per step over its planned horizon
                    self.metrics["rollout_cost_per_step"] = realised
                self.metrics["planning_horizon"] = float(self.horizon)
                self.metrics["planning_basis"] = float(posterior.inputs.shape[0])
                if sampled is not None:
                    self.metrics["J_sampled"] = float(sampled.sum())
                self.artifacts += self._save_model(workdir, trial, model, fit)
                if trial == 1:
                    self.artifacts.append(self._save_settings(workdir))
                self.schedule.after_search(search)  # the prediction rule
                self._state = {
                    "controller": cpu_state_dict(controller),
                    "hyperparameters": hyperparameters.to("cpu").as_dict(),
                    "trial": trial,
                    "predicted": predicted,
                    "sampled": sampled,
                    "planning_horizon": self.horizon,
                    "J_after": last_J,
                }
                yield PilcoPolicy.snapshot(controller, self.layout)
        finally:
            shutil.rmtree(workdir, ignore_errors=True)

    def planning_objective(self, controller: SquashedController, posterior, threads: int) -> PolicyObjective:
        """J (and dJ) of ``controller`` under a dynamics GP's ``posterior`` with this learner's settings: the
        task's cost and initial state distribution, the planning horizon (``self.horizon``), cost width,
        ``mean_only``, policy noise, kernel, device and CUDA graph option; ``threads`` for the contraction."""
        from plugins.pilco.objective import PolicyObjective

        spec = self.spec
        return PolicyObjective(controller, posterior, self.layout, spec.cost, spec.init_mean, spec.init_cov, self.horizon,
                               mean_only=self.mean_only, width=self.cost_width, policy_noise_std=self.policy_noise_std,
                               kernel=self.kernel, threads=threads, device=self.device, cuda_graph=self.options["cuda_graph"],
                               compile_step=self.options["compile_step"])

    def search_policy(self, objective: PolicyObjective, kernel: str, threads: int, what: str = "policy search"):
        """One policy search from the controller's current parameters within the preset's budgets
        (its progress shown as ``what: k/budget J + dJ, J best``)."""
        from plugins.pilco.moments import COMPILED_KERNELS
        from plugins.pilco.policy_search import optimise_policy

        budget = self.preset.policy_max_evaluations

        def shown(evaluations: int, best: float) -> None:
            self.report_status(f"{what}: {evaluations}/{budget} J + dJ, J {best:.2f}")

        # the compiled contraction runs its own threads; everything else in J is small
        with torch_threads(1 if kernel in COMPILED_KERNELS else threads):
            return optimise_policy(objective, self.preset.policy_max_iterations, budget, on_evaluation=shown)

    def _search_from(self, objective: PolicyObjective, search, start: dict, kernel: str, threads: int,
                     what: str) -> tuple[Any, float]:
        """A further policy search from the controller state ``start``; the lower J of it and ``search`` (the one that
        left the objective's controller where it is) is left in the controller. Returns the search to report (the kept
        one, with both searches' time and evaluations) and the further search's J (NaN if it failed)."""
        kept_theta = objective.get_flat()
        objective.controller.load_state_dict(start)  # copied onto the controller's device
        try:
            second = self.search_policy(objective, kernel, threads, what)
        except NumericalError:
            objective.set_flat(kept_theta)
            return search, math.nan
        better = second.J_after < search.J_after
        if not better:
            objective.set_flat(kept_theta)
        winner = second if better else search
        combined = replace(winner, J_before=search.J_before, seconds=search.seconds + second.seconds,
                           evaluations=search.evaluations + second.evaluations, iterations=search.iterations + second.iterations,
                           failed_evaluations=search.failed_evaluations + second.failed_evaluations)
        return combined, float(second.J_after)

    def _best_of(self, objective: PolicyObjective, search, starts: list[dict], kernel: str, threads: int,
                 what: str) -> tuple[Any, int, list[float]]:
        """Further policy searches from each controller state in ``starts`` (:meth:`_search_from`), the lowest J of all,
        ``search``'s included, left in the controller. Returns the search to report (the kept one, every search's time
        and evaluations counted), which was kept (0: ``search``; k: the k-th start) and each start's J (NaN: failed)."""
        kept, Js = 0, []
        for k, start in enumerate(starts, start=1):
            before = search.J_after
            label = what if len(starts) == 1 else f"{what} {k}/{len(starts)}"
            search, J = self._search_from(objective, search, start, kernel, threads, label)
            kept = k if search.J_after < before else kept
            Js.append(J)
        return search, kept, Js

    def _fresh_states(self, count: int, seed: Callable[[int], int]) -> list[dict]:
        """``count`` fresh initial controllers' states, the k-th (from 1) drawn with generator seed ``seed(k)``."""
        import torch

        return [self.new_controller(torch.Generator().manual_seed(seed(k))).state_dict() for k in range(1, count + 1)]

    def _fresh_start(self, objective: PolicyObjective, search, trial: int, kernel: str, threads: int) -> tuple[Any, dict[str, Any]]:
        """The fresh-start rule's second policy search from fresh initial parameters (seeded by run seed and
        trial); the lower J of the two is left in the controller. Returns the search to report (the kept one, with
        both searches' time and evaluations) and ``{"J": fresh J, "kept": bool}``."""
        start = self._fresh_states(1, lambda _: 1_000_003 * (self.seed + 1) + trial)
        search, kept, (J,) = self._best_of(objective, search, start, kernel, threads, "policy search from fresh parameters")
        return search, {"J": J, "kept": kept == 1}

    def _restarts(self, objective: PolicyObjective, search, trial: int, kernel: str, threads: int) -> tuple[Any, dict[str, float]]:
        """``restart_tol``: ``restarts`` more policy searches, each from the policy ``search`` handed over with every
        parameter tensor perturbed (:func:`~plugins.pilco.policy.perturbed_state`, ``restart_scale``; seeded by run
        seed, trial and restart), the lowest J of all left in the controller. Returns the search to report and the
        metrics ``restarted`` (1), ``restart_kept`` (0: the run's own search; k: the k-th restart) and
        ``J_restart_best`` (the lowest J a restart ended at)."""
        import torch

        from plugins.pilco.policy import perturbed_state

        o = self.options
        starts = [perturbed_state(objective.controller, o["restart_scale"],
                                  torch.Generator().manual_seed(3_000_017 * (self.seed + 1) + 1009 * trial + k))
                  for k in range(1, o["restarts"] + 1)]  # all near the policy the trial's search handed over
        search, kept, Js = self._best_of(objective, search, starts, kernel, threads, "policy search from restart")
        finite = [J for J in Js if math.isfinite(J)]
        return search, {"restarted": 1.0, "restart_kept": float(kept), "J_restart_best": min(finite) if finite else math.nan}

    def _more_starts(self, objective: PolicyObjective, search, trial: int, kernel: str, threads: int,
                     extra: int) -> tuple[Any, dict[str, float]]:
        """``early_starts``: ``extra`` more policy searches from fresh initial controllers (seeded by run seed, trial
        and start, apart from the fresh-start rule's seeds), the lowest J of all left in the controller. Returns the
        search to report and the metrics ``early_start_kept`` (0: the search from the controller handed over, k: the
        k-th fresh start) and ``J_early_starts_worst`` (the highest J any start ended at)."""
        first = search.J_after
        starts = self._fresh_states(extra, lambda k: 2_000_003 * (self.seed + 1) + 1009 * trial + k)
        search, kept, Js = self._best_of(objective, search, starts, kernel, threads, "policy search from start")
        worst = max([first] + [J for J in Js if math.isfinite(J)])
        return search, {"early_start_kept": float(kept), "J_early_starts_worst": float(worst)}

    def _save_settings(self, workdir: Path) -> Path:
        """``pilco_settings.json``: the resolved preset (options over the task's defaults) and layout."""
        settings = {
            "preset": asdict(self.preset), "planning_horizon": self.horizon, "cost_width": self.cost_width, "num_pseudo": self.num_pseudo,
            "model_inputs": list(self.layout.model_inputs), "policy_inputs": list(self.layout.policy_inputs),
            "mean_only": self.mean_only,
        }
        path = workdir / "pilco_settings.json"
        path.write_text(json.dumps(settings, indent=1))
        return path

    def state_dict(self) -> dict[str, Any]:
        """Controller parameters, GP hyperparameters (warm start, :meth:`GPHyperparameters.as_dict`), trial,
        pending prediction (closed form and sampled), planning horizon."""
        return self._state

    @classmethod
    def policy_state(cls, policy: Policy) -> dict[str, Any]:
        """:func:`~plugins.pilco.policy.pilco_policy_state`."""
        from plugins.pilco.policy import pilco_policy_state

        return pilco_policy_state(policy)

    @classmethod
    def policy_from_state(cls, state: dict[str, Any], spec: TaskSpec) -> PilcoPolicy:
        """:func:`~plugins.pilco.policy.pilco_policy_from_state`."""
        from plugins.pilco.policy import pilco_policy_from_state

        return pilco_policy_from_state(state, spec)

    def _trial_metrics(self, fit, search, failed: float, predicted, num_params: int) -> dict[str, float]:
        import torch

        metrics = {
            "n_data": float(fit.n_points),
            "gp_sparse": float(fit.sparse),
            "gp_nll": fit.nll,
            "model_train_seconds": fit.seconds,
            "policy_search_failed": failed,
            "predicted_cost": float(predicted[0].sum()) if predicted is not None else math.nan,
            "prediction_failed": float(predicted is None),
            "policy_parameters": float(num_params),
        }
        if search is not None:
            metrics.update(
                J_before=search.J_before, J_after=search.J_after, policy_opt_seconds=search.seconds,
                policy_evaluations=float(search.evaluations), line_searches=float(search.iterations),
                policy_failed_evaluations=float(search.failed_evaluations), policy_search_restarts=float(search.restarts),
                policy_search_status=float(search.status),
            )
        h = fit.hyperparameters
        for a in range(self.spec.state_dim):
            metrics[f"gp_signal_std_{a}"] = float(torch.exp(h.log_alpha[a]))
            metrics[f"gp_noise_std_{a}"] = float(torch.exp(h.log_sigma[a]))
        return metrics

    def _save_model(self, workdir: Path, trial: int, model: GPModel, fit) -> list[Path]:
        """The trained GP (state dict, for inspection) and its hyperparameters (readable JSON)."""
        import torch

        h = fit.hyperparameters
        model_path = workdir / f"model_trial{trial:03d}.pt"
        # plain data only, so that it loads with torch.load(weights_only=True) (SavedPilcoRun.saved_model)
        torch.save({"gp": model.state_dict(), "layout": asdict(self.layout), "preset": asdict(self.preset)}, model_path)
        hyp_path = workdir / f"gp_hyperparameters_trial{trial:03d}.json"
        hyp_path.write_text(json.dumps({
            "length_scales": torch.exp(h.log_ell).tolist(), "signal_std": torch.exp(h.log_alpha).tolist(),
            "noise_std": torch.exp(h.log_sigma).tolist(), "sparse": fit.sparse, "n_points": fit.n_points,
        }, indent=1))
        return [model_path, hyp_path]


class PilcoMean(Pilco):
    """Ablation: PILCO planning with the GP posterior mean only (model uncertainty dropped)."""

    name = "pilco-mean"
    description = "PILCO ablation: deterministic GP posterior mean in planning (no model uncertainty)"
    mean_only = True
