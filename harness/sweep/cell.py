"""The worker side of a sweep: one cell (learner, task, seed) run as a child of its task's sweep parent."""

from __future__ import annotations

import os
import tempfile
import traceback
from dataclasses import dataclass, field
from typing import Any, Literal

from harness.interrupts import StopRequested, catch_stop_requests_early, terminate_as_interrupt
from harness.store import layout
from harness.sweep.spec import Cell


@dataclass(frozen=True)
class CellJob:
    """Everything a worker needs to run one cell (plain, picklable data)."""

    cell: Cell
    learner_options: dict[str, str]
    task_options: dict[str, str]
    max_trials: int | None
    budget_seconds: float | None
    eval_episodes: int
    tracking_uri: str
    #: the experiment and the sweep parent run of the cell's task
    experiment_id: str
    parent_run_id: str
    sweep_id: str
    extra_params: dict[str, Any] = field(default_factory=dict)
    #: an interrupted child of this cell to continue from its last checkpoint
    resume_run_id: str | None = None
    #: this submission's lease on the cell (:mod:`harness.sweep.lease`; ``None``: unchecked)
    lease: str | None = None


@dataclass
class CellOutcome:
    """How one cell ended in this invocation (``skipped``: it had a FINISHED child already)."""

    cell: Cell
    status: Literal["finished", "failed", "skipped", "stopped", "superseded"]
    run_id: str | None
    solved: bool = False
    interaction_time_to_success: float | None = None
    interaction_seconds: float = 0.0
    wall_seconds: float = 0.0
    stop_reason: str = ""
    error: str = ""
    resumed: bool = False

    def line(self) -> str:
        head = f"{self.cell.label}" + (" (resumed from its checkpoint)" if self.resumed else "")
        if self.status == "failed":
            return f"{head}: FAILED ({self.error})"
        if self.status == "superseded":
            return f"{head}: given to another worker ({self.error})"
        if self.status == "skipped":
            return f"{head}: already finished (run {self.run_id})"
        if self.status == "stopped":
            return f"{head}: {self.stop_reason} (run {self.run_id} KILLED; the next invocation resumes it)"
        if self.solved:
            return f"{head}: solved after {self.interaction_time_to_success:.1f} s of interaction, wall {self.wall_seconds:.0f} s"
        return f"{head}: not solved ({self.stop_reason}) after {self.interaction_seconds:.1f} s, wall {self.wall_seconds:.0f} s"


def _single_thread() -> None:
    """One thread per cell (cells run side by side; :func:`harness.threads.single_threaded`)."""
    from harness.threads import single_threaded

    single_threaded()


def _node_tag() -> dict[str, str]:
    """``{NODE_TAG: node id}`` in a Ray worker (the driver names the node of a lost cell), else empty."""
    import sys

    ray = sys.modules.get("ray")
    if ray is None or not ray.is_initialized():
        return {}
    return {layout.NODE_TAG: ray.get_runtime_context().get_node_id()}


def run_cell(job: CellJob) -> CellOutcome:
    """Run one cell as a child of its task's sweep parent run; never raises for a failing learner
    (SIGTERM to the worker raises ``KeyboardInterrupt``: the runner marks the child KILLED;
    SIGUSR1 stops it after the trial in progress: a ``stopped`` outcome, the child KILLED)."""
    catch_stop_requests_early()
    _single_thread()
    terminate_as_interrupt()
    from harness.errors import CheckpointError
    from harness.progress import SilentProgress
    from harness.runner import RunConfig, run
    from harness.store import Store
    from harness.sweep.lease import LeaseCheck, LeaseLost
    from harness.tracking import MlflowTracker

    class CellTracker(MlflowTracker):
        """Adds the sweep's tags and params to the child run the runner starts, and writes nothing
        once the cell's lease has moved on to another worker (:mod:`harness.sweep.lease`)."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.holds_lease = LeaseCheck(self, job.parent_run_id, job.cell, job.lease)

        def start(self, experiment, run_name, params, tags):
            self.holds_lease("start its run")
            return super().start(experiment, run_name, {**params, **job.extra_params},
                                 {**tags, layout.SWEEP_TAG: job.sweep_id, layout.ROLE_TAG: layout.ROLE_CELL, **_node_tag()})

        def resume(self, run_id):
            self.holds_lease(f"resume run {run_id}")
            super().resume(run_id)
            self.set_tags(_node_tag())

        def log_metrics(self, metrics, step):
            self.holds_lease(f"log the metrics of step {step}")
            super().log_metrics(metrics, step)

        def set_tags(self, tags):
            self.holds_lease("set tags")
            super().set_tags(tags)

        def log_artifact(self, path, artifact_path=None):
            self.holds_lease(f"store {os.path.basename(path)}")
            super().log_artifact(path, artifact_path)

        def delete_artifact(self, name):
            self.holds_lease(f"delete {name}")
            super().delete_artifact(name)

        def finish(self, status):
            self.holds_lease(f"mark its run {status}")
            super().finish(status)

    cell = job.cell
    config = RunConfig(cell.learner, cell.task, cell.seed, dict(job.learner_options), dict(job.task_options),
                       job.max_trials, job.budget_seconds, job.eval_episodes)

    def new_tracker() -> CellTracker:
        return CellTracker(job.tracking_uri, parent_run_id=job.parent_run_id, experiment_id=job.experiment_id)

    tracker = new_tracker()
    resumed = False
    try:
        if job.resume_run_id is not None:
            try:
                result = run(config, tracker=tracker, progress=SilentProgress(), resume_run_id=job.resume_run_id)
                resumed = True
            except CheckpointError:  # no checkpoint, learner cannot resume, or other settings: start afresh
                if tracker.run_id is not None:
                    tracker.holds_lease(f"mark run {tracker.run_id} KILLED")
                    store = Store(job.tracking_uri, tracker.client)
                    if store.run(tracker.run_id).status == "RUNNING":
                        store.set_status(tracker.run_id, "KILLED")
                tracker = new_tracker()
                result = run(config, tracker=tracker, progress=SilentProgress())
        else:
            result = run(config, tracker=tracker, progress=SilentProgress())
    except StopRequested as stopped:
        return CellOutcome(cell, "stopped", tracker.run_id, stop_reason=str(stopped), resumed=job.resume_run_id is not None)
    except LeaseLost as lost:  # another worker has the run now: leave it alone
        return CellOutcome(cell, "superseded", tracker.run_id, error=str(lost))
    except Exception as exc:
        error = f"{type(exc).__name__}: {exc}".splitlines()[0][:500]
        if tracker.run_id is not None:
            _attach_error(tracker, error, traceback.format_exc())
        return CellOutcome(cell, "failed", tracker.run_id, error=error)
    return CellOutcome(
        cell, "finished", result.run_id, solved=result.solved,
        interaction_time_to_success=result.interaction_time_to_success,
        interaction_seconds=result.interaction_seconds, wall_seconds=result.wall_seconds,
        stop_reason=result.stop_reason, resumed=resumed,
    )


def _attach_error(tracker, error: str, trace: str) -> None:
    """The error line as a tag and the traceback as ``error.txt`` (best effort)."""
    try:
        tracker.set_tags({layout.ERROR_TAG: error})
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, layout.ERROR_TRACE)
            with open(path, "w") as fh:
                fh.write(trace)
            tracker.log_artifact(path)
    except Exception:  # the run is already marked FAILED by the runner; the outcome carries the error
        pass
