"""One learning run on a machine without an MLflow store (e.g. a lent GPU machine), its trials written as they end.

Usage::

    python benchmarks/device_run.py --learner mc-pilco --task unicycle --seed 100 --set learner.device=cuda \\
        --set task.init=code --max-trials 30 --out results/benchmarks/device_run_mc-pilco_unicycle.md

The run is :func:`harness.runner.run` with an in-memory tracker (nothing is stored, no checkpoint
survives the process): it is for measuring what a trial costs on a device and what the first trials
of a tuning seed do, not for reported results (those come from ``harness sweep`` into the store).
Runs sharing one machine should say how many threads each may use (``OMP_NUM_THREADS=N`` or
``--set learner.threads=N``): otherwise each takes every core (:func:`harness.threads.run_threads`).
After every hand-over the script prints the harness's progress line and rewrites ``--out`` (markdown:
a row per trial with the interaction, evaluation, the learner's J and where the trial's wall time
went) and a JSON file beside it with every metric, so a run stopped by a time limit keeps its trials.

``--resume-checkpoint FILE`` continues a stored run from one of its checkpoints (``harness store checkpoints
--paths`` lists them; the command must repeat the run's seed and options, as ``harness bench --resume``): a
late trial's cost on a device without re-running the trials before it. The newest checkpoint is copied
beside ``--out`` (``.ckpt``) after every trial.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402

if TYPE_CHECKING:
    from harness.tracking import MemoryTracker

#: metric -> column heading, in the table's order (a metric the learner does not log shows as "-")
COLUMNS = {
    "interaction_seconds": "interaction s", "eval_cost": "eval cost", "eval_success_rate": "eval success",
    "J_before": "J before", "J_after": "J after", "model_train_seconds": "GP fit s",
    "policy_opt_seconds": "policy search s", "policy_steps": "search steps", "policy_evaluations": "evaluations",
    "trial_wall_seconds": "trial wall s", "wall_seconds": "wall s (run)",
}


class FileProgress:
    """A :class:`~harness.progress.ProgressReporter` that prints each hand-over and rewrites the report."""

    def __init__(self, header: list[str], out: Path, tracker: MemoryTracker | None = None,
                 previous_wall: float | None = None) -> None:
        """``tracker``: the run's, whose newest checkpoint is copied beside ``out`` after every trial;
        ``previous_wall``: the run's wall time at the checkpoint it resumed from (None: a new run)."""
        self.header, self.out, self.records = header, out, []
        self.tracker = tracker
        self.previous_wall = previous_wall

    def start(self, title: str, total: float | None, unit: str) -> None:
        print(f"{title}: up to {total} {unit}", flush=True)

    def update(self, record: dict[str, Any], completed: float) -> None:
        from harness.progress import format_record

        print(format_record(record, self.previous_wall), flush=True)
        row = dict(record)
        if self.previous_wall is not None and record.get("wall_seconds") is not None:
            row["trial_wall_seconds"] = record["wall_seconds"] - self.previous_wall
        elif self.previous_wall is None and not self.records:
            row["trial_wall_seconds"] = record.get("wall_seconds")  # a run's first trial starts at 0
        self.previous_wall = record.get("wall_seconds")
        self.records.append(row)
        self.write()
        stored = self.tracker.list_artifacts("checkpoints") if self.tracker is not None else []
        if stored:  # checkpoint_name() pads the trial: the last name is the newest
            fetched = self.tracker.fetch_artifact(stored[-1], Path(tempfile.mkdtemp(prefix="device-run-")))
            shutil.move(fetched, self.out.with_suffix(".ckpt"))

    def status(self, text: str) -> None:  # within a trial: not printed (the device's output is read at the end)
        pass

    def finish(self, summary: str) -> None:
        print(summary, flush=True)
        self.write(summary)

    def write(self, summary: str | None = None) -> None:
        def cell(record: dict[str, Any], key: str) -> str:
            value = record.get(key)
            if value is None:
                return "-"
            if key == "eval_success_rate":
                return f"{100 * value:.0f} %"
            return f"{value:.0f}" if key in ("policy_steps", "policy_evaluations") else f"{value:.2f}"

        lines = list(self.header)
        lines += ["| trial | " + " | ".join(COLUMNS.values()) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
        lines += [f"| {r['trial']} | " + " | ".join(cell(r, key) for key in COLUMNS) + " |" for r in self.records]
        lines += ["", summary or f"(in progress: {len(self.records)} trials written, {time.strftime('%H:%M:%S')} UTC)"]
        write_report(lines, self.out, echo=False)
        write_report([json.dumps(self.records, indent=1, default=float)], self.out.with_suffix(".json"), echo=False)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--learner", required=True)
    parser.add_argument("--task", required=True)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="learner or task option, as harness bench --set (prefix learner./task. if ambiguous)")
    parser.add_argument("--max-trials", type=int, default=None)
    parser.add_argument("--budget-seconds", type=float, default=None)
    parser.add_argument("--out", type=Path, required=True, help="markdown report (a .json with every metric beside it)")
    parser.add_argument("--resume-checkpoint", type=Path, default=None, metavar="FILE",
                        help="continue from this checkpoint of a run (same seed and options as the run)")
    args = parser.parse_args(argv)

    from harness.checkpoint import checkpoint_name, load_checkpoint
    from harness.errors import CheckpointError
    from harness.interrupts import StopRequested
    from harness.options import parse_assignments
    from harness.runner import RunConfig, route_options, run
    from harness.tracking import MemoryTracker

    learner_options, task_options = route_options(args.learner, args.task, parse_assignments(args.set))

    config = RunConfig(args.learner, args.task, seed=args.seed, learner_options=learner_options, task_options=task_options,
                       max_trials=args.max_trials, budget_seconds=args.budget_seconds)
    config.validate()
    header = [f"# {args.learner} on {args.task}, seed {args.seed}: one run without a store", "",
              f"Command: `{command_line(__file__, argv)}`  ", f"{machine_line(load_average())}  "]
    try:
        import torch

        if torch.cuda.is_available():
            header[-1] += f"GPU: {torch.cuda.get_device_name(0)}.  "
    except ImportError:
        pass
    header += [f"Options: learner {learner_options or '{}'}, task {task_options or '{}'}. Nothing of this run is in the "
               "store: a tuning-seed measurement, not a reported result.", ""]
    tracker, resume_id, previous_wall = MemoryTracker(), None, None
    if args.resume_checkpoint is not None:
        if not args.resume_checkpoint.is_file():
            raise CheckpointError(f"no checkpoint file {args.resume_checkpoint}; list a run's with harness store checkpoints --paths")
        # the in-memory tracker holds the file as a run's checkpoint artifact (under the runner's name for its
        # trial), which run() resumes from
        checkpoint = load_checkpoint(args.resume_checkpoint)
        resume_id = tracker.start("", f"resumed from {args.resume_checkpoint.name}", params={}, tags={})
        staged = Path(tempfile.mkdtemp(prefix="device-run-")) / checkpoint_name(checkpoint.trial)
        tracker.log_artifact(Path(shutil.copy2(args.resume_checkpoint, staged)), "checkpoints")
        header[-2] += f" Resumed from `{args.resume_checkpoint.name}` after trial {checkpoint.trial} (not re-run)."
        # the first resumed trial's own wall is measured from the checkpoint's
        previous_wall = checkpoint.history[-1].get("wall_seconds") if checkpoint.history else None
    progress = FileProgress(header, args.out, tracker, previous_wall)
    try:
        result = run(config, tracker=tracker, progress=progress, resume_run_id=resume_id)
    except StopRequested as exc:  # the file says so too: left as it was, it would read "in progress"
        progress.finish(f"({len(progress.records)} trial(s) written, {time.strftime('%H:%M:%S')} UTC; {exc}: continue with "
                        f"the same command and --resume-checkpoint {args.out.with_suffix('.ckpt')})")
        return
    print(f"solved: {result.solved}; interaction to success: {result.interaction_time_to_success}; "
          f"trials: {result.trials}; stop: {result.stop_reason}", flush=True)


if __name__ == "__main__":
    exit_on_error(main)
