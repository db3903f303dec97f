"""One real PILCO trial under two checkouts, side by side: a stored run resumed for one trial by each.

Usage::

    .venv/bin/python benchmarks/compare_trial.py --before /path/to/old/checkout --after . \\
        --store results/runs --run RUN_ID -- -l pilco -t double-pendulum --seed 3 --max-trials 40 --set task.horizon=60 ...

The store folder (``mlflow.db`` and ``mlruns``) is copied once per side, relocated, and the run's
old pickled checkpoints converted (``harness store migrate``, this checkout's code); then both sides
run ``harness bench <args> --resume RUN_ID`` at the same time, each with one torch thread
(``--set threads=1``; ``PYTHONPATH`` = its checkout), and get ``SIGUSR1`` at once: each stops after
the trial it resumes with. So both see the same data, the same GP warm start and the same machine
load. Reported per side from the trial's own metrics: GP training and policy search seconds, J + dJ
evaluations, seconds per evaluation, and the trial's whole wall time (from the process start).
Writes ``--out`` (default ``results/benchmarks/trial_before_after.md``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402


def harness(checkout: Path, args: list[str], **kwargs) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(checkout), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "harness", *args], cwd=checkout, env=env, **kwargs)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--") if "--" in argv else len(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True)
    parser.add_argument("--after", type=Path, default=ROOT)
    parser.add_argument("--store", type=Path, required=True, help="folder holding mlflow.db and mlruns")
    parser.add_argument("--run", required=True, help="the run to resume for one trial")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "trial_before_after.md")
    args = parser.parse_args(argv[:split])
    bench = argv[split + 1 :]
    from harness.store import Store

    work = Path(tempfile.mkdtemp(prefix="compare-trial-"))
    sides = {"before": args.before.resolve(), "after": args.after.resolve()}
    uris = {}
    for side in sides:
        shutil.copytree(args.store, work / side)
        uris[side] = f"sqlite:///{work / side / 'mlflow.db'}"
        for command in (["store", "relocate"], ["store", "migrate", args.run, "--yes"]):
            harness(ROOT, [*command, "--tracking-uri", uris[side]], stdout=subprocess.DEVNULL).wait()
    first = len(Store(uris["after"]).run(args.run).history("interaction_seconds")) + 1
    load = load_average()
    procs, started, ended, logs = {}, {}, {}, {}
    for side, checkout in sides.items():
        log = logs[side] = tempfile.TemporaryFile(mode="w+")  # the run's output, its last line echoed below
        procs[side] = harness(checkout, ["bench", *bench, "--set", "threads=1", "--resume", args.run, "--tracking-uri", uris[side]],
                              stdout=log, stderr=subprocess.STDOUT)
        started[side] = time.perf_counter()
    time.sleep(30)  # past the imports: the stop request is honoured after the resumed trial
    for proc in procs.values():
        proc.send_signal(signal.SIGUSR1)
    while len(ended) < len(procs):
        for side, proc in procs.items():
            if side not in ended and proc.poll() is not None:
                ended[side] = time.perf_counter()
        time.sleep(1)
    rows = []
    for side in sides:
        run = Store(uris[side]).run(args.run)
        metric = lambda key: run.history(key).get(first, float("nan"))  # noqa: E731, B023
        gp, policy, evals = metric("model_train_seconds"), metric("policy_opt_seconds"), metric("policy_evaluations")
        rows.append((side, gp, policy, evals, policy / evals, ended[side] - started[side], metric("J_after")))
        logs[side].seek(0)
        print(f"{side}: {logs[side].read().strip().splitlines()[-1:]}")
    lines = [f"# One PILCO trial, before / after, side by side (run `{args.run[:8]}` resumed at trial {first})", "",
             f"Command: `{command_line(__file__, argv)}`  ", f"{machine_line(load)}  ",
             f"before = `{sides['before']}`, after = `{sides['after']}`; both processes at once, one torch thread each.", "",
             "| side | GP training s | policy search s | J + dJ evaluations | s per evaluation | trial wall s (process) | J after |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {s} | {gp:.1f} | {p:.1f} | {e:.0f} | {p / e:.3f} | {w:.0f} | {j:.4f} |" for s, gp, p, e, _, w, j in rows]
    (_, gp0, p0, _, pe0, w0, _), (_, gp1, p1, _, pe1, w1, _) = rows
    lines += ["", f"Speed-up after/before: GP training {gp0 / gp1:.2f}x, policy search {p0 / p1:.2f}x, per evaluation {pe0 / pe1:.2f}x, "
              f"trial wall {w0 / w1:.2f}x."]
    write_report(lines, args.out)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
