"""One PILCO J + dJ with two settings of the dynamics' moment matching, interleaved in one process.

Usage::

    .venv/bin/python benchmarks/ab_objective.py --a symmetric_pairs=false --b symmetric_pairs=true \\
        [--configs "double-pendulum n=400 H=60" "unicycle n=300 H=40" "cart-pole full n=100" ...] [--rounds 12]

``--a`` and ``--b`` are keyword arguments of :class:`plugins.pilco.moments.MomentMatchingGP`
(``kernel=fused``, ``symmetric_pairs=false``, ``threads=2``), ``torch_threads=K``: torch's intra-op threads while
that side runs (default ``--torch-threads``; the learner gives torch all its threads with ``kernel=torch`` and one
with a compiled kernel, which runs its own: ``--a kernel=torch,torch_threads=2 --b kernel=fused,threads=2`` compares
the two as a two-core run uses them), ``compile_step=true``: that side's rollout steps as ``torch.compile``'d code
(the objective's ``compile_step``; needs ``kernel=torch``; its first J + dJ, the build, is in the warm-up), and ``moments=PATH``: take the class from
another checkout's ``plugins/pilco/moments.py`` (loaded under its own module name; what it imports
comes from this checkout, so it must fit this checkout's kernels: for a change inside moment matching
itself, e.g. ``--a moments=/tmp/old/plugins/pilco/moments.py``). Each configuration's objective is built
once (``benchmarks/task_objectives.py`` for the real tasks, ``benchmarks/bench_objective.py`` for the
cart-pole ones) and J + dJ is then timed ``--rounds`` times per side, alternating ``a b``, ``b a``, ...
On a shared machine whose load changes by 10-30 % from minute to minute (this project's: two vCPUs
that the sweeps share), two sides timed seconds apart in one process see the same load; two
processes started in turn (``benchmarks/compare_objective.py``, which compares checkouts) may not.

Reported per configuration: median and minimum CPU milliseconds (``time.process_time``; wall where
threads > 1), the ratio of the medians a / b, and how far J and dJ of the two sides are apart next to
how far they move for a 1-2 ulp change of theta (the objective's own rounding sensitivity).
Writes ``--out`` (markdown).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402

CARTPOLE = {"cart-pole full n=100": (100, None), "cart-pole full n=300": (300, None),
            "cart-pole FITC n=1000, 300 pseudo": (1000, 300)}


def parse_side(text: str) -> dict:
    """``"kernel=fused,symmetric_pairs=false"`` -> ``{"kernel": "fused", "symmetric_pairs": False}``."""
    out = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--a/--b: {item!r} is not KEY=VALUE (e.g. symmetric_pairs=false)")
        low = value.strip().lower()
        out[key.strip()] = {"true": True, "false": False}.get(low, int(low) if low.isdigit() else value.strip())
    return out


def build(config: str):
    """The objective of one configuration name (a task of ``task_objectives.TASK_CONFIGS`` or ``CARTPOLE``)."""
    if config in CARTPOLE:
        from benchmarks.bench_objective import dynamics_posterior, make_objective

        return make_objective(dynamics_posterior(*CARTPOLE[config]))
    spec = importlib.util.spec_from_file_location("task_objectives", ROOT / "benchmarks" / "task_objectives.py")
    tasks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tasks)
    if config not in tasks.TASK_CONFIGS:
        raise SystemExit(f"unknown configuration {config!r}; choose from {sorted([*tasks.TASK_CONFIGS, *CARTPOLE])}")
    return tasks.task_objective(*tasks.TASK_CONFIGS[config])


def moments_class(path: str | None):
    """``MomentMatchingGP`` of this checkout (``path`` None) or of the ``moments.py`` at ``path``."""
    if path is None:
        from plugins.pilco.moments import MomentMatchingGP

        return MomentMatchingGP
    file = Path(path)
    if not file.is_file():
        raise SystemExit(f"moments={path}: no such file (give another checkout's plugins/pilco/moments.py)")
    spec = importlib.util.spec_from_file_location(f"_ab_moments_{abs(hash(str(file.resolve())))}", file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    from plugins.pilco.moments import MomentMatchingGP

    # a subclass of this checkout's class with every method of the other one: callers that check
    # isinstance(..., MomentMatchingGP) (the rollout) take it as it is instead of wrapping it
    members = {k: v for k, v in vars(module.MomentMatchingGP).items() if k not in ("__dict__", "__weakref__")}
    return type("OtherMomentMatchingGP", (MomentMatchingGP,), members)


def measure(config: str, sides: dict[str, dict], rounds: int, torch_threads: int = 1) -> dict:
    """Times J + dJ of ``config`` under each side's ``MomentMatchingGP`` settings, interleaved (torch's
    threads per side: its ``torch_threads``, else ``torch_threads``; the caller's setting is restored after)."""
    before = torch.get_num_threads()
    try:
        return _measure(config, sides, rounds, torch_threads)
    finally:
        torch.set_num_threads(before)


def _measure(config: str, sides: dict[str, dict], rounds: int, torch_threads: int) -> dict:
    obj = build(config)
    models = {}
    for name, kwargs in sides.items():
        options = {k: v for k, v in kwargs.items() if k not in ("moments", "torch_threads", "compile_step")}
        if kwargs.get("compile_step") and options.get("kernel") != "torch":
            raise SystemExit(f"--a/--b: compile_step=true needs kernel=torch on the same side (got {kwargs})")
        models[name] = moments_class(kwargs.get("moments"))(obj.posterior, **options)
    theta = obj.get_flat()
    results, times = {}, {name: [] for name in sides}

    def use(name: str) -> None:
        obj.dynamics = models[name]
        obj.compile_step = bool(sides[name].get("compile_step", False))
        torch.set_num_threads(int(sides[name].get("torch_threads", torch_threads)))

    first = {}
    for name in models:  # warm-up (compiles the kernels) and each side's own result
        use(name)
        t0 = time.perf_counter()
        obj(theta)
        first[name] = time.perf_counter() - t0
        results[name] = obj(theta)
    threaded = wall_clock(sides, torch_threads)
    clock = time.perf_counter if threaded else time.process_time
    order = list(sides)
    for r in range(rounds):
        for name in order if r % 2 == 0 else order[::-1]:
            use(name)
            t0 = clock()
            obj(theta)
            times[name].append(clock() - t0)
    a, b = order
    use(a)
    nudged = theta * (1 + np.finfo(float).eps * np.random.default_rng(0).choice([-2.0, -1.0, 1.0, 2.0], theta.shape))
    J_ulp, g_ulp = obj(nudged)
    (J_a, g_a), (J_b, g_b) = results[a], results[b]
    return dict(
        first=first, median={k: 1e3 * float(np.median(v)) for k, v in times.items()}, minimum={k: 1e3 * min(v) for k, v in times.items()},
        rel_J=abs(J_b - J_a) / abs(J_a), rel_dJ=float(np.linalg.norm(g_b - g_a) / np.linalg.norm(g_a)),
        ulp_J=abs(J_ulp - J_a) / abs(J_a), ulp_dJ=float(np.linalg.norm(g_ulp - g_a) / np.linalg.norm(g_a)), clock=clock.__name__,
    )


def wall_clock(sides: dict[str, dict], torch_threads: int) -> bool:
    """Whether either side runs more than one thread (then wall time, else CPU time, is compared)."""
    return any(max(int(s.get("threads", 1)), int(s.get("torch_threads", torch_threads))) > 1 for s in sides.values())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--a", default="symmetric_pairs=false", help="side a: MomentMatchingGP keyword arguments")
    parser.add_argument("--b", default="symmetric_pairs=true", help="side b: MomentMatchingGP keyword arguments")
    parser.add_argument("--configs", nargs="+",
                        default=["double-pendulum n=400 H=60", "unicycle n=300 H=40", "cart-pole full n=100", "cart-pole full n=300"])
    parser.add_argument("--rounds", type=int, default=12)
    parser.add_argument("--torch-threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "ab_objective.md")
    args = parser.parse_args()
    torch.set_num_threads(args.torch_threads)
    sides = {"a": parse_side(args.a), "b": parse_side(args.b)}
    load0 = load_average()
    rows = []
    for config in args.configs:
        m = measure(config, sides, args.rounds, args.torch_threads)
        print(f"{config:34s} a {m['median']['a']:8.1f} ms  b {m['median']['b']:8.1f} ms  a/b {m['median']['a'] / m['median']['b']:.3f}",
              flush=True)
        rows.append(
            f"| {config} | {m['median']['a']:.0f} / {m['median']['b']:.0f} | {m['minimum']['a']:.0f} / {m['minimum']['b']:.0f} "
            f"| {m['median']['a'] / m['median']['b']:.2f} | {m['first']['a']:.1f} / {m['first']['b']:.1f} | {m['rel_J']:.1e} | {m['rel_dJ']:.1e} | {m['ulp_J']:.1e}, {m['ulp_dJ']:.1e} |"
        )
    clock = "wall" if wall_clock(sides, args.torch_threads) else "CPU"
    lines = [
        "# PILCO J + dJ, two moment-matching settings interleaved in one process",
        "",
        f"Command: `{command_line(__file__)}`  ",
        f"{machine_line(load0)}  ",
        f"a = `{args.a}`, b = `{args.b}` (`MomentMatchingGP` arguments; `compile_step`: the objective's); {args.rounds} J + dJ per side and configuration, "
        f"alternating a b / b a; torch threads {args.torch_threads} unless a side says; {clock} time.",
        "",
        f"| configuration | median {clock} ms a / b | min ms a / b | a / b | first J + dJ wall s a / b (builds) | rel. diff J | rel. diff dJ (2-norm) | a's own change of J, dJ for theta +- 1-2 ulp |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    write_report(lines, args.out, echo=False)


if __name__ == "__main__":
    main()
