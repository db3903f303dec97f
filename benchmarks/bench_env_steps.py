"""Raw environment throughput of the simulated tasks (steps per second, random actions).

Usage::

    .venv/bin/python benchmarks/bench_env_steps.py [--steps 20000] [--repeats 3] [--set task.key=value ...]

Prints steps/s for each env (best of ``--repeats``, resets included) and writes
``results/benchmarks/env_steps.md`` with the command, the machine load and the numbers.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from harness.errors import NumericalError  # noqa: E402
from tasks.cartpole import CartPole  # noqa: E402
from tasks.double_pendulum import CartDoublePendulum  # noqa: E402
from tasks.unicycle import Unicycle  # noqa: E402

#: the simulated tasks (stepped by tasks.simulation); dm_control's cart-pole is MuJoCo's business.
TASKS = {"cartpole": CartPole, "double-pendulum": CartDoublePendulum, "unicycle": Unicycle}


def steps_per_second(task, steps: int, seed: int = 0) -> tuple[float, float, int]:
    """``(steps per CPU second, steps per wall second, diverged episodes)`` under uniform random actions.

    An episode whose simulation diverges (:class:`~harness.errors.NumericalError`) is counted
    and replaced by a fresh one.

    CPU time of this process is the figure to compare across runs: the machine is shared, and
    wall time then measures the other jobs as much as the env.
    """
    env = task.make_env()
    rng = np.random.default_rng(seed)
    spec = task.spec
    actions = rng.uniform(spec.action_low, spec.action_high, size=(steps, spec.action_dim))
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
    return steps / (time.process_time() - cpu), steps / (time.perf_counter() - wall), diverged


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="TASK.KEY=VALUE",
                        help="task option, e.g. cartpole.substeps=40")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "env_steps.md")
    args = parser.parse_args(argv)
    options: dict[str, dict[str, str]] = {name: {} for name in TASKS}
    for item in args.set:
        key, value = item.split("=", 1)
        name, opt = key.rsplit(".", 1)
        options[name][opt] = value
    rows = []
    for name, cls in TASKS.items():
        task = cls(**options[name])
        runs = [steps_per_second(task, args.steps, seed=r) for r in range(args.repeats)]
        cpu, wall = max(r[0] for r in runs), max(r[1] for r in runs)
        diverged = sum(r[2] for r in runs)
        rows.append((name, task.spec.dt, task.options["substeps"], cpu, wall, diverged))
        print(f"{name:16s} dt={task.spec.dt:.2f}s substeps={task.options['substeps']:3d}  "
              f"{cpu:8.0f} steps/CPU-s  {wall:8.0f} steps/wall-s  diverged episodes: {diverged}", flush=True)
    command = "python benchmarks/bench_env_steps.py " + " ".join(argv if argv is not None else sys.argv[1:])
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# Raw env throughput of the simulated tasks",
        "",
        f"Command: `{command.strip()}`  ",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load average {load:.1f} at the start (shared machine), Python {platform.python_version()}  ",
        f"Random uniform actions, {args.steps} steps per repeat, best of {args.repeats}, resets included. "
        "steps/CPU-s uses this process's CPU time (comparable across loads); steps/wall-s is what "
        "a run on this shared machine saw.",
        "",
        "| env | dt [s] | RK4 sub-steps | steps/CPU-s | steps/wall-s | diverged episodes |",
        "|---|---|---|---|---|---|",
    ]
    lines += [f"| {n} | {dt:.2f} | {s} | {c:.0f} | {w:.0f} | {d} |" for n, dt, s, c, w, d in rows]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
