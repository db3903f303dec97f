"""Side-by-side timing of one PILCO J(theta) + dJ/dtheta evaluation for two checkouts of this repo.

Usage::

    .venv/bin/python benchmarks/compare_objective.py --before /path/to/old/checkout --after . [--rounds 3] [--repeats 10]

Every measurement runs in a fresh subprocess with one torch thread (``PYTHONPATH`` = that checkout,
so each side imports its own ``plugins.pilco``); the subprocesses alternate ``before, after,
before, after, ...`` so that both sides see the same machine load. Each builds the objective of
``benchmarks/bench_objective.py`` (cart-pole, T = 40, RBF policy with 50 centres; full GP with
n = 100 and 300, FITC with n = 1000 and 300 pseudo-inputs) or, with ``--tasks``, the learner's
objective at a real task's size (``benchmarks/task_objectives.py``, loaded from *this* checkout by
both sides: the unicycle, 55 output pairs on n = 300 basis points over 40 steps; the
cart-double-pendulum, 21 pairs on n = 400 over 60 steps) and reports, per configuration:

* median wall and CPU (``time.process_time``) milliseconds of ``--repeats`` J + dJ evaluations
  after 3 warm-ups (the medians of the rounds are then medianed), and the fastest single evaluation's CPU time
  over all rounds (on a shared machine whose speed drifts by tens of per cent, the least disturbed one);
* aten operator calls per J + dJ (``TorchDispatchMode``);
* memory: growth of the process's peak resident set (``VmHWM``) over the evaluations, from just
  after the objective is built (what one J + dJ adds at its peak, buffers kept between evaluations included);
* J and dJ of both sides at the same theta, and their relative differences; for scale, how much J
  and dJ of the *same* side change when every entry of theta moves by one or two ulps (the
  objective's own rounding sensitivity: two implementations that round differently cannot agree
  more closely than this).

Writes a markdown table to ``--out`` (default ``results/benchmarks/objective_gradient_before_after.md``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # for benchmarks.report_file; the measured code is imported by the child processes

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402

CONFIGS = {"full n=100": (100, None), "full n=300": (300, None), "FITC n=1000, 300 pseudo": (1000, 300)}
TASK_FILE = ROOT / "benchmarks" / "task_objectives.py"

CHILD = r"""
import json, os, sys, time
root, config, repeats, task_file, threads = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], int(sys.argv[5])
sys.path.insert(0, root)
import numpy as np, torch
torch.set_num_threads(1)
sys.argv = [sys.argv[0]]
from collections import Counter
from torch.utils._python_dispatch import TorchDispatchMode

def status_mb(key):
    with open("/proc/self/status") as fh:
        return int(next(l for l in fh if l.startswith(key)).split()[1]) / 1024

if config.startswith("task:"):
    import importlib.util
    spec = importlib.util.spec_from_file_location("task_objectives", task_file)
    tasks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tasks)
    obj = tasks.task_objective(*tasks.TASK_CONFIGS[config[5:]])
else:
    from benchmarks.bench_objective import dynamics_posterior, make_objective
    n, pseudo = json.loads(config)
    obj = make_objective(dynamics_posterior(n, pseudo))
if threads > 1:  # as the learner does: the compiled kernel runs its own threads, the torch path torch's
    import inspect
    from plugins.pilco.moments import MomentMatchingGP
    if "threads" in inspect.signature(MomentMatchingGP).parameters:
        obj.dynamics = MomentMatchingGP(obj.posterior, threads=threads)
        torch.set_num_threads(1 if obj.dynamics.kernel in ("numba", "fused") else threads)
    else:
        torch.set_num_threads(threads)
theta = obj.get_flat()
hwm0 = status_mb("VmHWM")
for _ in range(3):
    J, g = obj(theta)
wall, cpu = [], []
for _ in range(repeats):
    t0, c0 = time.perf_counter(), time.process_time()
    obj(theta)
    wall.append(time.perf_counter() - t0)
    cpu.append(time.process_time() - c0)
hwm1 = status_mb("VmHWM")

class Counting(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.calls = 0
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.calls += 1
        return func(*args, **(kwargs or {}))

with Counting() as counter:
    obj(theta)
rng = np.random.default_rng(0)
J1, g1 = obj(theta * (1 + np.finfo(float).eps * rng.choice([-2.0, -1.0, 1.0, 2.0], theta.shape)))
print(json.dumps(dict(wall=1e3 * float(np.median(wall)), cpu=1e3 * float(np.median(cpu)), cpu_min=1e3 * min(cpu), peak_growth_mb=hwm1 - hwm0,
                      ops=counter.calls, J=float(J), grad=g.tolist(), ulp_rel_j=abs(J1 - J) / abs(J),
                      ulp_rel_g=float(np.linalg.norm(g1 - g) / np.linalg.norm(g)))))
"""


def run_child(root: str, config: str, repeats: int, threads: int = 1, extra_env: dict | None = None) -> dict:
    """One side's measurements in a fresh process; ``config``: ``json [n, pseudo]`` or ``task:<name>``;
    ``extra_env``: variables for this side (e.g. ``HARNESS_PILCO_KERNEL=torch``)."""
    env = dict(os.environ, PYTHONPATH=root, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), **(extra_env or {}))
    args = [sys.executable, "-c", CHILD, root, config, str(repeats), str(TASK_FILE), str(threads)]
    proc = subprocess.run(args, capture_output=True, text=True, env=env, cwd=root, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed for {root} {config}:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _commit(root: str) -> str:
    """The checkout's commit, ``+dirty`` if its code differs from it (``git describe``-like)."""
    sha = subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", root, "status", "--porcelain", "--", "harness", "plugins", "tasks"], capture_output=True, text=True).stdout.strip()
    return (sha or "no git") + ("+dirty" if dirty else "")


def _env_text(env: dict) -> str:
    return "".join(f", {k}={v}" for k, v in env.items())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", required=True, help="checkout with the old implementation")
    parser.add_argument("--after", default=str(ROOT), help="checkout with the new implementation")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--tasks", action="store_true", help="the real-task configurations of benchmarks/task_objectives.py instead of the cart-pole ones")
    parser.add_argument("--out", default=None, help="default: results/benchmarks/objective_gradient_before_after[_tasks].md")
    parser.add_argument("--before-env", action="append", default=[], metavar="KEY=VALUE",
                        help="environment variable for the before side's processes (repeatable), e.g. HARNESS_PILCO_KERNEL=torch")
    parser.add_argument("--after-env", action="append", default=[], metavar="KEY=VALUE", help="the same for the after side")
    parser.add_argument("--threads", type=int, default=1, help="threads per side (the learner's split: the compiled kernel's "
                        "own threads, else torch's); above 1 compare wall times")
    args = parser.parse_args()
    sides = {"before": str(Path(args.before).resolve()), "after": str(Path(args.after).resolve())}
    side_env = {side: dict(kv.split("=", 1) for kv in getattr(args, f"{side}_env")) for side in sides}
    if args.tasks:
        spec = importlib.util.spec_from_file_location("task_objectives", TASK_FILE)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        configs = {name: f"task:{name}" for name in module.TASK_CONFIGS}
    else:
        configs = {name: json.dumps([n, pseudo]) for name, (n, pseudo) in CONFIGS.items()}
    out = args.out or str(ROOT / "results" / "benchmarks" / f"objective_gradient_before_after{'_tasks' if args.tasks else ''}.md")

    load_before = load_average()
    results = {name: {side: [] for side in sides} for name in configs}
    for _ in range(args.rounds):
        for name, config in configs.items():
            for side, root in sides.items():
                results[name][side].append(run_child(root, config, args.repeats, args.threads, side_env[side]))
                r = results[name][side][-1]
                print(f"{name:26s} {side:6s} wall {r['wall']:7.1f} ms  cpu {r['cpu']:7.1f} ms", flush=True)

    lines = [
        "# PILCO objective J + dJ: before / after, side by side ("
        + ("the learner's objective at the unicycle's and the cart-double-pendulum's sizes, benchmarks/task_objectives.py)" if args.tasks
           else "cart-pole setting of bench_objective.py)"),
        "",
        f"Command: `{command_line(__file__)}`  ",
        f"{machine_line(load_before)} Prefer CPU time and ratios.  ",
        f"before = `{sides['before']}` ({_commit(sides['before'])}{_env_text(side_env['before'])}), after = `{sides['after']}` "
        f"({_commit(sides['after'])}{_env_text(side_env['after'])}); {args.rounds} rounds x {args.repeats} "
        f"evaluations per side and configuration, alternating subprocesses, {args.threads} thread{'s' if args.threads > 1 else ''}; medians, and the fastest evaluation.",
        "",
        "| dynamics posterior | wall ms before / after | CPU ms before / after | CPU speed-up | fastest CPU ms before / after (speed-up) "
        "| aten calls before / after "
        "| peak RSS growth MB before / after | rel. diff J | rel. diff dJ (2-norm) | max abs diff dJ / max abs dJ "
        "| before's own change of J, dJ for theta +- 1-2 ulp |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, per_side in results.items():
        med = {side: {k: statistics.median(r[k] for r in runs) for k in ("wall", "cpu", "peak_growth_mb")} for side, runs in per_side.items()}
        fast = {side: min(r["cpu_min"] for r in runs) for side, runs in per_side.items()}  # the least-disturbed evaluation
        b, a = per_side["before"][0], per_side["after"][0]
        gb, ga = np.array(b["grad"]), np.array(a["grad"])
        rel_j = abs(a["J"] - b["J"]) / abs(b["J"])
        rel_g = np.linalg.norm(ga - gb) / np.linalg.norm(gb)
        max_g = np.max(np.abs(ga - gb)) / np.max(np.abs(gb))
        lines.append(
            f"| {name} | {med['before']['wall']:.0f} / {med['after']['wall']:.0f} | {med['before']['cpu']:.0f} / {med['after']['cpu']:.0f} "
            f"| {med['before']['cpu'] / med['after']['cpu']:.2f} | {fast['before']:.0f} / {fast['after']:.0f} ({fast['before'] / fast['after']:.2f}) "
            f"| {b['ops']} / {a['ops']} "
            f"| {med['before']['peak_growth_mb']:.0f} / {med['after']['peak_growth_mb']:.0f} | {rel_j:.1e} | {rel_g:.1e} | {max_g:.1e} "
            f"| {b['ulp_rel_j']:.1e}, {b['ulp_rel_g']:.1e} |"
        )
    write_report(lines, out)


if __name__ == "__main__":
    main()
