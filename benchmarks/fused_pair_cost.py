"""What one output pair costs in the fused kernel's forward pass with saved gradients (``forward_jac``).

Usage::

    .venv/bin/python benchmarks/fused_pair_cost.py [--sizes 400:9:6 300:12:10] [--repeats 7] [--out FILE]

For each size ``n:d:E`` (basis points, GP inputs, outputs; defaults: the double pendulum's and the
unicycle's), random inputs shaped as moment matching makes them (the first ``E`` pairs symmetric, as
its diagonal pairs are) go through the compiled kernels directly, one thread: the diagonal pairs with the
whole ``Q`` (``forward_jac``) and with its upper triangle (``forward_jac_sym`` plus the driver's
completion, :func:`plugins.pilco.fused._symmetric_jacobian`), and the off-diagonal pairs. Reported:
the fastest of ``--repeats`` CPU times per pair (``time.process_time``), and the cost of a symmetric
traced pair relative to an ordinary one, which :func:`plugins.pilco.fused.pair_groups` uses to give two
threads equal work.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402


def pair_costs(n: int, d: int, e: int, repeats: int, seed: int = 0) -> dict[str, float]:
    """Milliseconds of CPU per pair: ``diagonal whole``, ``diagonal half``, ``off-diagonal``."""
    from plugins.pilco import fused

    rng = np.random.default_rng(seed)
    p = e * (e + 1) // 2
    B = rng.normal(size=(p, n, d))
    half = 0.1 * rng.normal(size=(e, d, d))
    M = half + half.transpose(0, 2, 1)
    A = 0.3 * rng.normal(size=(p, n, d))
    A[:e] = B[:e] @ M
    v = -1.0 - rng.random((p, n))
    u = -1.0 - rng.random((p, n))
    u[:e] = v[:e] - 0.3
    L = np.ascontiguousarray(np.concatenate([A, u[..., None], np.ones((p, n, 1))], -1))
    Rt = np.ascontiguousarray(np.concatenate([B, np.ones((p, n, 1)), v[..., None]], -1).transpose(0, 2, 1))
    Bt = np.ascontiguousarray(Rt[:, :d])
    wl = rng.normal(size=(p, n))
    wr = wl.copy()
    K = rng.normal(size=(e, n, n))
    ik = K + K.transpose(0, 2, 1)
    j = dict(gA=np.empty((p, n, d)), gu=np.empty((p, n)), gBv=np.empty((p, d + 1, n)), gwr=np.empty((p, n)),
             hA=np.empty((e, n, d)), hu=np.empty((e, n)), hBv=np.empty((e, d + 1, n)))
    quad, trace, q_wr = np.empty(p), np.empty(e), np.empty((p, n))
    module = fused.kernels(d)

    def whole(first, last):
        module.forward_jac(L, Rt, np.empty(n), np.empty(n), first, last, A, Bt, wl, wr, ik, quad, trace, q_wr, *j.values())

    def upper(first, last):
        module.forward_jac_sym(L, Rt, np.empty(n), np.empty(n), first, last, Bt, wl, wr, ik, quad, trace, q_wr,
                               j["gA"], j["gu"], j["gBv"], j["hA"], j["hu"], j["hBv"])
        fused._symmetric_jacobian(j, q_wr, M, first, last)

    out = {}
    for name, fn, first, last in (("diagonal whole", whole, 0, e), ("diagonal half", upper, 0, e), ("off-diagonal", whole, e, p)):
        fn(first, last)  # compiles on first use
        times = []
        for _ in range(repeats):
            t0 = time.process_time()
            fn(first, last)
            times.append(time.process_time() - t0)
        out[name] = 1e3 * min(times) / (last - first)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["400:9:6", "300:11:10"], help="n:d:E (double pendulum, unicycle)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "fused_pair_cost.md")
    args = parser.parse_args(argv)
    load = load_average()
    rows = []
    for size in args.sizes:
        try:
            n, d, e = (int(x) for x in size.split(":"))
        except ValueError:
            raise SystemExit(f"--sizes: {size!r} is not n:d:E (e.g. 400:9:6)") from None
        c = pair_costs(n, d, e, args.repeats)
        print(f"n={n} d={d} E={e}: " + ", ".join(f"{k} {v:.3f} ms" for k, v in c.items()), flush=True)
        rows.append(f"| n={n}, d={d}, E={e} | {c['diagonal whole']:.3f} | {c['diagonal half']:.3f} | {c['off-diagonal']:.3f} "
                    f"| {c['diagonal whole'] / c['diagonal half']:.2f} | {c['diagonal half'] / c['off-diagonal']:.2f} |")
    lines = ["# One output pair in the fused kernel (forward pass with saved gradients), whole Q or its upper triangle", "",
             f"Command: `{command_line(__file__, argv)}`  ", machine_line(load) + "  ",
             f"Random inputs shaped as moment matching makes them; fastest of {args.repeats} CPU times, one thread, per pair. "
             "The diagonal pairs carry the trace term (they read `inv_k` too).", "",
             "| size | diagonal pair, whole Q, ms | diagonal pair, upper triangle, ms | off-diagonal pair, ms | whole / half "
             "| half / off-diagonal (pair_groups' weight 1.5 x 0.6 = 0.9) |",
             "|---|---|---|---|---|---|", *rows]
    write_report(lines, args.out, echo=False)


if __name__ == "__main__":
    main()
