"""What the report knows of a sweep and of a run: :class:`SweepInfo`, :class:`RunRecord` (read from
a stored run through :class:`~harness.store.RunReader`), and :class:`ReportData` (all of them)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from harness.configuration import run_config
from harness.errors import HarnessError
from harness.learner_logs import declared_logs
from harness.store import RunReader, layout
from harness.sweep.spec import parse_seeds


@dataclass(frozen=True)
class ParentRun:
    """One parent run of a sweep: in a task's experiment (``task``), or the one legacy parent (``task`` empty)."""

    run_id: str
    task: str
    status: str


@dataclass
class SweepInfo:
    """A sweep (its parent runs and spec), or a group of `harness bench` runs (no parents)."""

    sweep_id: str
    parents: list[ParentRun]
    params: dict[str, str]
    #: what the notes say of a bench group instead of its parents' status
    status: str = ""

    @property
    def parent_run_ids(self) -> list[str]:
        return [p.run_id for p in self.parents]

    def expected_cells(self) -> set[tuple[str, str, int]]:
        try:
            learners = [s for s in self.params["learners"].split(",") if s]
            tasks = [s for s in self.params["tasks"].split(",") if s]
            seeds = parse_seeds(self.params["seeds"])
        except (KeyError, HarnessError):
            return set()
        return {(l, t, s) for l in learners for t in tasks for s in seeds}


@dataclass
class RunRecord:
    """One run as the report needs it (from its tags, params and final metrics)."""

    run_id: str
    sweep_id: str
    learner: str
    task: str
    seed: int
    status: str
    start_time: int
    solved: bool
    stop_reason: str
    time_to_success: float | None
    trials_to_success: float | None
    interaction_seconds: float
    wall_seconds: float
    policy_parameters: float | None
    state_dim: int | None
    error: str = ""
    label: str = ""
    #: interaction episodes the run recorded, random ones included (like ``interaction_seconds``:
    #: a stopped run's count includes the rollout of its last policy)
    episodes: float | None = None
    #: what the run was configured with: limits and resolved options (params ``learner.*``, ``task.*``)
    config: dict[str, str] = field(default_factory=dict)
    #: the process that last logged into the run (tag :data:`harness.provenance.PROCESS_TAG`)
    process: str = ""
    #: the stored run, for its metric histories and files (``None`` for a record made by hand)
    reader: RunReader | None = field(default=None, repr=False, compare=False)

    @property
    def cell(self) -> tuple[str, str, int]:
        return (self.learner, self.task, self.seed)


def record_from_run(run: RunReader, sweep_id: str) -> RunRecord | None:
    """A :class:`RunRecord` of a stored run (``None`` if it is not a harness run: no learner, task, seed)."""
    if run.cell is None:
        return None
    learner, task, seed = run.cell
    state_dim = run.params.get("spec.state_dim")
    size_metric = declared_logs(learner).policy_size
    return RunRecord(
        run_id=run.run_id, sweep_id=sweep_id, learner=learner, task=task, seed=seed,
        status=run.status, start_time=run.start_time, solved=run.solved,
        stop_reason=run.tags.get(layout.STOP_REASON_TAG, run.status.lower()),
        time_to_success=run.time_to_success,
        trials_to_success=run.metric(layout.TRIALS_TO_SUCCESS) if run.solved else None,
        interaction_seconds=run.reached(layout.INTERACTION_SECONDS),
        wall_seconds=run.reached(layout.WALL_SECONDS),
        policy_parameters=run.metric(size_metric) if size_metric else None,
        state_dim=int(float(state_dim)) if state_dim not in (None, "") else None,
        error=run.tags.get(layout.ERROR_TAG, ""),
        episodes=run.reached(layout.INTERACTION_EPISODES),
        config=run_config(run.params),
        process=run.tags.get(layout.PROCESS_TAG, ""),
        reader=run,
    )


def select_run(records: Sequence[RunRecord]) -> RunRecord:
    """The newest FINISHED run of a cell, else the newest run."""
    finished = [r for r in records if r.status == "FINISHED"]
    return max(finished or records, key=lambda r: r.start_time)


@dataclass
class ReportData:
    """The counted runs, and every run that was not counted, with why."""

    sweeps: list[SweepInfo]
    runs: list[RunRecord]
    incomplete: list[RunRecord] = field(default_factory=list)
    missing: list[tuple[str, tuple[str, str, int]]] = field(default_factory=list)
    tracking_uri: str = ""
