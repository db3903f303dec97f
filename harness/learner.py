"""The learner plugin API.

A learner is constructed with the task's :class:`~harness.task.TaskSpec` (never the environment),
its resolved options and a seed, and learns through :meth:`Learner.learn`: a generator that acts
on the system **only** through the harness-owned :class:`~harness.interaction.Interaction` and
*yields* a policy each time it has a new one to hand over. At each hand-over the harness
evaluates the policy on its own environment instance and stops the generator (``close()``) once
the task is solved or the trial / budget limit is reached.

Minimal example (uniform random controls)::

    class RandomLearner(Learner):
        name = "random"
        description = "uniform random controls"

        def learn(self, interaction):
            rng = np.random.default_rng(self.seed)
            spec = self.spec
            policy = lambda obs: rng.uniform(spec.action_low, spec.action_high)
            while True:
                interaction.rollout(policy)   # one episode, counted by the harness
                yield policy                  # the harness evaluates it here
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from harness.learner_logs import Logs
from harness.options import Option, OptionSet
from harness.task import TaskSpec

if TYPE_CHECKING:
    from harness.interaction import Interaction

#: the kind of a policy file (:mod:`harness.datafile`) and its name in a run, ``policies/policy_trialKKK.policy``
POLICY_KIND = "policy"
POLICY_PREFIX = "policy_trial"


class Policy(Protocol):
    """A deterministic controller: observation ``(D,)`` -> action ``(F,)`` (in control units)."""

    def __call__(self, observation: np.ndarray) -> np.ndarray: ...


class Learner(ABC):
    """Base class of learner plugins.

    Class attributes:
        name: the entry-point name, e.g. ``"pilco"``.
        description: one line for ``harness list``.
        options: declared options (see :mod:`harness.options`); resolved values arrive in
            ``self.options``.
        extra: the pip extra this learner needs (e.g. ``"sb3"``), for install hints.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    options: ClassVar[tuple[Option, ...]] = ()
    extra: ClassVar[str | None] = None
    #: top-level modules this plugin needs at use time (checked by discovery, e.g. ``("dm_control",)``).
    requires: ClassVar[tuple[str, ...]] = ()
    #: whether :meth:`state_dict`/:meth:`load_state_dict` capture everything needed to continue
    #: a run after a hand-over (then the harness checkpoints after every trial where the interaction
    #: allows it, :attr:`Interaction.can_checkpoint`, and can resume)
    supports_resume: ClassVar[bool] = False
    #: how many of a run's newest checkpoints its store keeps (``None``: all, e.g. for benchmarks
    #: that read a run's model at an earlier trial; a learner whose state is large, such as a
    #: replay buffer, keeps a few: the newest, and the one before in case the newest was cut by a crash)
    keep_checkpoints: ClassVar[int | None] = None
    #: checkpoint after a trial only once this many wall seconds have passed since the last one
    #: (``None``: after every trial); for learners with many short trials and a state that grows with
    #: the interaction (the recorded episodes, a replay buffer). A stop asked with ``kill -USR1``
    #: always checkpoints the trial it stops after; a crash resumes from the last checkpoint written.
    checkpoint_every_seconds: ClassVar[float | None] = None
    #: limits used when the user gives neither --max-trials nor --budget-seconds
    default_max_trials: ClassVar[int | None] = 20
    default_budget_seconds: ClassVar[float | None] = None
    #: what its ``metrics`` and ``artifacts`` mean, for progress lines and reports (:class:`~harness.learner_logs.Logs`)
    logs: ClassVar[Logs] = Logs()

    def __init__(self, spec: TaskSpec, options: dict[str, Any] | None = None, seed: int = 0) -> None:
        self.spec = spec
        self.seed = int(seed)
        self.options: dict[str, Any] = self.option_set().resolve(options)
        #: per-hand-over numbers the learner wants tracked (e.g. J before/after); the harness
        #: logs and clears this dict after each hand-over.
        self.metrics: dict[str, float] = {}
        #: files (paths) the learner wants attached to the run after each hand-over.
        self.artifacts: list[Path] = []
        #: the state to continue from, set by :meth:`load_state_dict` before :meth:`learn`.
        self._resume_state: dict[str, Any] | None = None
        #: where :meth:`report_status` goes: set by the harness's runner (``harness bench`` shows it live
        #: beside its progress bar; sweep cells get a silent one); ``None``: nowhere (library use)
        self.status_sink: Callable[[str], None] | None = None

    @classmethod
    def option_set(cls) -> OptionSet:
        return OptionSet(cls.options, f"learner '{cls.name}'")

    @classmethod
    def default_limits(cls, spec: TaskSpec) -> tuple[int | None, float | None]:
        """``(max_trials, budget_seconds)`` used when the user sets neither (may depend on the task)."""
        return cls.default_max_trials, cls.default_budget_seconds

    def options_used(self) -> dict[str, Any]:
        """``self.options`` with each option left to the learner (``None``: "the task preset's") replaced
        by the value it uses; logged beside the options (params ``used.learner.<name>``)."""
        return dict(self.options)

    @abstractmethod
    def learn(self, interaction: Interaction) -> Iterator[Policy]:
        """Act through ``interaction`` and yield a policy at every hand-over."""

    def report_status(self, text: str) -> None:
        """Say what the learner is doing between two hand-overs, e.g. ``"policy search: 80/300 J + dJ,
        J 41.20"``: a long trial then shows its progress. The text replaces the previous one until the
        next hand-over; it is shown, not logged. Cheap: the text is only stored (the bar redraws ~10 times a
        second), so calling it at every step of a search is fine."""
        sink = getattr(self, "status_sink", None)  # a subclass may not have called Learner.__init__
        if sink is not None:
            sink(text)

    def state_dict(self) -> dict[str, Any]:
        """The learner's state at its last hand-over, as plain data (:mod:`harness.datafile`: dicts, lists,
        tuples, numbers, strings, ``None``, NumPy arrays, torch tensors), stored in checkpoints.

        A learner with ``supports_resume = True`` must make ``load_state_dict(state_dict())``
        followed by ``learn(interaction)`` continue exactly after that hand-over.
        """
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` before :meth:`learn` is called (see ``supports_resume``)."""
        self._resume_state = state

    # -- policies as data ------------------------------------------------------------------
    # A run's policies are stored as plain data (harness.datafile): a learner says what its policy
    # is made of (policy_state) and rebuilds it from that (policy_from_state); the harness writes,
    # checks and reads the files (save_policy, load_policy), so reading a policy runs no code from it.

    @classmethod
    def policy_state(cls, policy: Policy) -> dict[str, Any]:
        """``policy`` as plain data (dicts, lists, tuples, numbers, strings, ``None``, NumPy arrays, torch
        tensors) from which :meth:`policy_from_state` rebuilds a policy that acts exactly the same.

        Every learner whose runs ``harness eval`` should test overrides both (the conformance suite,
        :mod:`harness.testing`, checks the round trip); this default raises ``NotImplementedError``
        and the runner records that the run's policies were not saved.
        """
        raise NotImplementedError(f"learner '{cls.name}' does not save its policies (it defines no policy_state and policy_from_state)")

    @classmethod
    def policy_from_state(cls, state: dict[str, Any], spec: TaskSpec) -> Policy:
        """The policy that :meth:`policy_state` described, for a task with ``spec``. Raise ``KeyError``,
        ``TypeError``, ``ValueError`` or ``RuntimeError`` for a state that is not one (the harness refuses the file)."""
        raise NotImplementedError(f"learner '{cls.name}' does not load policies (it defines no policy_state and policy_from_state)")

    @classmethod
    def save_policy(cls, policy: Policy, path: Path) -> Path:
        """Write ``policy`` to ``<path>.policy`` (data only) and return the written path."""
        from harness import datafile

        path = Path(path).with_suffix(datafile.POLICY_SUFFIX)
        return datafile.write(path, POLICY_KIND, cls.policy_state(policy), {"learner": cls.name})

    @classmethod
    def load_policy(cls, path: Path, spec: TaskSpec) -> Policy:
        """The policy of a file written by :meth:`save_policy`, for a task with ``spec``.

        Raises :class:`~harness.datafile.DataFileError` (a :class:`~harness.errors.CheckpointError`) for
        a file that is cut, changed, foreign, another learner's or in an older pickled format.
        """
        from harness import datafile

        path = Path(path)
        meta, state = datafile.read(path, POLICY_KIND)
        if meta.get("learner") != cls.name:
            raise datafile.DataFileError(f"policy {path.name} was saved by learner {meta.get('learner')!r}, not '{cls.name}': "
                                         "load it with that learner")
        if not isinstance(state, dict):
            raise datafile.DataFileError(f"policy {path.name} holds a {type(state).__name__}, not a policy's state: refused")
        try:
            return cls.policy_from_state(state, spec)
        except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as exc:
            raise datafile.DataFileError(f"policy {path.name} does not hold a '{cls.name}' policy for task {spec.name!r} "
                                         f"({type(exc).__name__}: {exc}): refused") from None

    @classmethod
    def read_legacy_policy(cls, path: Path, spec: TaskSpec) -> Policy:
        """A policy file of an older harness version (``.pkl``: a pickle), for ``harness store migrate`` only.

        **Reading it runs code from the file**: call it only on the user's explicit request, for files
        from a store they trust. Learners whose older files were not pickles override it.
        """
        import pickle

        with open(path, "rb") as fh:
            return pickle.load(fh)
