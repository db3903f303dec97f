"""benchmarks/objective_floor.py: the work it counts is the work a J + dJ asks of the compiled kernels."""

from __future__ import annotations

import pytest

pytest.importorskip("numba")

from benchmarks.bench_objective import HORIZON  # noqa: E402
from benchmarks.objective_floor import MADDS, entries_formed, measure  # noqa: E402
from plugins.pilco import fused  # noqa: E402


def test_entries_as_the_two_row_loops_form_them():
    """Rows i0 and i0 + 1 at a time (an odd n's last pass forms row i0 twice); the symmetric kernels from column i0."""
    for n in (1, 2, 5, 100, 101):
        exps_sym = exps_full = 0
        for i0 in range(0, n, 2):
            exps_sym += len([(row, j) for row in (0, 1) for j in range(i0, n)])
            exps_full += len([(row, j) for row in (0, 1) for j in range(n)])
        assert entries_formed("forward_jac_sym", n) == exps_sym
        assert entries_formed("forward_jac_rows", n) == exps_full
    assert entries_formed("forward_jac_rows", 400) == 400 * 400
    assert entries_formed("forward_jac_sym", 400) == 400 * 400 // 2 + 400


def test_cartpole_counts_every_output_pair_once_per_step():
    """Cart-pole's dynamics GP has E = 4 outputs: 10 output pairs, the 4 diagonal ones symmetric and traced."""
    before = {name: getattr(fused.kernels(6), name) for name in ("forward_jac_rows", "forward_jac_sym")}
    m = measure("cart-pole full n=100", repeats=1)
    n, e = 100, 4
    off_diagonal, diagonal = e * (e - 1) // 2, e
    assert m["calls"] == {"forward_jac_rows": HORIZON, "forward_jac_sym": HORIZON}
    assert m["by_kernel"]["forward_jac_rows"]["entries"] == HORIZON * off_diagonal * n * n
    assert m["by_kernel"]["forward_jac_sym"]["entries"] == HORIZON * diagonal * (n * n // 2 + n)
    assert m["entries"] == HORIZON * (off_diagonal * n * n + diagonal * (n * n // 2 + n))
    assert m["madds"] == HORIZON * (off_diagonal * n * n * MADDS[("forward_jac_rows", False)](6)
                                    + diagonal * (n * n // 2 + n) * MADDS[("forward_jac_sym", True)](6))
    assert 0 < m["by_kernel"]["forward_jac_rows"]["cpu"] < m["kernel"] < m["total"]
    # the recording wrappers are gone afterwards
    assert {name: getattr(fused.kernels(6), name) for name in before} == before

