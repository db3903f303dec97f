"""What a person watching a run sees: one line per hand-over and a bar towards the limit."""

from __future__ import annotations

from typing import Any, Protocol

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Column

from harness.learner_logs import EVALUATION, Logs


class ProgressReporter(Protocol):
    def start(self, title: str, total: float | None, unit: str) -> None: ...

    def update(self, record: dict[str, Any], completed: float) -> None: ...

    def status(self, text: str) -> None: ...

    def finish(self, summary: str) -> None: ...


class SilentProgress:
    """Reports nothing (library use, tests, sweep workers)."""

    def start(self, title: str, total: float | None, unit: str) -> None:
        pass

    def update(self, record: dict[str, Any], completed: float) -> None:
        pass

    def status(self, text: str) -> None:
        pass

    def finish(self, summary: str) -> None:
        pass


def format_record(record: dict[str, Any], previous_wall: float | None = None, logs: Logs = Logs()) -> str:
    """``trial 3/10 | 12.0 s interaction | success 30% | eval cost 31.20 | J 25.1 | wall 42 s (trial 35 s: GP 3 s, policy 30 s, eval 2 s)``:
    the run's limits where ``record`` has them (``max_trials``; ``budget_seconds``: ``12.0/2000 s interaction``),
    the metrics the learner shows (``logs.shown``, e.g. PILCO's J), the wall time since the run started,
    this trial's (since ``previous_wall``, the wall time at the last hand-over, when given) and where it
    went, as far as the learner (``logs.timings``) and the runner (the evaluation) log it."""
    parts = [f"trial {record['trial']}" + (f"/{record['max_trials']}" if record.get("max_trials") else "")]
    budget = record.get("budget_seconds")
    parts.append(f"{record['interaction_seconds']:.1f}" + (f"/{budget:.0f}" if budget else "") + " s interaction")
    parts.append(f"success {100 * record['eval_success_rate']:.0f}%")
    parts.append(f"eval cost {record['eval_cost']:.2f}")
    for key, label, *spec in logs.shown:
        if key in record:
            parts.append(f"{label} {record[key]:{spec[0] if spec else '.2f'}}")
    split = [f"{t.short} {record[t.metric]:.0f} s" for t in (*logs.timings, EVALUATION) if t.metric in record]
    if previous_wall is not None:
        split.insert(0, f"trial {record['wall_seconds'] - previous_wall:.0f} s" + (":" if split else ""))
        detail = split[0] + (" " + ", ".join(split[1:]) if len(split) > 1 else "")
    else:
        detail = ", ".join(split)
    parts.append(f"wall {record['wall_seconds']:.0f} s" + (f" ({detail})" if detail else ""))
    return " | ".join(parts)


class RichProgress:
    """A rich progress bar (total = trials or budget seconds), what the run is doing now (the learner's
    :meth:`~harness.learner.Learner.report_status`, the evaluation) after it, and a printed line per
    hand-over (with what the learner's ``logs`` declare)."""

    def __init__(self, console: Console | None = None, logs: Logs = Logs()) -> None:
        self.console = console or Console(stderr=True)
        self.logs = logs
        self._progress: Progress | None = None
        self._task = None
        self._last_wall: float | None = None

    def start(self, title: str, total: float | None, unit: str) -> None:
        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(bar_width=12),
            TextColumn("{task.completed:.0f}/{task.total:.0f} " + unit),
            TimeElapsedColumn(),
            # what the run is doing now takes the rest of the line, cut short rather than squeezing the others
            TextColumn("{task.fields[status]}", markup=False,
                       table_column=Column(no_wrap=True, overflow="ellipsis", ratio=1)),
            console=self.console,
            transient=True,
            expand=True,
        )
        self._progress.start()
        self._task = self._progress.add_task(title, total=total, status="")

    def update(self, record: dict[str, Any], completed: float) -> None:
        assert self._progress is not None
        self._progress.console.print(format_record(record, self._last_wall, self.logs), soft_wrap=True)
        self._last_wall = record.get("wall_seconds")
        self._progress.update(self._task, completed=completed, status="")

    def status(self, text: str) -> None:
        if self._progress is not None:
            self._progress.update(self._task, status=text)

    def finish(self, summary: str) -> None:
        if self._progress is not None:
            self._progress.stop()
        self.console.print(summary, soft_wrap=True)
