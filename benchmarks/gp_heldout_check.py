"""How good were the dynamics GPs that PILCO runs actually planned with: one common held-out set.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gp_heldout_check.py --runs RUN_ID [RUN_ID ...]
        --trials 8 10 12 --test RUN_ID:FIRST-LAST [--tracking-uri URI] [--out FILE]

Loads the GP each run trained at each of ``--trials`` (``trialK/model_trialK.pt``, as saved: the
hyperparameters and pseudo-inputs it planned with) and scores all of them on the same transitions:
episodes ``FIRST`` to ``LAST`` (0-based, inclusive; random rollouts count) recorded by the run
``--test``, e.g. the later episodes of a run that solved the task, where good policies go. Scores
as in ``gp_budget_check``: one-step NLPD (nats per transition, summed over the state dimensions;
lower is better) and SMSE (0 = perfect, 1 = no better than the targets' mean). A run whose own
episodes are in the test set is marked: its GPs of those trials have not seen them either, since a
trial-K GP is trained on the episodes before trial K, but they come from its own policies.

Runs that differ only in a GP option (e.g. ``gp_refresh_pseudo``) and share a seed share their
data up to the first trial where the option acts, so their models can be compared trial by trial.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.gp_budget_check import one_step_scores  # noqa: E402
from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from plugins.pilco.policy import transitions  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402

#: learner options that tell apart runs of the GP experiments (the label of a run's row)
GP_OPTIONS = ("gp_fitc_evals", "gp_hyper_subset", "gp_refresh_pseudo", "num_pseudo", "sparse_threshold")


def parse_test(text: str) -> tuple[str, int, int]:
    """``"RUN:20-27"`` -> ``("RUN", 20, 27)``."""
    try:
        run_id, span = text.split(":")
        first, last = (int(v) for v in span.split("-"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--test {text!r}: expected RUN_ID:FIRST-LAST, e.g. 62916e51...:20-27") from None
    if not 0 <= first <= last:
        raise argparse.ArgumentTypeError(f"--test {text!r}: need 0 <= FIRST <= LAST")
    return run_id, first, last


def label(params: dict[str, str]) -> str:
    """The GP options the run logged with a value (not None, not False), e.g. ``gp_fitc_evals=100,
    gp_refresh_pseudo=True``; an option added after the run was made is absent from its label."""
    parts = [f"{k}={params[f'learner.{k}']}" for k in GP_OPTIONS if params.get(f"learner.{k}") not in (None, "None", "False")]
    return ", ".join(parts) or "GP options at their defaults"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", required=True)
    parser.add_argument("--trials", type=int, nargs="+", required=True)
    parser.add_argument("--test", type=parse_test, required=True)
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=None, help="markdown file (default: print only)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    test_run, first, last = args.test
    with SavedPilcoRun(test_run, args.tracking_uri) as run:
        episodes = run.episodes()
        if last >= len(episodes):
            sys.exit(f"--test: run {test_run} recorded {len(episodes)} episodes (0..{len(episodes) - 1}); asked for up to {last}")
        test_episodes, test_task = episodes[first:last + 1], run.params["task"]

    rows, n_test = [], 0
    for run_id in args.runs:
        with SavedPilcoRun(run_id, args.tracking_uri, task=test_task) as run:
            available = set(run.model_trials())
            for trial in args.trials:
                if trial not in available:
                    print(f"run {run_id[:8]}: no GP of trial {trial} (it has {min(available)}-{max(available)}); skipped", flush=True)
                    continue
                saved, model = run.saved_model(trial), run.model(trial)
                x, y = transitions(test_episodes, saved["layout"])
                nlpd, smse = one_step_scores(model, x, y)
                own = " (own episodes)" if run_id.startswith(test_run) or test_run.startswith(run_id) else ""
                rows.append((run_id[:8] + own, run.params.get("seed", "?"), label(run.params), trial,
                             int(saved["gp"]["inputs"].shape[0]), "FITC" if model.sparse else "full", nlpd, smse))
                n_test = len(x)
                print(f"{run_id[:8]} seed {rows[-1][1]} trial {trial}: NLPD {nlpd:.3f}, SMSE {smse:.4f}", flush=True)

    if not rows:
        sys.exit("no GP scored: none of the runs has a GP of the asked trials")
    lines = [
        f"# The GPs PILCO runs planned with, on one held-out set ({test_task})", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"Test set: episodes {first}-{last} of run `{test_run[:8]}` ({n_test} transitions). NLPD in nats per transition "
        "(summed over the state dimensions; lower is better); SMSE averaged over the state dimensions.", "",
        "| run | seed | GP options | trial | points | GP | NLPD | SMSE |",
        "|---|---|---|---|---|---|---|---|",
    ]
    lines += [f"| `{r}` | {s} | {lab} | {t} | {n} | {kind} | {nlpd:.3f} | {smse:.4f} |"
              for r, s, lab, t, n, kind, nlpd, smse in rows]
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
