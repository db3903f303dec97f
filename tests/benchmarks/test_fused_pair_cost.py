"""benchmarks/fused_pair_cost.py times the fused kernel per output pair (whole Q, its upper triangle, off-diagonal)
and fails with the fix on a malformed size."""

from __future__ import annotations

import pytest

pytest.importorskip("numba")

from benchmarks.fused_pair_cost import main, pair_costs  # noqa: E402


def test_pair_costs_at_a_tiny_size(tmp_path):
    costs = pair_costs(9, 2, 2, repeats=1)
    assert set(costs) == {"diagonal whole", "diagonal half", "off-diagonal"} and all(c > 0 for c in costs.values())
    out = tmp_path / "cost.md"
    main(["--sizes", "8:2:2", "--repeats", "1", "--out", str(out)])
    assert "| n=8, d=2, E=2 |" in out.read_text()
    with pytest.raises(SystemExit, match="is not n:d:E"):
        main(["--sizes", "8x2", "--out", str(out)])
