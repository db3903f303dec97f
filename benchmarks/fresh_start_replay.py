"""Where PILCO's fresh-start rule would have fired in runs made without it, from their stored metrics and episodes.

Usage::

    python benchmarks/fresh_start_replay.py --sweep 0fff704d9116 --tol 0.02 0.05 \\
        --tracking-uri sqlite:///$PWD/results/runs/mlflow.db --out results/benchmarks/fresh_start_replay_double-pendulum.md

The rule (``fresh_start_tol``, :func:`plugins.pilco.learner.stalled`, the learner's own function) fires after
trial ``k``'s search when its J moved less than ``tol`` (relative) from trial ``k-1``'s and the episode of
policy ``k-1`` cost within ``tol`` of what the model predicted for it; the learner then also searches from
fresh parameters and keeps the lower J. Replayed here on runs that did not use it, per run: the trials at
which it would have fired, beside the trial at which the run was solved. This says how often the rule would
spend a second search and whether it singles out the runs that stay stuck; not what the runs would have done
with it (that needs runs). The prediction compared is the learner's logged ``predicted_cost`` (the expected
cost summed over the planning horizon), the realised cost the same steps of the stored episode.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.errors import HarnessError, exit_on_error  # noqa: E402


def fires(J: dict[int, float], predicted: dict[int, float], episodes_before: dict[int, float],
          episode_costs: list[np.ndarray], tol: float, horizon: dict[int, float] | None = None) -> list[int]:
    """Trials ``k`` at which :func:`~plugins.pilco.learner.stalled` is true: ``J[k]`` against ``J[k-1]``, and the
    cost of policy ``k-1``'s episode (the newest of the ``episodes_before[k]`` the learner had at trial ``k``)
    against ``predicted[k-1]``. ``episode_costs[i]``: episode ``i``'s per-step costs, summed over the steps the
    prediction covered (``horizon[k-1]``, the planning horizon it was made with; all steps without it), as the
    learner's own ``_realised_sum`` does."""
    from plugins.pilco.learner import stalled

    out = []
    for k in sorted(J):
        if k - 1 not in J or k - 1 not in predicted or k not in episodes_before:
            continue
        index = int(episodes_before[k]) - 1
        if not 0 <= index < len(episode_costs):
            continue
        steps = int(horizon[k - 1]) if horizon and k - 1 in horizon else None
        if stalled(J[k], J[k - 1], predicted[k - 1], float(np.sum(episode_costs[index][:steps])), tol):
            out.append(k)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sweep", action="append", required=True, help="sweep id (repeatable)")
    parser.add_argument("--tol", type=float, nargs="+", default=[0.02, 0.05])
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    from harness.evaluation import SOLVED_FRACTION
    from harness.store.client import Store

    store = Store(args.tracking_uri)
    rows = []
    for sweep in args.sweep:
        for parent in store.sweep_parents(sweep):
            for run in sorted(store.children(parent), key=lambda r: r.name):
                J = run.history("J_after") if run.role == "cell" else {}
                if not J:
                    continue
                predicted, before = run.history("predicted_cost"), run.history("interaction_episodes")
                try:
                    costs = [e.costs for e in run.episodes()]
                except HarnessError:  # a run whose episodes are not stored (one superseded before they were)
                    rows.append((sweep, run.name, run.status, len(J), None, None))
                    continue
                horizon, success = run.history("planning_horizon"), run.history("eval_success_rate")
                solved_at = next((k for k, v in sorted(success.items()) if v >= SOLVED_FRACTION), None) if run.solved else None
                rows.append((sweep, run.name, run.status, len(J), solved_at,
                             [fires(J, predicted, before, costs, tol, horizon) for tol in args.tol]))

    lines = ["# The fresh-start rule replayed on runs made without it", "",
             f"Command: `{command_line(__file__, argv)}`  ", "",
             "Trials at which `plugins.pilco.learner.stalled` would have fired (so the learner would also have searched "
             "from fresh parameters), per run, for each tolerance; a replay on stored metrics and episodes, not runs made "
             "with the rule.", "",
             "| sweep | run | status | trials | solved at trial | " + " | ".join(f"fires, tol {t:g}" for t in args.tol) + " |",
             "|---" * (5 + len(args.tol)) + "|"]
    for sweep, name, status, trials, solved_at, fired in rows:
        cells = (["(no episodes stored)"] * len(args.tol) if fired is None
                 else [f"{len(f)} of {trials - 1}: {', '.join(map(str, f)) or '-'}" for f in fired])
        lines.append(f"| `{sweep}` | {name} | {status} | {trials} | {solved_at or '-'} | " + " | ".join(cells) + " |")
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
