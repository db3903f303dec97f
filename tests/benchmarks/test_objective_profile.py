"""benchmarks/objective_profile.py: every part of a J + dJ is measured where it runs, and the timing is undone."""

from __future__ import annotations

import pytest

pytest.importorskip("numba")

from benchmarks.objective_profile import PARTS, profile  # noqa: E402
from plugins.pilco import fused  # noqa: E402
from plugins.pilco.moments import MomentMatchingGP  # noqa: E402


def test_parts_on_cartpole():
    before = (MomentMatchingGP._forward, MomentMatchingGP._backward, fused.pair_factors)
    parts = profile("cart-pole full n=100", repeats=1)
    assert set(parts) == {*PARTS, "total"}
    # the kernel, the compiled glue and the policy's GP all ran and were timed inside their callers
    assert parts["Q kernel"] > 0 and parts["compiled glue"] > 0 and parts["policy GP"] > 0
    assert all(parts[p] >= -1e-3 for p in PARTS)  # the nested parts fit inside the dynamics GP's time
    assert (MomentMatchingGP._forward, MomentMatchingGP._backward, fused.pair_factors) == before
