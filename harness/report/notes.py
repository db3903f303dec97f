"""``sweeps.md``: which sweeps and bench groups a report was made from, and every run it did not count."""

from __future__ import annotations

from harness.provenance import process_alive
from harness.report.records import ReportData, RunRecord, SweepInfo


def incomplete_status(record: RunRecord) -> str:
    """A not-counted run's status; a RUNNING run whose process is gone is said to be stale."""
    if record.status == "RUNNING" and process_alive(record.process) is False:
        host, pid, _ = record.process.rsplit(":", 2)
        return (f"RUNNING in the store, but its process (pid {pid} on {host}) is gone: it stopped without being "
                "marked; re-run its command to resume it")
    return record.status


def notes_markdown(data: ReportData) -> str:
    """``sweeps.md``: the sweeps used, and every run or cell not counted."""
    lines = ["# Sweeps behind these results", "", f"Tracking store: `{data.tracking_uri}`", ""]
    for s in data.sweeps:
        lines += [_sweep_line(s), f"  `{s.params.get('command', '?')}`"]
    lines.append("")
    errored = [r for r in data.runs if r.status == "FAILED"]
    if errored:
        lines += ["## Runs that raised (counted as unsolved)", ""]
        lines += [f"- {r.learner} on {r.task}, seed {r.seed} (run `{r.run_id}`): {r.error or 'FAILED'}" for r in errored]
        lines.append("")
    if data.incomplete:
        lines += ["## Runs not counted (still running or killed)", ""]
        lines += [f"- {r.learner} on {r.task}, seed {r.seed} (run `{r.run_id}`): {incomplete_status(r)}" for r in data.incomplete]
        lines.append("")
    if data.missing:
        lines += ["## Cells of the sweeps without any run (not counted)", ""]
        lines += [f"- sweep `{sid}`: {l} on {t}, seed {s}" for sid, (l, t, s) in data.missing]
        lines.append("")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# the command
# ---------------------------------------------------------------------------------------------


def _sweep_line(sweep: SweepInfo) -> str:
    """``- sweep `<id>` (parent run `<run>`, status FINISHED):``, a parent per task in the per-task
    layout (``parent runs `<run>` (cartpole, FINISHED), ...``), or ``- `bench-<hash>`: bench runs``."""
    if not sweep.parents:
        return f"- `{sweep.sweep_id}`: {sweep.status}"
    if len(sweep.parents) == 1 and not sweep.parents[0].task:
        return f"- sweep `{sweep.sweep_id}` (parent run `{sweep.parents[0].run_id}`, status {sweep.parents[0].status}):"
    parents = ", ".join(f"`{p.run_id}` ({p.task}, {p.status})" for p in sweep.parents)
    return f"- sweep `{sweep.sweep_id}` (parent runs {parents}):"
