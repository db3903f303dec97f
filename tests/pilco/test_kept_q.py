"""The backward pass's use of each step's kept ``Q`` (plugins.pilco.moments._Workspace.keep).

A rollout whose gradient is taken keeps every step's ``Q`` so that the backward pass need not
recompute it. The gradients must be exactly those of the recomputing path, also when the memory
cap lets only some steps keep theirs, and a kept ``Q`` that a later rollout overwrote must not be
used (the stamp check).
"""

from __future__ import annotations

import numpy as np
import torch

import plugins.pilco.moments as moments
from tests.pilco.test_fused_step import _objective

torch.set_num_threads(1)


def _value_and_grad(obj, keep_bytes: int):
    obj.dynamics.workspace = moments._Workspace(keep_bytes)
    return obj(obj.get_flat())


def test_kept_q_gives_the_recomputed_gradient() -> None:
    obj = _objective("rbf-two-controls")
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
    policy: the dynamics GP is the only moment matching); with none kept, once per step."""
    obj = _objective("linear-sin")
    calls: list[bool] = []  # per exp-bilinear: written to a kept buffer?
    original = moments._exp_bilinear

    def counting(left, right, workspace, out=None):
        calls.append(out is not None)
        return original(left, right, workspace, out)

    monkeypatch.setattr(moments, "_exp_bilinear", counting)
    for keep_bytes, forward, backward in ((1 << 40, [True] * obj.horizon, []), (0, [False] * obj.horizon, [False] * obj.horizon)):
        obj.dynamics.workspace = moments._Workspace(keep_bytes)
        calls.clear()
        obj.set_flat(obj.get_flat())
        J = obj.value()
        assert calls == forward
        calls.clear()
        torch.autograd.grad(J, obj.params)
        assert calls == backward


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
