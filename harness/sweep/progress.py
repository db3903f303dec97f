"""What a person watching a sweep sees: one bar for the sweep, a line per finished cell, and each new
trial of the running cells as the store has it (:class:`TrialWatcher`)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

from harness.store import layout
from harness.sweep.cell import CellOutcome

if TYPE_CHECKING:
    from harness.store import Store
    from harness.sweep.driver import CellRetry, SweepResult


class SweepProgress(Protocol):
    def start(self, sweep_id: str, total: int, skipped: int) -> None: ...

    def update(self, done: int, running: int, failed: int, eta_seconds: float | None) -> None: ...

    def cell_done(self, outcome: CellOutcome) -> None: ...

    def cell_retried(self, retry: CellRetry) -> None: ...

    def trial(self, label: str, learner: str, record: dict[str, float]) -> None: ...

    def finish(self, result: SweepResult) -> None: ...


class SilentSweepProgress:
    def start(self, sweep_id: str, total: int, skipped: int) -> None:
        pass

    def update(self, done: int, running: int, failed: int, eta_seconds: float | None) -> None:
        pass

    def cell_done(self, outcome: CellOutcome) -> None:
        pass

    def cell_retried(self, retry: CellRetry) -> None:
        pass

    def trial(self, label: str, learner: str, record: dict[str, float]) -> None:
        pass

    def finish(self, result: SweepResult) -> None:
        pass


def format_duration(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "–"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class RichSweepProgress:
    """One bar for the whole sweep (done / running / failed, ETA) and a line per finished cell."""

    def __init__(self, console=None) -> None:
        from rich.console import Console

        self.console = console or Console(stderr=True)
        self._progress = None
        self._task = None
        self._total = 0

    def start(self, sweep_id: str, total: int, skipped: int) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._total = total
        self._progress = Progress(TextColumn(f"[bold]sweep {sweep_id}"), BarColumn(), MofNCompleteColumn(),
                                  TextColumn("{task.description}"), TimeElapsedColumn(), console=self.console, transient=True)
        self._progress.start()
        self._task = self._progress.add_task("", total=total, completed=skipped)
        if skipped:
            self.console.print(f"{skipped} of {total} cells already finished in an earlier invocation: skipped")

    def update(self, done: int, running: int, failed: int, eta_seconds: float | None) -> None:
        if self._progress is not None:
            self._progress.update(self._task, completed=done,
                                  description=f"running {running} | failed {failed} | ETA {format_duration(eta_seconds)}")

    def cell_done(self, outcome: CellOutcome) -> None:
        style = {"failed": "red", "stopped": "yellow"}.get(outcome.status, "")
        self.console.print(outcome.line(), style=style, soft_wrap=True)

    def cell_retried(self, retry: CellRetry) -> None:
        self.console.print(retry.line(), style="yellow", soft_wrap=True)

    def trial(self, label: str, learner: str, record: dict[str, float]) -> None:
        from harness.learner_logs import declared_logs
        from harness.progress import format_record

        line = format_record(record, record.get(PREVIOUS_WALL), logs=declared_logs(learner))
        self.console.print(f"{label}: {line}", soft_wrap=True)

    def finish(self, result: SweepResult) -> None:
        if self._progress is not None:
            self._progress.stop()


#: seconds between two looks at the running cells' newest trials (:class:`TrialWatcher`)
TRIAL_POLL_SECONDS = 20.0


#: key of a trial record from :class:`TrialWatcher`: the run's wall time at the trial before (for the trial's own)
PREVIOUS_WALL = "previous_wall_seconds"


def _limits(params: dict[str, str]) -> dict[str, float]:
    """A run's ``max_trials`` and ``budget_seconds`` from its params (logged as text, ``"None"`` when unset)."""
    limits = {}
    for key in ("max_trials", "budget_seconds"):
        try:
            limits[key] = float(params[key])
        except (KeyError, ValueError):
            continue
    if "max_trials" in limits:
        limits["max_trials"] = int(limits["max_trials"])
    return limits


class TrialWatcher:
    """Reports each new trial of the sweep's running cells, read from the tracking store.

    Workers log every hand-over to their MLflow run; the driver already holds the store, so it
    reads the running children of the sweep's parents (``(experiment id, parent run id)``, one per
    task) every :data:`TRIAL_POLL_SECONDS` (the same for local and Ray workers, no channel to the
    workers). A cell's trial number is the newest step of its ``interaction_seconds`` history; its
    record carries the run's limits (params ``max_trials``, ``budget_seconds``) and its wall time at the
    trial before (:data:`PREVIOUS_WALL`), so that the line gives the trial's own wall time.
    """

    def __init__(self, store: Store, parents: Sequence[tuple[str, str]], poll_seconds: float = TRIAL_POLL_SECONDS) -> None:
        self.store, self.parents = store, list(parents)
        self.poll_seconds = poll_seconds
        self._seen: dict[str, int] = {}  # run id -> newest trial reported
        self._last = -math.inf

    def poll(self, progress: SweepProgress, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        if now - self._last < self.poll_seconds:
            return
        self._last = now
        try:
            running = [run for experiment_id, parent in self.parents
                       for run in self.store.children(parent, experiment_id, "attributes.status = 'RUNNING'")]
            for run in sorted(running, key=lambda r: r.name):
                trial = max(run.history(layout.INTERACTION_SECONDS), default=0)
                if trial <= self._seen.get(run.run_id, 0):
                    continue
                self._seen[run.run_id] = trial
                record = {**run.metrics, "trial": trial, **_limits(run.params)}
                previous = run.history(layout.WALL_SECONDS).get(trial - 1)
                if previous is not None:
                    record[PREVIOUS_WALL] = previous
                if all(k in record for k in (layout.EVAL_SUCCESS_RATE, layout.EVAL_COST, layout.WALL_SECONDS)):
                    progress.trial(run.name, run.tags.get(layout.LEARNER_TAG, ""), record)
        except Exception:  # a busy or locked store must never stop the sweep; the next poll retries
            return
