"""A PILCO run read back from its tracking store: task, settings, trained GPs, policies and data.

What a PILCO run stores (artifact paths in the run):

* ``trial001/pilco_settings.json``: the learner's resolved settings (preset, planning horizon,
  model and policy inputs, ``mean_only``), written once (``Pilco._save_settings``);
* ``trialKKK/model_trialKKK.pt``: the GP trained at trial K, with its layout and preset
  (``Pilco._save_model``; tensors and plain values, read with ``torch.load(weights_only=True)``);
* ``policies/policy_trialKKK.policy``: the policy handed over at trial K (the runner; data only,
  :mod:`harness.datafile`);
* ``episodes/interaction_episodes.npz``: every interaction episode, random ones first (the runner).

The benchmarks that re-examine a run (``pilco_prediction_check``, ``gp_budget_check``,
``unicycle_objective_check``) read it through :class:`SavedPilcoRun`::

    with SavedPilcoRun(run_id, tracking_uri) as run:
        model, policy = run.model(15), run.policy(15)

A local store's files are read where they are (wherever the store was copied to); a server's are
downloaded into a temporary folder that is removed when the ``with`` block ends.
"""

from __future__ import annotations

import json
import pickle
from dataclasses import asdict
from functools import cached_property
from pathlib import Path
from typing import Any

import torch

from harness.discovery import load_learner, load_task
from harness.datafile import LegacyFormatError, is_legacy, legacy_message
from harness.errors import CheckpointError
from harness.seeding import derive_seeds
from harness.store import Store
from harness.store.layout import SEED_TAG, trial_folder
from harness.task import Episode
from harness.testrun import task_options
from plugins.pilco.gp import GPModel
from plugins.pilco.objective import PolicyObjective
from plugins.pilco.posterior import GPPosterior
from plugins.pilco.presets import Preset
from plugins.pilco.propagate import StateLayout


class SavedPilcoRun:
    """One PILCO (or ``pilco-mean``) run of a tracking store, opened for reading (through
    :class:`harness.store.RunReader`). An ``mc-pilco`` run opens too: it saves PILCO's controllers and
    the same episodes, but no ``pilco_settings.json`` and no GP files.

    Args:
        run_id: the MLflow run id.
        tracking_uri: the store (default: ``MLFLOW_TRACKING_URI``, else the local SQLite default).
        task: if given, the run must be on this task.

    Raises:
        TrackingError: there is no run ``run_id`` in the store.
        CheckpointError: the run is not a PILCO run (on ``task``), or a requested file is missing.
    """

    def __init__(self, run_id: str, tracking_uri: str | None = None, task: str | None = None) -> None:
        self.run_id = run_id
        self.run = Store(tracking_uri).run(run_id)
        self.params: dict[str, str] = self.run.params
        learner, task_name = self.params.get("learner", ""), self.params.get("task")
        if not (learner.startswith("pilco") or learner == "mc-pilco"):
            raise CheckpointError(f"run {run_id} is a {learner or 'non-harness'!r} run; this needs a PILCO (or mc-pilco) run")
        if task is not None and task_name != task:
            raise CheckpointError(f"run {run_id} is PILCO on {task_name!r}; this needs a run on {task!r}")
        self.learner_cls = load_learner(learner)
        self.task = load_task(task_name)(**task_options(self.params))
        self._saved_models: dict[int, dict[str, Any]] = {}

    def __enter__(self) -> SavedPilcoRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Remove the files downloaded from a server (a local store's files are read in place)."""
        self.run.close()

    def file(self, artifact: str) -> Path:
        """A local copy of one artifact of the run."""
        return self.run.file(artifact)

    @cached_property
    def settings(self) -> dict[str, Any]:
        """The learner's resolved settings (``pilco_settings.json``). Where a store kept only the later
        trials' folders, rebuilt from the earliest saved GP's preset and layout, the options the run was
        given and its logged first planning horizon (as ``Pilco.__init__`` resolves them)."""
        try:
            return json.loads(self.file(f"{trial_folder(1)}/pilco_settings.json").read_text())
        except CheckpointError:
            trials = self.model_trials()
            if not trials:
                raise
        saved = self.saved_model(trials[0])
        preset, layout = saved["preset"], saved["layout"]

        def given(name: str) -> str | None:
            value = self.params.get(f"learner.{name}")
            return None if value in (None, "None") else value

        schedule = preset.horizon_schedule
        first = self.metric("planning_horizon").get(1)
        horizon = (int(first) if first is not None else int(given("planning_horizon") or preset.planning_horizon
                                                             or (schedule[0] if schedule else self.task.spec.horizon)))
        width = given("cost_width")
        return json.loads(json.dumps({"preset": asdict(preset), "planning_horizon": horizon,  # as the file reads (lists)
                "cost_width": float(width) if width is not None else preset.cost_width,
                "num_pseudo": int(given("num_pseudo") or preset.sparse_threshold),
                "model_inputs": list(layout.model_inputs), "policy_inputs": list(layout.policy_inputs),
                "mean_only": bool(getattr(self.learner_cls, "mean_only", False))}))

    @property
    def planning_horizon(self) -> int:
        """Predicted steps in J at the first trial (a horizon schedule may have grown it later)."""
        return int(self.settings["planning_horizon"])

    def planning_horizon_at(self, trial: int) -> int:
        """Predicted steps in J of trial ``trial``'s policy search: the run's ``planning_horizon`` metric at
        that trial (a horizon schedule grows it), else :attr:`planning_horizon` (a run logged before the metric)."""
        return int(self.metric("planning_horizon").get(trial, self.planning_horizon))

    @property
    def mean_only(self) -> bool:
        """Whether the run planned with the GP mean only (the ``pilco-mean`` ablation)."""
        return bool(self.settings["mean_only"])

    def option_used(self, name: str) -> str | None:
        """The learner option ``name`` as the run used it (logged as ``used.learner.<name>`` where the
        preset decided it, else as given), or ``None`` for a run logged before the option existed."""
        return self.params.get(f"used.learner.{name}", self.params.get(f"learner.{name}"))

    @property
    def plans_with_noise(self) -> bool:
        """Whether the run planned with measurement noise at the policy's input (``plan_with_noise``)."""
        return self.option_used("plan_with_noise") == "True"

    @property
    def layout(self) -> StateLayout:
        """The run's state layout: its task's state and angles, the GP's and the policy's inputs as its settings say."""
        spec = self.task.spec
        return StateLayout(spec.state_dim, spec.angle_indices, tuple(self.settings["model_inputs"]), tuple(self.settings["policy_inputs"]))

    @property
    def initial_rollouts(self) -> int:
        """Random episodes before the first trial: trial K's GP is trained on the first
        ``initial_rollouts + K - 1`` episodes."""
        return int(self.settings["preset"]["initial_rollouts"])

    def gp_fit_seed(self, trial: int) -> int:
        """The seed of trial ``trial``'s GP training (its random hyperparameter subset and first pseudo-inputs):
        the learner's seed, derived from the run's (:func:`~harness.seeding.derive_seeds`), plus the trial, as
        ``Pilco.learn`` passes it. Refitting with it on the same data and warm start reproduces the run's GP."""
        return derive_seeds(int(self.run.tags[SEED_TAG]))["learner"] + int(trial)

    def gp_model(self, **overrides: Any) -> GPModel:
        """An untrained :class:`GPModel` with the run's GP settings: its sparse threshold and pseudo-input count, and
        the options ``gp_max_evals``, ``gp_fitc_evals``, ``gp_hyper_subset``, ``gp_pseudo_subset``, ``gp_refresh_pseudo`` as
        the run used them (the learner's defaults where it logged none); ``overrides`` (``GPModel``'s keyword arguments)
        replace any."""
        options = self.learner_cls.option_set()
        given = {name: self.option_used(name)
                 for name in ("gp_max_evals", "gp_fitc_evals", "gp_hyper_subset", "gp_pseudo_subset", "gp_refresh_pseudo")}
        o = options.resolve({name: v for name, v in given.items() if name in options and v not in (None, "None")})
        settings = {"sparse_threshold": int(self.settings["preset"]["sparse_threshold"]), "num_pseudo": int(self.settings["num_pseudo"]),
                    "max_evals_full": o["gp_max_evals"], "max_evals_fitc": o["gp_fitc_evals"], "hyper_subset": o["gp_hyper_subset"],
                    "pseudo_subset": o["gp_pseudo_subset"], "refresh_pseudo": o["gp_refresh_pseudo"]}
        return GPModel(**{**settings, **overrides})

    def refit_model(self, trial: int, inputs, targets, seed: int | None = None) -> GPModel:
        """Trial ``trial``'s GP trained again as the run trained it (:meth:`gp_model`, warm start from its trial
        ``trial - 1`` GP) on ``inputs (n, d)``, ``targets (n, E)``; ``seed`` draws its random subsets (default: the
        run's own draw, :meth:`gp_fit_seed`, which on the run's own data gives its GP back)."""
        model = self.gp_model()
        model.fit(inputs, targets, warm_start=self.model(trial - 1).hyperparameters, seed=self.gp_fit_seed(trial) if seed is None else seed)
        return model

    def objective(self, trial: int, policy, posterior: GPPosterior | None = None, task_cost: bool = False) -> PolicyObjective:
        """J of ``policy`` as trial ``trial``'s policy search computed it: that trial's planning horizon,
        the run's cost width, ``mean_only`` and measurement noise at the policy's input (``plan_with_noise``),
        under ``posterior`` (default: the GP trained at that trial). ``task_cost``: the task's own cost
        width instead of the run's planning width (what a real episode's cost is measured with)."""
        spec = self.task.spec
        return PolicyObjective(policy.controller, self.model(trial).posterior() if posterior is None else posterior,
                               policy.layout, spec.cost, spec.init_mean, spec.init_cov, self.planning_horizon_at(trial),
                               mean_only=self.mean_only, width=None if task_cost else self.settings.get("cost_width"),
                               policy_noise_std=spec.measurement_noise_std if self.plans_with_noise else None)

    def model_trials(self) -> list[int]:
        """Trials with a saved GP (``trialKKK/model_trialKKK.pt``; a store may keep only a trial's
        hyperparameters), ascending."""
        return sorted(int(Path(p).stem[len("model_trial"):]) for p in self.run.trial_files("model_trial*.pt"))

    def policy_trials(self) -> list[int]:
        """Trials with a saved policy, ascending."""
        return self.run.policy_trials()

    def saved_model(self, trial: int) -> dict[str, Any]:
        """The stored dict of trial ``trial``'s GP: ``gp`` (state dict), ``layout`` (a :class:`StateLayout`),
        ``preset`` (a :class:`Preset`)."""
        if trial not in self._saved_models:
            artifact = f"{trial_folder(trial)}/model_trial{trial:03d}.pt"
            try:
                saved = torch.load(self.file(artifact), weights_only=True)
            except pickle.UnpicklingError:  # objects of other classes than tensors: an older harness's file
                raise LegacyFormatError(legacy_message(f"{artifact} of run {self.run_id}", "model file", self.run_id)) from None
            self._saved_models[trial] = {**saved, "layout": StateLayout(**saved["layout"]), "preset": Preset(**saved["preset"])}
        return self._saved_models[trial]

    def model(self, trial: int) -> GPModel:
        """The GP trained at trial ``trial``, ready to predict."""
        model = GPModel()
        model.load_state_dict(self.saved_model(trial)["gp"])
        return model

    def policy(self, trial: int):
        """The policy handed over at trial ``trial`` (a ``PilcoPolicy``)."""
        artifact = self.run.policy(trial)
        if is_legacy(artifact):
            raise LegacyFormatError(legacy_message(artifact, "policy", self.run_id))
        return self.learner_cls.load_policy(self.file(artifact), self.task.spec)

    def episodes(self) -> list[Episode]:
        """Every interaction episode of the run, in the order they happened (random ones first)."""
        return self.run.episodes()

    def metric(self, key: str) -> dict[int, float]:
        """A per-trial metric's history, ``{step: value}``."""
        return self.run.history(key)
