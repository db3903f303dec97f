"""benchmarks/ab_objective.py times two moment-matching settings on one objective, interleaved, and says how far
their J and dJ are apart; its side arguments parse to MomentMatchingGP keywords or fail with the fix."""

from __future__ import annotations

import pytest

from benchmarks.ab_objective import measure, parse_side


def test_sides_parse_to_keyword_arguments():
    assert parse_side("kernel=fused,symmetric_pairs=false,threads=2") == {"kernel": "fused", "symmetric_pairs": False, "threads": 2}
    assert parse_side("") == {}
    with pytest.raises(SystemExit, match="is not KEY=VALUE"):
        parse_side("symmetric_pairs")


def test_symmetric_pairs_against_whole_q_on_cartpole():
    pytest.importorskip("numba")
    m = measure("cart-pole full n=100", {"a": {"kernel": "fused", "symmetric_pairs": False},
                                         "b": {"kernel": "fused", "symmetric_pairs": True}}, rounds=2)
    assert set(m["median"]) == {"a", "b"} and all(t > 0 for t in m["median"].values())
    assert m["rel_J"] < 1e-10 and m["rel_dJ"] < 1e-7  # the tolerances for a faster kernel
    assert m["rel_dJ"] > 0  # the two sides do run different code (half of Q against all of it)
    with pytest.raises(SystemExit, match="unknown configuration"):
        measure("cart-pole n=7", {"a": {}, "b": {}}, rounds=1)


def test_a_side_can_take_moment_matching_from_another_file(tmp_path):
    """``moments=PATH``: the class comes from that file (here a copy of this checkout's, so the same J and dJ),
    as a subclass of this checkout's class, so the rollout takes it as it is; a missing file fails with the fix."""
    from pathlib import Path

    import plugins.pilco.moments as moments
    from benchmarks.ab_objective import moments_class

    copy = tmp_path / "moments.py"
    copy.write_text(Path(moments.__file__).read_text())
    other = moments_class(str(copy))
    assert other is not moments.MomentMatchingGP and issubclass(other, moments.MomentMatchingGP)
    m = measure("cart-pole full n=100", {"a": {"moments": str(copy)}, "b": {}}, rounds=1)
    assert m["rel_J"] == 0.0 and m["rel_dJ"] == 0.0
    with pytest.raises(SystemExit, match="no such file"):
        moments_class(str(tmp_path / "missing.py"))


def test_a_side_can_run_torch_on_its_own_threads(monkeypatch):
    """``torch_threads=K``: torch runs on K threads while that side is timed and on ``torch_threads`` (the
    command's ``--torch-threads``) for the other; a side with more than one thread is timed by the wall clock."""
    import torch

    from benchmarks.ab_objective import wall_clock

    seen = []
    real = torch.set_num_threads
    monkeypatch.setattr(torch, "set_num_threads", lambda k: (seen.append(k), real(k)))
    before = torch.get_num_threads()
    m = measure("cart-pole full n=100", {"a": {"kernel": "torch", "torch_threads": 2}, "b": {"kernel": "torch"}}, rounds=2)
    assert seen[:2] == [2, 1] and set(seen[:-1]) == {1, 2}  # warm-up a then b, each on its own threads
    assert seen[-1] == before and torch.get_num_threads() == before  # and the caller's threads put back
    # the same kernel: two threads split torch's sums differently, a round-off apart (J 2e-13, dJ 3e-10 here; a 1-ulp
    # change of theta moves dJ by 7e-9): within the tolerances for a new kernel
    assert m["clock"] == "perf_counter" and m["rel_J"] < 1e-10 and m["rel_dJ"] < 1e-7
    assert wall_clock({"a": {"torch_threads": 2}, "b": {}}, 1) and not wall_clock({"a": {}, "b": {}}, 1)
    assert wall_clock({"a": {"threads": 2}, "b": {}}, 1) and wall_clock({"a": {}, "b": {}}, 2)


def test_a_side_can_compile_its_rollout_steps(monkeypatch):
    """``compile_step=true``: that side's objective runs each rollout step as torch.compile'd code (traced here with
    aot_eager, no C++ build), the other side's does not; the same maths, so J and dJ agree to round-off; the build is
    the first J + dJ, reported per side; a side without kernel=torch fails with the fix."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    from plugins.pilco import propagate

    monkeypatch.setattr(propagate, "COMPILE_BACKEND", "aot_eager")
    torch._dynamo.reset()
    counters.clear()
    try:
        m = measure("cart-pole full n=100", {"a": {"kernel": "torch"}, "b": {"kernel": "torch", "compile_step": True}}, rounds=1)
        assert counters["stats"]["unique_graphs"] == 2  # one step's forward and backward, compiled once
    finally:
        torch._dynamo.reset()
    assert m["rel_J"] < 1e-12 and m["rel_dJ"] < 1e-10 and set(m["first"]) == {"a", "b"}
    with pytest.raises(SystemExit, match="compile_step=true needs kernel=torch"):
        measure("cart-pole full n=100", {"a": {"kernel": "fused", "compile_step": True}, "b": {}}, rounds=1)
