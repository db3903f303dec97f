"""Raw environment throughput of the simulated tasks (steps per CPU second, random actions).

Usage::

    .venv/bin/python benchmarks/bench_env_steps.py [--steps 10000] [--repeats 5] [--set task.key=value ...]
        [--tasks cartpole,unicycle] [--baseline PATH [--baseline-label COMMIT]]

Every measurement runs in a fresh worker process (this script with ``--worker``), so that the
current code and a ``--baseline`` checkout of an older commit (e.g. made with
``mkdir /tmp/base && git archive <commit> | tar -x -C /tmp/base``; its ``tasks`` package is
imported instead) are measured
the same way, interleaved repeat by repeat on the shared machine. Prints and writes
``results/benchmarks/env_steps.md``: the command, the load average, the median over the repeats
of steps per CPU second (and of steps per wall second) for each env, and the speed-up against
the baseline when one is given.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: task name -> (module, class). dmc-cartpole needs the ``dmc`` extra (dm_control).
TASKS = {
    "cartpole": ("tasks.cartpole", "CartPole"),
    "double-pendulum": ("tasks.double_pendulum", "CartDoublePendulum"),
    "unicycle": ("tasks.unicycle", "Unicycle"),
    "dmc-cartpole": ("tasks.dmc_cartpole", "DMCCartpole"),
}


def steps_per_second(task, steps: int, seed: int = 0) -> tuple[float, float, int, float]:
    """``(steps per CPU second, steps per wall second, diverged episodes, first step CPU s)`` under uniform random actions.

    Resets are included. The first step is timed on its own and left out of the rates: it carries
    one-off work (the unicycle's numba compilation). An episode whose simulation diverges
    (:class:`~harness.errors.NumericalError`) is counted and replaced by a fresh one. CPU time of
    this process is the figure to compare across runs: the machine is shared, and wall time then
    measures the other jobs as much as the env.
    """
    from harness.errors import NumericalError

    env = task.make_env()
    rng = np.random.default_rng(seed)
    spec = task.spec
    actions = rng.uniform(spec.action_low, spec.action_high, size=(steps, spec.action_dim))
    env.reset(seed=seed)
    cpu = time.process_time()
    env.step(actions[0])
    first = time.process_time() - cpu
    env.reset(seed=seed)
    cpu, wall = time.process_time(), time.perf_counter()
    diverged = 0
    for k in range(steps):
        try:
            _, _, terminated, truncated, _ = env.step(actions[k])
        except NumericalError:
            diverged += 1
            terminated = True
        if terminated or truncated:
            env.reset()
    return steps / (time.process_time() - cpu), steps / (time.perf_counter() - wall), diverged, first


def worker(root: Path, name: str, options: dict[str, str], steps: int, seed: int) -> dict:
    """One measurement with the ``tasks`` package of ``root``; returns the figures and the task's settings."""
    sys.path.insert(0, str(root))
    import importlib

    module, cls = TASKS[name]
    task = getattr(importlib.import_module(module), cls)(**options)
    cpu, wall, diverged, first = steps_per_second(task, steps, seed)
    opts = task.options
    return {"cpu": cpu, "wall": wall, "diverged": diverged, "first": first, "dt": task.spec.dt,
            "substeps": opts.get("substeps", opts.get("action_repeat"))}


def measure(root: Path, name: str, options: dict[str, str], steps: int, seed: int) -> dict:
    """Run :func:`worker` in a fresh interpreter (``root``'s code on the path, this file as the driver)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", name, "--root", str(root),
           "--steps", str(steps), "--seed", str(seed)]
    cmd += [f"--set={name}.{k}={v}" for k, v in options.items()]
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--tasks", default=",".join(TASKS), help="comma-separated task names")
    parser.add_argument("--set", action="append", default=[], metavar="TASK.KEY=VALUE",
                        help="task option, e.g. cartpole.substeps=40")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="checkout of an older commit to measure side by side (its tasks package)")
    parser.add_argument("--baseline-label", default=None, help="what the baseline is, e.g. its commit id")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "env_steps.md")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    parser.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    names = [n for n in args.tasks.split(",") if n]
    options: dict[str, dict[str, str]] = {name: {} for name in TASKS}
    for item in args.set:
        key, value = item.split("=", 1)
        name, opt = key.rsplit(".", 1)
        options[name][opt] = value
    if args.worker:
        print(json.dumps(worker(args.root, args.worker, options[args.worker], args.steps, args.seed)))
        return

    # imported here, not at the top: a worker may run with a baseline checkout first on its path
    sys.path.insert(0, str(ROOT))
    from benchmarks.report_file import command_line, load_average, machine_line, write_report

    load = load_average()
    versions = {"current": ROOT} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
    rows = []
    for name in names:
        runs: dict[str, list[dict]] = {v: [] for v in versions}
        for r in range(args.repeats):
            for version, root in versions.items():  # interleaved: both see the same machine load
                runs[version].append(measure(root, name, options[name], args.steps, seed=r))
        med = {v: {k: statistics.median(run.get(k, float("nan")) for run in rs) for k in ("cpu", "wall", "first")}
               for v, rs in runs.items()}
        first = runs["current"][0]
        row = {"name": name, "dt": first["dt"], "substeps": first["substeps"], "median": med,
               "spread": {v: (min(x["cpu"] for x in rs), max(x["cpu"] for x in rs)) for v, rs in runs.items()},
               "diverged": {v: sum(x["diverged"] for x in rs) for v, rs in runs.items()}}
        rows.append(row)
        text = "  ".join(f"{v}: {m['cpu']:7.0f} steps/CPU-s ({m['wall']:7.0f}/wall-s)" for v, m in med.items())
        print(f"{name:16s} dt={row['dt']:.2f}s sub-steps={row['substeps']:3d}  {text}", flush=True)
    lines = [
        "# Raw env throughput of the simulated tasks",
        "",
        f"Command: `{command_line(__file__, argv)}`  ",
        f"{machine_line(load)}  ",
        f"Uniform random actions, {args.steps} steps per repeat, resets included, each repeat in a fresh process; "
        f"median of {args.repeats} repeats (min-max in brackets). steps/CPU-s uses the process's CPU time "
        "(comparable across loads); steps/wall-s is what a run on this shared machine saw.",
    ]
    if args.baseline:
        label = f"commit {args.baseline_label}" if args.baseline_label else "an older commit"
        lines.append(f"Baseline: the `tasks` package of `{args.baseline}` ({label}), measured interleaved "
                     "with the current code.")
    lines.append("")
    if args.baseline:
        lines += ["| env | dt [s] | sub-steps | baseline steps/CPU-s | current steps/CPU-s | speed-up | "
                  "current steps/wall-s | current first step [CPU s] | diverged episodes |", "|---|---|---|---|---|---|---|---|---|"]
    else:
        lines += ["| env | dt [s] | sub-steps | steps/CPU-s | steps/wall-s | first step [CPU s] | diverged episodes |",
                  "|---|---|---|---|---|---|---|"]
    for row in rows:
        cur, (lo, hi) = row["median"]["current"], row["spread"]["current"]
        cells = [row["name"], f"{row['dt']:.2f}", str(row["substeps"])]
        if args.baseline:
            base, (blo, bhi) = row["median"]["baseline"], row["spread"]["baseline"]
            cells += [f"{base['cpu']:.0f} [{blo:.0f}-{bhi:.0f}]", f"{cur['cpu']:.0f} [{lo:.0f}-{hi:.0f}]",
                      f"{cur['cpu'] / base['cpu']:.2f}x"]
        else:
            cells += [f"{cur['cpu']:.0f} [{lo:.0f}-{hi:.0f}]"]
        cells += [f"{cur['wall']:.0f}", f"{cur['first']:.3f}", str(row["diverged"]["current"])]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Sub-steps: RK4 sub-steps per control step for the ODE tasks, MuJoCo physics steps "
              "(action repeat) for dmc-cartpole. First step: CPU seconds of a process's first env step, left out "
              "of the rates (one-off work such as the unicycle's numba compilation)."]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
