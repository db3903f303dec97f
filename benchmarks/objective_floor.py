"""One PILCO J + dJ against the arithmetic floor of its compiled ``Q`` kernel, on this CPU.

Usage::

    python benchmarks/objective_floor.py [--configs "double-pendulum n=400 H=60" "unicycle n=300 H=40" "cart-pole full n=100"] \\
        [--repeats 5] [--out results/benchmarks/objective_floor.md]

Issue #23's floor (0.56 s of exponentials and products for the double pendulum's J + dJ) was measured
for the torch path on the issue's machine. The ``fused`` kernel (:mod:`plugins.pilco.fused`, the
default with numba) does less arithmetic than that path (half of each diagonal pair's ``Q``, the lean
jacobian, no ``Q`` stored), and CPUs differ in vector width by 4x. So this measures, on the machine it
runs on and for the kernel as it is:

* **what the kernel computes** per J + dJ: every call of a compiled kernel is recorded (its pairs, basis
  points, traced pairs), and the entries of ``Q`` it forms (each one ``exp``) and the multiply-adds it
  does are counted from the kernel's source (:data:`MADDS`; an add or a multiply on its own counts as one);
* **this core's peak rates** for that arithmetic: multiply-adds per second of a large square float64
  matrix product on one thread (BLAS's register-blocked loop: the most a core's FMA units deliver), and
  ``exp`` per second of the kernel's own :func:`~plugins.pilco.fused.exp_inline` in a vectorised loop
  over a row of 400 numbers in L1 cache (compiled with the kernels' flags; the loop also sums the results,
  one add per ``exp``);
* the **floor** of the ``Q`` kernel: its multiply-adds at the peak rate plus its ``exp`` at the ``exp`` rate
  (nothing for memory: the rows are formed in registers and L1), against the measured CPU time of its
  calls; and what J + dJ would cost with the kernel at its floor and everything else as measured.

One torch thread; CPU time (``time.process_time``), median over ``--repeats`` J + dJ after a warm-up.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from benchmarks.task_objectives import TASK_CONFIGS  # noqa: E402

#: multiply-adds per entry of ``Q`` formed, by kernel and whether the pair has a trace term (``p < ntrace``),
#: for ``d`` GP inputs, counted from the templates of :mod:`plugins.pilco.fused` (per row of the two-row
#: loops; a line ``x += g0 * a + g1 * b`` run once per column for two rows is one per entry):
#:
#: * every kernel: the exponent ``L[p, i] . Rt[p, :, j]``, ``d + 2``;
#: * ``forward_jac_rows`` (the dynamics GP's off-diagonal pairs in a policy search): the forward sum
#:   ``s0 += q0 * w`` 1; ``_JAC_ROWS``: ``g0 = q0 * w`` 1, ``s0_c += g0 * b_c`` ``d``, the column sum 1:
#:   ``2d + 5``; a traced pair adds ``r0 += q0 * inv_k`` 1 and ``_JAC_ROWS``' trace sweep ``g0 = q0 * inv_k`` 1,
#:   ``d``, its column sum 1: ``+ d + 3``;
#: * ``forward_jac_sym`` (the diagonal pairs, upper triangle only): the forward sums ``s0``, the mirror's
#:   ``q_wr`` and (traced) ``r0``: 3; ``_JAC_QUAD``: ``c0 * w`` 1, ``g0 = q0 * (.)`` 1, ``s0_c += g0 * b_c`` ``d``,
#:   the mirror's ``out[p, c, j] += g0 * a0_c + g1 * a1_c`` ``d``, ``su0 += g0`` 1, ``out[p, d, j] += g0 + g1``
#:   1/2: ``2d + 3.5``; ``_JAC_TRACE`` (traced): ``g0 = q0 * inv_k`` 1 and the same ``2d + 1.5``: ``2d + 2.5``.
#:   Untraced: ``(d + 2) + 2 + (2d + 3.5)``; traced: ``(d + 2) + 3 + (2d + 3.5) + (2d + 2.5)``.
MADDS = {
    ("forward_jac_rows", False): lambda d: (d + 2) + 1 + (d + 2),
    ("forward_jac_rows", True): lambda d: (d + 2) + 1 + (d + 2) + (d + 3),
    ("forward_jac_sym", False): lambda d: (d + 2) + 2 + (2 * d + 3.5),
    ("forward_jac_sym", True): lambda d: (d + 2) + 3 + (2 * d + 3.5) + (2 * d + 2.5),
}

#: the kernels whose calls are recorded; a J + dJ of the learner calls the two above (a kernel with no
#: count here makes the script stop with its name rather than leave its work out of the floor)
KERNELS = ("forward_q", "forward_jac", "forward_jac_rows", "forward_q_sym", "forward_jac_sym", "backward", "backward_q")


def entries_formed(name: str, n: int) -> int:
    """Entries of one pair's ``Q`` that a kernel forms (one ``exp`` each), as its two-row loop forms them:
    two rows per pass, the second a repeat of the first where ``n`` is odd; every column (``n^2`` for even
    ``n``), or for the symmetric kernels from column ``i0`` on (the upper triangle: ``n^2 / 2 + n``)."""
    symmetric = name.endswith("_sym")
    return sum(2 * (n - i0 if symmetric else n) for i0 in range(0, n, 2))


def peak_madds_per_second(size: int = 1024, repeats: int = 5) -> float:
    """Multiply-adds per CPU second of a ``(size, size) @ (size, size)`` float64 product on one thread (median)."""
    a = torch.randn(size, size, dtype=torch.float64)
    b = torch.randn(size, size, dtype=torch.float64)
    torch.mm(a, b)
    times = []
    for _ in range(repeats):
        start = time.process_time()
        torch.mm(a, b)
        times.append(time.process_time() - start)
    return size**3 / statistics.median(times)


def exp_per_second(n: int = 400, sweeps: int = 20000, repeats: int = 5) -> float:
    """``exp_inline`` per CPU second in a vectorised loop over ``n`` numbers in L1 (median), compiled with the
    kernels' fast-math flags; the loop sums the results (one add per ``exp``) so that none is optimised away."""
    from numba import njit

    from plugins.pilco.fused import FASTMATH, NoAliasCompiler, exp_inline

    @njit(fastmath=FASTMATH, nogil=True, pipeline_class=NoAliasCompiler)
    def sweep(x, times):
        total = 0.0
        for _ in range(times):
            for j in range(x.shape[0]):
                total += exp_inline(x[j])
            x[0] = x[0] * 1.0000000001  # keeps the sweeps from being merged
        return total

    x = np.random.default_rng(0).uniform(-30.0, 0.0, n)  # the exponents of Q: log-weights, mostly negative
    sweep(x, 1)
    cpu = []
    for _ in range(repeats):
        start = time.process_time()
        sweep(x, sweeps)
        cpu.append(time.process_time() - start)
    return n * sweeps / statistics.median(cpu)


def measure(config: str, repeats: int) -> dict:
    """J + dJ CPU time, the recorded kernel calls' CPU time and their counted work, for one configuration."""
    import plugins.pilco.fused as fused
    from benchmarks.ab_objective import build

    objective = build(config)  # a task of benchmarks/task_objectives.py or a cart-pole size of benchmarks/bench_objective.py
    theta = objective.get_flat()
    objective(theta)  # compiles the kernels for this d
    calls = defaultdict(int)
    by_kernel = defaultdict(lambda: {"entries": 0, "madds": 0.0, "cpu": 0.0})
    originals = {}
    for (d, _), module in fused._modules.items():
        for name in KERNELS:
            original = getattr(module, name)
            originals[(module, name)] = original

            def recorded(*args, _original=original, _name=name, _d=d):
                first, last, nb = args[4], args[5], args[0].shape[1]
                ntrace = args[9].shape[0] if _name != "backward" else 0
                counted = False
                for p in range(first, last):
                    key = (_name, p < ntrace)
                    if key not in MADDS:
                        raise SystemExit(f"kernel {_name} has no multiply-add count (MADDS): add its count before using this floor")
                    counted = True
                    entries = entries_formed(_name, nb)
                    by_kernel[_name]["entries"] += entries
                    by_kernel[_name]["madds"] += entries * MADDS[key](_d)
                calls[_name] += counted
                start = time.process_time()
                out = _original(*args)
                by_kernel[_name]["cpu"] += time.process_time() - start
                return out

            setattr(module, name, recorded)
    try:
        totals = []
        for _ in range(repeats):
            start = time.process_time()
            objective(theta)
            totals.append(time.process_time() - start)
    finally:
        for (module, name), original in originals.items():
            setattr(module, name, original)
    per_kernel = {k: {q: v / repeats for q, v in w.items()} for k, w in by_kernel.items()}
    return {"total": statistics.median(totals), **{q: sum(w[q] for w in per_kernel.values()) for q in ("entries", "madds")},
            "kernel": sum(w["cpu"] for w in per_kernel.values()), "calls": {k: v // repeats for k, v in calls.items()},
            "by_kernel": per_kernel}


def _pass_columns_text() -> str:
    import plugins.pilco.fused as fused

    return f"{fused.PASS_COLUMNS} columns of B per pass of its saved-gradient sweeps"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=list(TASK_CONFIGS),
                        help="task sizes of benchmarks/task_objectives.py or cart-pole ones of benchmarks/ab_objective.py")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pass-columns", type=int, default=None,
                        help="the fused kernel's columns of B per pass (plugins.pilco.fused.PASS_COLUMNS; default: this CPU's)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.pass_columns is not None:
        import plugins.pilco.fused as fused

        fused.PASS_COLUMNS = args.pass_columns  # read by kernels() whenever a caller names none
    load_start = load_average()

    peak = peak_madds_per_second()
    exp_rate = exp_per_second()
    rows, kernel_rows = [], []
    for config in args.configs:
        m = measure(config, args.repeats)
        for name, w in sorted(m["by_kernel"].items()):
            kfloor = w["madds"] / peak + w["entries"] / exp_rate
            kernel_rows.append(f"| {config} | `{name}` | {m['calls'][name]} | {w['entries'] / 1e6:.1f} | {w['madds'] / w['entries']:.1f} | "
                               f"{1e3 * w['cpu']:.0f} | {1e3 * kfloor:.0f} | {w['cpu'] / kfloor:.2f}x |")
        floor = m["madds"] / peak + m["entries"] / exp_rate
        rest = m["total"] - m["kernel"]
        rows.append(
            f"| {config} | {1e3 * m['total']:.0f} | {1e3 * m['kernel']:.0f} | {m['entries'] / 1e6:.1f} | {m['madds'] / 1e9:.2f} | "
            f"{1e3 * m['madds'] / peak:.0f} + {1e3 * m['entries'] / exp_rate:.0f} = **{1e3 * floor:.0f}** | "
            f"{m['kernel'] / floor:.2f}x | {1e3 * rest:.0f} | **{1e3 * (rest + floor):.0f}** |")
    lines = [
        "# One PILCO J + dJ against the arithmetic floor of its compiled Q kernel", "",
        f"Command: `{command_line(__file__, argv)}`  ",
        f"{machine_line(load_start)}  ",
        f"One torch thread, CPU time; J + dJ: median of {args.repeats} after a warm-up (the `fused` kernel, this checkout's "
        f"default; {_pass_columns_text()}). Definitions in the script's docstring.", "",
        f"This core's rates: **{2 * peak / 1e9:.1f} GFLOP/s** ({peak / 1e9:.2f} G multiply-adds/s, a 1024 x 1024 float64 "
        f"matrix product on one thread) and **{exp_rate / 1e9:.3f} G exp/s** (the kernel's `exp_inline`, vectorised, in L1).", "",
        "| configuration | J + dJ (ms) | Q kernel (ms) | entries of Q formed (M) = exp | multiply-adds (G) | Q kernel's floor: "
        "multiply-adds + exp (ms) | Q kernel against its floor | the rest of J + dJ (ms) | J + dJ with the Q kernel at its floor (ms) |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows, "",
        "By kernel (the same J + dJ): the symmetric kernels form the diagonal pairs' upper triangle and save the gradients "
        "of both their sums (by row and, for the mirror, by column); the rows kernels the off-diagonal pairs' row products only.", "",
        "| configuration | kernel | calls | entries (M) | multiply-adds per entry | CPU (ms) | floor (ms) | against its floor |",
        "|---|---|---|---|---|---|---|---|",
        *kernel_rows,
    ]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
