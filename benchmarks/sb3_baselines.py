"""Run the SAC / PPO baselines through the CLI, one process at a time, and collect one row per seed.

Each run is exactly ``harness bench --learner L --task T --seed S --budget-seconds B -q
--tracking-uri URI [--set ...]``; its one-line summary is parsed and appended (immediately, so a
partial sweep keeps what finished) to ``results/baselines/sb3_<task>.csv``. ``--summarise``
rewrites ``results/baselines/sb3_<task>.md`` from the CSV: the exact commands, per-seed rows and
medians (an unsolved run counts as "> budget"; a median that falls on an unsolved run is a lower
bound and is printed as such).

    .venv/bin/python benchmarks/sb3_baselines.py --learner sac --task cartpole --seeds 0 1 2 3 4 --budget-seconds 2000
    .venv/bin/python benchmarks/sb3_baselines.py --task cartpole --summarise
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import write_report  # noqa: E402

OUT = ROOT / "results" / "baselines"
DEFAULT_URI = f"sqlite:///{ROOT / 'results' / 'runs' / 'mlflow.db'}"
FIELDS = [
    "learner", "task", "seed", "solved", "interaction_time_to_success", "trials_to_success", "trials",
    "interaction_seconds", "interaction_episodes", "budget_seconds", "wall_seconds", "stop_reason",
    "run_id", "finished_utc", "command",
]
SOLVED = re.compile(r"SOLVED after ([\d.]+) s of interaction \((\d+) episodes, (\d+) trials\), wall (\d+) s")
UNSOLVED = re.compile(r"not solved \((.+?)\) after ([\d.]+) s of interaction \((\d+) episodes, (\d+) trials\), wall (\d+) s")
RUN_ID = re.compile(r"MLflow run (\w+)")


def run_one(learner: str, task: str, seed: int, budget: float, sets: list[str], uri: str) -> dict:
    cmd = [str(ROOT / ".venv" / "bin" / "harness"), "bench", "--learner", learner, "--task", task, "--seed", str(seed),
           "--budget-seconds", f"{budget:g}", "-q", "--tracking-uri", uri]
    for s in sets:
        cmd += ["--set", s]
    shown = "harness " + " ".join(shlex.quote(c) for c in cmd[1:])
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - start
    out = proc.stdout + proc.stderr
    row = {"learner": learner, "task": task, "seed": seed, "budget_seconds": budget, "command": shown,
           "finished_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"), "wall_seconds": f"{wall:.0f}"}
    if m := SOLVED.search(out):
        row.update(solved=True, interaction_time_to_success=m[1], trials_to_success=m[2], trials=m[3],
                   interaction_seconds=m[1], interaction_episodes=m[2], stop_reason="solved")
    elif m := UNSOLVED.search(out):
        row.update(solved=False, interaction_time_to_success="", trials_to_success="", trials=m[4],
                   interaction_seconds=m[2], interaction_episodes=m[3], stop_reason=m[1])
    else:
        row.update(solved=False, stop_reason=f"error (exit {proc.returncode}): {out.strip().splitlines()[-1] if out.strip() else ''}")
    if m := RUN_ID.search(out):
        row["run_id"] = m[1]
    return row


def append(row: dict, path: Path) -> None:
    new = not path.exists()
    with open(path, "a", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=FIELDS)
        if new:
            writer.writeheader()
        writer.writerow({k: row.get(k, "") for k in FIELDS})


def _median_text(rows: list[dict]) -> str:
    """Median interaction time to success; unsolved runs sort last as '> budget'."""
    keyed = sorted(((float(r["interaction_time_to_success"]) if r["solved"] == "True" else math.inf, r) for r in rows),
                   key=lambda pair: pair[0])
    n = len(keyed)
    if n == 0:
        return "-"
    mids = [keyed[(n - 1) // 2], keyed[n // 2]]
    if any(math.isinf(v) for v, _ in mids):
        return f"> {min(float(r['budget_seconds']) for _, r in mids):g} s (more than half unsolved within the budget)"
    return f"{(mids[0][0] + mids[1][0]) / 2:.1f} s"


def summarise(task: str) -> Path:
    csv_path = OUT / f"sb3_{task}.csv"
    rows = list(csv.DictReader(open(csv_path)))
    lines = [f"# SAC / PPO (stable-baselines3) on `{task}`: interaction time to success", "",
             "One row per run; made by `benchmarks/sb3_baselines.py` (it runs the exact command shown, one",
             "process at a time on the shared 2-core machine, torch threads 1). Success: the harness's",
             "evaluation (10 episodes on a separate, uncounted environment, >= 90 % successful) after a hand-over;",
             "interaction time = counted steps x dt before that hand-over. Unsolved runs are reported with the",
             "budget as a lower bound, never as a number. Wall = wall-clock seconds of the whole command",
             "(imports and evaluations included). Tracking store: `results/runs/mlflow.db`.", ""]
    for learner in sorted({r["learner"] for r in rows}):
        sub = [r for r in rows if r["learner"] == learner]
        solved = sum(r["solved"] == "True" for r in sub)
        lines += [f"## {learner}", "", f"Solved {solved}/{len(sub)}; median interaction time to success: {_median_text(sub)}.", "",
                  "| seed | solved | interaction time to success [s] | episodes | trials | interaction used [s] | budget [s] | wall [s] | stop |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in sub:
            t = r["interaction_time_to_success"] if r["solved"] == "True" else f"> {float(r['budget_seconds']):g} (unsolved)"
            lines.append(f"| {r['seed']} | {r['solved']} | {t} | {r['interaction_episodes']} | {r['trials']} | "
                         f"{r['interaction_seconds']} | {float(r['budget_seconds']):g} | {r['wall_seconds']} | {r['stop_reason']} |")
        lines += ["", "Commands:", "", "```"] + [r["command"] for r in sub] + ["```", ""]
    notes = OUT / f"sb3_{task}_notes.md"  # hand-written reading of the runs, kept across regenerations
    if notes.exists():
        lines += ["## Notes", "", notes.read_text().strip(), ""]
    md = OUT / f"sb3_{task}.md"
    write_report(lines, md, echo=False)
    return md


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--learner", choices=("sac", "ppo"))
    parser.add_argument("--task", required=True)
    parser.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    parser.add_argument("--budget-seconds", type=float)
    parser.add_argument("--set", dest="sets", action="append", default=[])
    parser.add_argument("--tracking-uri", default=DEFAULT_URI)
    parser.add_argument("--stop-after", default=None, help="UTC HH:MM; start no run after this time")
    parser.add_argument("--summarise", action="store_true")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    (ROOT / "results" / "runs").mkdir(parents=True, exist_ok=True)
    if not args.summarise:
        if args.learner is None or args.budget_seconds is None:
            parser.error("--learner and --budget-seconds are needed to run")
        for seed in args.seeds:
            if args.stop_after and datetime.now(timezone.utc).strftime("%H:%M") >= args.stop_after:
                print(f"not starting seed {seed}: past {args.stop_after} UTC", flush=True)
                break
            row = run_one(args.learner, args.task, seed, args.budget_seconds, args.sets, args.tracking_uri)
            append(row, OUT / f"sb3_{args.task}.csv")
            print({k: row.get(k) for k in ("learner", "seed", "solved", "interaction_time_to_success", "interaction_seconds", "wall_seconds", "stop_reason")}, flush=True)
    summarise(args.task)
    sys.exit(0)


if __name__ == "__main__":
    main()
