"""One evaluation of the FITC pseudo-input objective (NLL and its hand-derived gradient), against its arithmetic floor.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/fitc_eval_profile.py --data benchmarks/data/gp_double-pendulum_50ec8b95_t20.npz \\
        --out results/benchmarks/fitc_eval_profile.md

The pseudo-input stage of a late double-pendulum GP fit is ~100 such evaluations and most of the fit
(``results/findings_double-pendulum.md``). This prints and writes: the CPU time per evaluation (median of
``--repeats``, one torch thread), the time by torch operator (one profiled evaluation), the evaluation's
multiply-adds counted from its algebra (:func:`multiply_adds`), and the rate this core reaches on the
evaluation's own dense product shape (an ``(E, M, n) x (E, n, M)`` batched product), which gives the
evaluation's floor: its multiply-adds at that rate.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from plugins.pilco.sparse import fitc_nll_and_pseudo_gradient  # noqa: E402


def multiply_adds(num_outputs: int, n: int, m: int, d: int) -> dict[str, float]:
    """Multiply-adds of one :func:`fitc_nll_and_pseudo_gradient` by kind (the function's docstring has the
    algebra), ``M`` pseudo-inputs, ``n`` transitions, ``d`` inputs:

    - four triangular solves with ``n`` right-hand sides (``V``, ``R``, ``h``, ``dNLL/dK_mn``), ``M^2 n / 2`` each;
    - two ``M x n x M`` products (``A = I + V Lambda^-1 V^T`` and the inner matrix), ``M^2 n`` each;
    - the ``M x M`` work: ``dNLL/dK_mm`` (two triangular solves with ``M`` right-hand sides, ``M^3 / 2`` each),
      two Cholesky factors (``M^3 / 3`` each), ``A^-1`` from its factor (``2 M^3 / 3``);
    - the ``d``-wide products: the kernels' cross terms (``n M d``, ``M^2 d``) and the gradient to ``Z``
      through both kernels (``n M d``, ``M^2 d``).

    ``tests/benchmarks/test_fitc_eval_profile.py`` checks the ``M x n x M`` products against torch's own count."""
    per_output = {
        "triangular solves, n right-hand sides": 4 * m * m * n / 2,
        "M x n x M products": 2 * m * m * n,
        "M x M solves, factorisations, inverses": (1 + 2 / 3 + 2 / 3) * m**3,
        "d-wide products": 2 * n * m * d + 2 * m * m * d,
    }
    return {k: v * num_outputs for k, v in per_output.items()}


def cpu_times(f, repeats: int) -> list[float]:
    """CPU seconds of ``repeats`` calls of ``f()`` after one warm-up call."""
    f()
    times = []
    for _ in range(repeats):
        start = time.process_time()
        f()
        times.append(time.process_time() - start)
    return times


def gemm_rate(num_outputs: int, n: int, m: int, repeats: int = 5) -> float:
    """Multiply-adds per CPU second of ``(E, M, n) @ (E, n, M)``, the evaluation's own dense product (median)."""
    a = torch.randn(num_outputs, m, n, dtype=torch.float64)
    b = torch.randn(num_outputs, n, m, dtype=torch.float64)
    return num_outputs * m * m * n / statistics.median(cpu_times(lambda: torch.bmm(a, b), repeats))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a benchmarks/data/gp_*.npz file (compare_gp_fit.py --extract)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--top", type=int, default=10, help="operators listed")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load_start = load_average()

    data = np.load(args.data)
    t = lambda name: torch.from_numpy(np.ascontiguousarray(data[name], dtype=np.float64))  # noqa: E731
    inputs = (t("x"), t("y"), t("pseudo_inputs"), t("log_ell"), t("log_alpha"), t("log_sigma"))
    (n, d), num_outputs, m = inputs[0].shape, inputs[1].shape[1], inputs[2].shape[0]

    times = cpu_times(lambda: fitc_nll_and_pseudo_gradient(*inputs), args.repeats)
    seconds = statistics.median(times)

    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fitc_nll_and_pseudo_gradient(*inputs)
    ops = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    profiled_ms = sum(e.self_cpu_time_total for e in ops) / 1e3

    counts = multiply_adds(num_outputs, n, m, d)
    total = sum(counts.values())
    rate = gemm_rate(num_outputs, n, m)
    floor = total / rate

    lines = [
        "# One FITC pseudo-input evaluation (NLL + gradient) against its arithmetic floor", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"{machine_line(load_start)}  ",
        f"Data: `{args.data.name}`: n = {n} transitions, M = {m} pseudo-inputs, d = {d} inputs, E = {num_outputs} outputs; "
        f"one torch thread, CPU time.", "",
        f"**{1e3 * seconds:.0f} ms** per evaluation (median of {args.repeats}; "
        f"{', '.join(f'{1e3 * x:.0f}' for x in times)} ms). Counted: **{total / 1e9:.2f} G multiply-adds** "
        f"({2 * total / seconds / 1e9:.1f} GFLOP/s achieved). This core's rate on the evaluation's own dense product "
        f"(`({num_outputs}, {m}, {n}) @ ({num_outputs}, {n}, {m})`): {2 * rate / 1e9:.1f} GFLOP/s, so the floor is "
        f"**{1e3 * floor:.0f} ms**; the evaluation runs at **{seconds / floor:.2f}x** it.", "",
        "| multiply-adds by kind | G | share |", "|---|---|---|",
        *[f"| {k} | {v / 1e9:.3f} | {100 * v / total:.0f} % |" for k, v in counts.items()], "",
        f"By operator (one profiled evaluation, {profiled_ms:.0f} ms under the profiler):", "",
        "| operator | calls | self CPU ms | share |", "|---|---|---|---|",
        *[f"| `{e.key}` | {e.count} | {e.self_cpu_time_total / 1e3:.1f} | {100 * e.self_cpu_time_total / 1e3 / profiled_ms:.0f} % |"
          for e in ops[: args.top]],
    ]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
