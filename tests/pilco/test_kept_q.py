"""The backward pass's use of each step's kept ``Q`` (plugins.pilco.moments._Workspace.keep).

A rollout whose gradient is taken keeps every step's ``Q`` so that the backward pass need not
recompute it (kernels torch and numba; the fused kernel forms ``Q`` inside its loops and stores none). The gradients must be exactly those of the recomputing path, also when the memory
cap lets only some steps keep theirs, and a kept ``Q`` that a later rollout overwrote must not be
used (the stamp check).
"""

from __future__ import annotations

import numpy as np
import torch

import plugins.pilco.moments as moments
from tests.pilco.test_fused_step import _objective

torch.set_num_threads(1)


def _keeping(obj):
    """``obj`` with a dynamics GP whose kernel stores ``Q`` (numba where installed, else torch)."""
    kernel = "numba" if moments.numba_available() else "torch"
    obj.dynamics = moments.MomentMatchingGP(obj.dynamics.posterior, kernel=kernel)
    return obj


def _value_and_grad(obj, keep_bytes: int):
    obj.dynamics.workspace = moments._Workspace(keep_bytes)
    return obj(obj.get_flat())


def test_kept_q_gives_the_recomputed_gradient() -> None:
    obj = _keeping(_objective("rbf-two-controls"))
    J0, g0 = _value_and_grad(obj, 0)
    assert obj.dynamics.workspace.slots == []
    J1, g1 = _value_and_grad(obj, 1 << 40)
    assert len(obj.dynamics.workspace.slots) == obj.horizon
    one = obj.dynamics.workspace.slots[0]
    J2, g2 = _value_and_grad(obj, 4 * one.numel() * one.element_size())  # the first 4 steps keep theirs
    assert len(obj.dynamics.workspace.slots) == 4
    assert J0 == J1 == J2
    np.testing.assert_array_equal(g1, g0)
    np.testing.assert_array_equal(g2, g0)


def test_kept_q_is_used(monkeypatch) -> None:
    """Not vacuous: with every step kept, the backward pass computes no ``Q`` of its own (a linear
    policy: the dynamics GP is the only moment matching); with none kept, once per step and block
    of output pairs."""
    obj = _keeping(_objective("linear-sin"))
    calls: list[bool] = []  # per exp-bilinear (one block of pairs): written into a kept buffer?
    original = moments._exp_bilinear

    def counting(left, right, out):
        kept = {slot.untyped_storage().data_ptr() for slot in obj.dynamics.workspace.slots}
        calls.append(out.untyped_storage().data_ptr() in kept)
        return original(left, right, out)

    monkeypatch.setattr(moments, "_exp_bilinear", counting)  # the torch path's
    if moments.numba_available():
        from plugins.pilco import fused

        monkeypatch.setattr(fused, "exp_bilinear", counting)  # the compiled path's (NumPy's exp)
    gp = obj.dynamics
    blocks = len(moments._pair_blocks(gp.num_pairs, gp.posterior.inputs.shape[0], 8))
    per_rollout = blocks * obj.horizon
    for keep_bytes, forward, backward in ((1 << 40, [True] * per_rollout, []), (0, [False] * per_rollout, [False] * per_rollout)):
        obj.dynamics.workspace = moments._Workspace(keep_bytes)
        calls.clear()
        obj.set_flat(obj.get_flat())
        J = obj.value()
        assert calls == forward
        calls.clear()
        torch.autograd.grad(J, obj.params)
        assert calls == backward


def test_contraction_blocks_cover_the_pairs_within_the_byte_budget(monkeypatch) -> None:
    """Blocks of output pairs tile 0..P in order, each within BLOCK_BYTES (one pair at least); J and dJ
    do not depend on the blocking (one block for all pairs vs one pair per block) beyond round-off."""
    monkeypatch.setattr(moments, "BLOCK_BYTES", 3 * 100 * 100 * 8)
    assert moments._pair_blocks(7, 100, 8) == [(0, 3), (3, 6), (6, 7)]
    assert moments._pair_blocks(2, 1000, 8) == [(0, 1), (1, 2)]  # larger than the budget: one pair each
    obj = _objective("linear-sin")
    theta = obj.get_flat()
    monkeypatch.setattr(moments, "BLOCK_BYTES", 1 << 40)
    J_one, g_one = obj(theta)
    monkeypatch.setattr(moments, "BLOCK_BYTES", 1)
    J_each, g_each = obj(theta)
    assert moments._pair_blocks(obj.dynamics.num_pairs, 10, 8) == [(i, i + 1) for i in range(obj.dynamics.num_pairs)]
    assert abs(J_one - J_each) <= 1e-12 * abs(J_one)
    np.testing.assert_allclose(g_each, g_one, rtol=1e-10, atol=1e-12 * np.abs(g_one).max())


def test_overwritten_kept_q_is_recomputed() -> None:
    """Forward A, forward B (same slots, other theta), backward A: A's gradient, not B's Q."""
    obj = _objective("linear-sin")
    obj.dynamics.workspace = moments._Workspace(1 << 40)
    theta = obj.get_flat()
    J_ref, g_ref = obj(theta)

    obj.set_flat(theta)
    J_a = obj.value()
    obj.set_flat(theta + 0.3)
    obj.value()  # overwrites every slot A kept
    obj.set_flat(theta)
    g_a = torch.cat([g.reshape(-1) for g in torch.autograd.grad(J_a, obj.params)]).numpy()
    assert float(J_a.detach()) == J_ref
    np.testing.assert_array_equal(g_a, g_ref)
