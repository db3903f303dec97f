"""Did each policy search end below where it started? A sweep's runs, trial by trial, from the store.

Usage::

    .venv/bin/python benchmarks/search_outcome_check.py --sweep SWEEP_ID [--margin 1.0]
        [--tracking-uri URI] [--out FILE]

For every run of the sweep (all its cells, stopped and restarted runs included, oldest first) it reads
the per-trial metrics ``J_before`` and ``J_after``: the objective at the policy a search started from
and at the one it handed over, both under the trial's model. ``mc-pilco`` estimates both on one fixed
set of particles (common random numbers), so their difference is the search's own doing, not the
estimate's noise. A search "ended above its start" when ``J_after > J_before + margin``. Beside each
run: its evaluation cost per trial and its state (solved, unsolved at its limit, stopped).

Reading: a search that ends above its start hands over a policy the model itself rates worse than the
one it had; with ``mc-pilco``'s default ``keep=last`` that policy runs the next trial.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, machine_line, write_report  # noqa: E402
from harness.errors import HarnessError, exit_on_error  # noqa: E402
from harness.store.client import Store  # noqa: E402
from harness.store.reader import RunReader  # noqa: E402


def search_changes(run: RunReader) -> dict[int, float]:
    """``{trial: J_after - J_before}`` of the run's finished searches, in trial order."""
    before, after = run.history("J_before"), run.history("J_after")
    return {t: after[t] - before[t] for t in sorted(before) if t in after}


def searches_above_start(changes: dict[int, float], margin: float) -> list[tuple[int, float]]:
    """``(trial, J_after - J_before)`` of the searches (:func:`search_changes`) that ended more than ``margin`` above their start."""
    return [(t, d) for t, d in changes.items() if d > margin]


def run_row(run: RunReader, margin: float) -> dict:
    """One run's row: seed, trials, evaluation costs, its searches and those that ended above their start, state."""
    costs = run.history("eval_cost")
    trials = len(costs)
    if run.status == "FINISHED":
        state = f"solved at {run.time_to_success:.0f} s" if run.solved else f"unsolved ({run.reached('interaction_seconds'):.0f} s)"
    else:
        state = f"{run.status.lower()} after trial {trials}"
    changes = search_changes(run)
    return {"seed": run.cell[2] if run.cell else None, "run": run.run_id[:8], "trials": trials,
            "costs": " ".join(f"{costs[t]:.1f}" for t in sorted(costs)), "searches": len(changes),
            "above": searches_above_start(changes, margin), "state": state, "solved": run.solved,
            "finished": run.status == "FINISHED"}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sweep", required=True, help="sweep id (harness sweep prints it)")
    parser.add_argument("--margin", type=float, default=1.0, help="how far above its start a search must end to count")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=None, help="write the markdown report here")
    args = parser.parse_args(argv)
    store = Store(args.tracking_uri)
    parents = store.sweep_parents(args.sweep)
    if not parents:
        raise HarnessError(f"no sweep {args.sweep} in the store; `harness report --tracking-uri URI` names the sweeps it holds")
    runs = [r for p in parents for r in store.children(p)]
    runs.sort(key=lambda r: (r.cell[2] if r.cell else -1, r.start_time))
    rows = [run_row(r, args.margin) for r in runs]
    lines = [f"| seed | run | trials | evaluation cost per trial | searches ending > {args.margin:g} above start (trial: J_after - J_before) | state |",
             "|---|---|---|---|---|---|"]
    for row in rows:
        above = ", ".join(f"{t}: +{d:.1f}" for t, d in row["above"]) or "-"
        lines.append(f"| {row['seed']} | `{row['run']}` | {row['trials']} | {row['costs']} | {above} | {row['state']} |")
    finished = [r for r in rows if r["finished"]]
    total = sum(r["searches"] for r in rows)
    count = lambda rs: sum(len(r["above"]) for r in rs)  # noqa: E731
    solved = [r for r in finished if r["solved"]]
    unsolved = [r for r in finished if not r["solved"]]
    lines += ["", f"{count(rows)} of {total} searches (every run above) ended more than {args.margin:g} above their start; "
              f"finished runs: {len(solved)} solved with {count(solved)} such searches, {len(unsolved)} unsolved with {count(unsolved)}."]
    head = [f"# Policy searches of sweep {args.sweep}: where each ended against its start", "",
            f"Command: `{command_line(__file__, argv)}`  ", machine_line(), ""]
    write_report(head + lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
