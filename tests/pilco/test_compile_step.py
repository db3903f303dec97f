"""``compile_step``: each rollout step of J + dJ as ``torch.compile``'d code (the GPU's option against
kernel launches, ``plugins.pilco.propagate.FusedStep``).

On the CPU the steps are traced with the ``aot_eager`` backend: dynamo and functionalization run as they
do for inductor (graph breaks, guards, in-place writes, the deferred checks' list), but no code is
built (inductor's C++ build takes minutes on a small CPU). With a GPU the inductor build itself is
compared with the CPU and with the uncompiled GPU path (skipped, visibly, without one).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from harness.errors import OptionError
from plugins.pilco import propagate
from plugins.pilco.moments import MomentMatchingGP
from tests.devices import CUDA, run_on_cuda
from tests.pilco.test_device import _degenerate, _on_cuda
from tests.pilco.test_fused_step import _objective

torch.set_num_threads(1)


@pytest.fixture
def traced(monkeypatch):
    """``compile_step`` with the ``aot_eager`` backend, from a clean dynamo cache; yields dynamo's counters."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    monkeypatch.setattr(propagate, "COMPILE_BACKEND", "aot_eager")
    torch._dynamo.reset()
    counters.clear()
    yield counters
    torch._dynamo.reset()


def _compiled_copy(case: str):
    """The case's objective twice on the torch kernel: uncompiled, and with ``compile_step``."""
    plain, compiled = _objective(case), _objective(case)
    for obj in (plain, compiled):
        obj.dynamics = MomentMatchingGP(obj.posterior, kernel="torch")
    compiled.compile_step = True
    return plain, compiled


@pytest.mark.parametrize("case", ["rbf-two-controls", "two-angles-linear"])
def test_compiled_steps_equal_the_uncompiled_ones_in_one_graph_each(case, traced) -> None:
    plain, compiled = _compiled_copy(case)
    rng = np.random.default_rng(1)
    theta0 = plain.get_flat()
    for k in range(3):
        theta = theta0 + (0.0 if k == 0 else 0.05) * rng.normal(size=theta0.shape)
        (J0, g0), (J1, g1) = plain(theta), compiled(theta)
        assert abs(J1 - J0) <= 1e-13 * abs(J0)
        assert np.linalg.norm(g1 - g0) <= 1e-12 * np.linalg.norm(g0)
        compiled.defer_checks = True  # the GPU's path (checks deferred) from the second evaluation on
        out = compiled._deferred_output().numpy()
        compiled.defer_checks = False
        assert out[1] == 0.0 and abs(out[0] - J0) <= 1e-13 * abs(J0)
    # one graph for the step's forward pass and one for its backward, not one per step or per theta
    assert dict(traced["graph_break"]) == {}
    assert traced["stats"]["unique_graphs"] == 2


def test_a_failed_factorisation_in_a_compiled_step_raises_as_without(traced) -> None:
    plain, compiled = _compiled_copy("rbf-two-controls")
    plain, compiled = _degenerate(plain), _degenerate(compiled)
    theta = plain.get_flat()
    with pytest.raises(torch.linalg.LinAlgError):
        plain(theta)
    with pytest.raises(torch.linalg.LinAlgError):  # redone without the compiled code, which raises
        compiled(theta)
    compiled.defer_checks = True
    assert compiled._deferred_output()[1] == 1.0  # flagged through the compiled step's list


def test_compile_step_needs_the_torch_kernel() -> None:
    from plugins.pilco.learner import Pilco
    from tasks.cartpole import CartPole

    spec = CartPole().spec
    with pytest.raises(OptionError, match=r"compile_step=true needs kernel=torch.*--set kernel=torch"):
        Pilco(spec, {"compile_step": "true", "kernel": "numba"}, 0)
    assert Pilco(spec, {"compile_step": "true", "kernel": "torch"}, 0).options["compile_step"] is True
    obj = _objective("rbf-two-controls")
    with pytest.raises(ValueError, match="compile_step needs the torch kernel"):
        type(obj)(obj.controller, obj.posterior, obj.layout, obj.cost.cost, obj.init_mean.numpy(), obj.init_cov.numpy(),
                  obj.horizon, kernel="numba", compile_step=True)


@CUDA
@pytest.mark.parametrize("case", ["rbf-two-controls", "two-angles-linear", "rbf-fitc-mean-only"])
def test_compiled_steps_on_cuda_equal_the_cpu_and_the_uncompiled_graph(case) -> None:
    """Inductor's code replayed as a CUDA graph: J to 1e-10 and dJ to 1e-7 of the CPU (the issue's bounds),
    and to 1e-12 / 1e-10 of the uncompiled GPU graph."""
    obj = _objective(case)
    obj.dynamics = MomentMatchingGP(obj.posterior, kernel="torch")
    plain, compiled = _on_cuda(obj), _on_cuda(obj)
    compiled.compile_step = True
    rng = np.random.default_rng(2)
    theta0 = obj.get_flat()
    for k in range(3):
        theta = theta0 + (0.0 if k == 0 else 0.05) * rng.normal(size=theta0.shape)
        (J_cpu, g_cpu), (J_plain, g_plain), (J_comp, g_comp) = obj(theta), plain(theta), compiled(theta)
        assert compiled.graph_error is None
        assert abs(J_comp - J_cpu) <= 1e-10 * abs(J_cpu)
        assert np.linalg.norm(g_comp - g_cpu) <= 1e-7 * np.linalg.norm(g_cpu)
        assert abs(J_comp - J_plain) <= 1e-12 * abs(J_plain)
        assert np.linalg.norm(g_comp - g_plain) <= 1e-10 * np.linalg.norm(g_plain)


@CUDA
def test_pilco_runs_on_cuda_with_compiled_steps() -> None:
    result = run_on_cuda("pilco", {"num_centres": "5", "policy_max_evaluations": "10", "gp_max_evals": "30", "plots": "false",
                                   "compile_step": "true"})
    assert result.trials == 2
    assert [h["cuda_graph"] for h in result.history] == [1.0, 1.0]
