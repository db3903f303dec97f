"""PILCO on another device (``device=cuda``): every tensor follows its inputs' device.

Without a GPU the CUDA tests below are skipped (``pytest -ra`` lists them with the reason). What runs
everywhere: J + dJ and the GP training with torch's default device set to ``meta``, a device that
holds no data. A tensor created without an explicit device lands there and the first operation that
mixes it with the real (CPU) tensors fails, so a pass means that nothing in these paths would be
left on the host when the model lives on a GPU. And the whole J + dJ of the GPU path with the objective
itself on ``meta``, which refuses every copy to or from the host, as a CUDA graph's capture does.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from harness.errors import OptionError
from plugins.pilco.gp import GPModel
from plugins.pilco.learner import resolve_device
from plugins.pilco.moments import MomentMatchingGP
from plugins.pilco.objective import PolicyObjective
from tests.devices import CUDA, default_device, run_on_cuda
from tests.pilco.test_fused_step import _objective

torch.set_num_threads(1)
CASES = ["rbf-two-controls", "linear-sin", "no-angles-rbf-policy-noise", "two-angles-linear", "rbf-fitc-mean-only"]


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("kernel", ["torch", "numba"])
def test_objective_creates_no_tensor_on_the_default_device(case, kernel) -> None:
    obj = _objective(case)
    obj.dynamics = MomentMatchingGP(obj.posterior, kernel=kernel)
    theta = obj.get_flat()
    J0, g0 = obj(theta)
    with default_device("meta"):
        J1, g1 = obj(theta)
    assert J1 == J0 and np.array_equal(g1, g0)


@pytest.mark.parametrize("sparse", [False, True])
def test_gp_training_creates_no_tensor_on_the_default_device(sparse) -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(60, 3))
    y = np.sin(x[:, :2]) + 0.01 * rng.normal(size=(60, 2))
    settings = dict(sparse_threshold=40 if sparse else 300, num_pseudo=20, max_evals_full=20, max_evals_fitc=10)
    reference = GPModel(**settings).fit(x, y, seed=1)
    with default_device("meta"):
        model = GPModel(**settings, device="cpu")
        report = model.fit(x, y, seed=1)
        mean, var = model.predict(x[:5])
    assert report.nll == reference.nll and report.sparse == sparse
    assert mean.device.type == "cpu" and bool(torch.isfinite(var).all())


def test_devices_and_kernels_resolve_or_fail_with_the_fix() -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(OptionError, match=r"device=cuda: torch sees no CUDA GPU here .*--set device=cpu"):
            resolve_device("cuda")
    from plugins.pilco.moments import resolve_kernel

    with pytest.raises(ValueError, match="kernel 'numba' runs on the CPU"):
        resolve_kernel("numba", "cuda")
    assert resolve_kernel("auto", "cuda") == "torch"


def _on_cuda(obj: PolicyObjective, cuda_graph: bool = True) -> PolicyObjective:
    """``obj``'s J on the GPU (a copy of its controller; the same posterior, cost, start and noise)."""
    return PolicyObjective(copy.deepcopy(obj.controller), obj.posterior, obj.layout, obj.cost.cost, obj.init_mean.cpu().numpy(),
                           obj.init_cov.cpu().numpy(), obj.horizon, obj.mean_only, obj.cost.width,
                           policy_noise_std=obj.policy_noise_std, kernel="torch", device="cuda", cuda_graph=cuda_graph)


@pytest.mark.parametrize("case", CASES)
def test_deferred_objective_reads_nothing_on_the_host(case) -> None:
    """The whole J + dJ of the GPU path (checks deferred) on torch's meta device, which holds no data and
    refuses every copy to or from the host: what a CUDA graph's capture needs, checked without a GPU (a host
    copy inside J once made every capture fail, and with it every GPU run's search ~8x slower)."""
    obj = _objective(case)
    meta = PolicyObjective(copy.deepcopy(obj.controller), obj.posterior, obj.layout, obj.cost.cost,
                           obj.init_mean.cpu().numpy(), obj.init_cov.cpu().numpy(), obj.horizon, obj.mean_only,
                           obj.cost.width, policy_noise_std=obj.policy_noise_std, kernel="torch", device="meta",
                           cuda_graph=False)
    out = meta._deferred_output()
    assert out.device.type == "meta" and out.shape == (2 + obj.get_flat().size,)


def _degenerate(obj: PolicyObjective) -> PolicyObjective:
    """``obj`` started from an indefinite covariance: the first step's factorisation fails."""
    obj.init_cov = -obj.init_cov
    return obj


@pytest.mark.parametrize("case", CASES)
def test_deferred_checks_give_the_checked_result(case) -> None:
    """J + dJ with the factorisations' checks deferred (the GPU path) equals the checked path exactly."""
    obj = _objective(case)
    obj.dynamics = MomentMatchingGP(obj.posterior, kernel="torch")
    theta = obj.get_flat()
    J, g = obj(theta)
    obj.defer_checks = True
    out = obj._deferred_output().numpy()
    assert out[1] == 0.0 and out[0] == J and np.array_equal(out[2:], g)
    assert obj(theta)[0] == J


def test_a_deferred_failure_is_redone_with_the_checks() -> None:
    """A factorisation that fails inside deferred checks is flagged, not raised; the objective then
    redoes the evaluation checked, so it raises as the CPU path does (the policy search's +inf)."""
    from plugins.pilco.kernels import any_failed, cholesky, cholesky_checked, deferred_checks

    bad = -torch.eye(3, dtype=torch.float64)
    with deferred_checks() as flags:
        cholesky_checked(bad)
        assert bool(any_failed(flags, bad))  # flagged, not raised
        cholesky(torch.eye(3, dtype=torch.float64))
        cholesky(bad, "test matrix")
    assert len(flags) == 3 and not bool(any_failed(flags[1:2], bad)) and bool(any_failed(flags[2:], bad))
    with pytest.raises(torch.linalg.LinAlgError):
        cholesky_checked(bad)
    obj = _degenerate(_objective("rbf-two-controls"))
    theta = obj.get_flat()
    with pytest.raises(torch.linalg.LinAlgError):
        obj(theta)
    obj.defer_checks = True
    assert obj._deferred_output()[1] == 1.0
    with pytest.raises(torch.linalg.LinAlgError):
        obj(theta)


def test_triangular_solves_equal_torchs_cholesky_solve_and_inverse() -> None:
    """The GPU's Cholesky solve and inverse (two triangular solves; MAGMA's cannot be graph-captured),
    run here on the CPU, against ``torch.cholesky_solve`` / ``torch.cholesky_inverse``, values and gradients."""
    from plugins.pilco.kernels import cho_inverse, cho_solve

    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 6, 6))
    A = torch.tensor(a @ a.transpose(0, 2, 1) + 6 * np.eye(6), requires_grad=True)
    b = torch.tensor(rng.normal(size=(3, 6, 2)))
    results = []
    for triangular in (False, True):
        chol = torch.linalg.cholesky(A)
        x, inv = cho_solve(chol, b, triangular), cho_inverse(chol, triangular)
        grad = torch.autograd.grad((x.sum() + (inv * inv).sum()), A)[0]
        results.append((x, inv, grad))
    for ref, tri in zip(results[0], results[1]):
        assert torch.allclose(tri, ref, rtol=1e-12, atol=1e-14)


@CUDA
@pytest.mark.parametrize("case", CASES)
def test_objective_on_cuda_equals_the_cpu(case) -> None:
    """J to 1e-10 and dJ to 1e-7 relative (the issue's bounds; GPU reductions round differently)."""
    obj = _objective(case)
    theta = obj.get_flat()
    obj.dynamics = MomentMatchingGP(obj.posterior, kernel="torch")
    J_cpu, g_cpu = obj(theta)
    cuda = _on_cuda(obj)
    J_gpu, g_gpu = cuda(theta)
    assert cuda.graph_error is None
    assert abs(J_gpu - J_cpu) <= 1e-10 * abs(J_cpu)
    assert np.linalg.norm(g_gpu - g_cpu) <= 1e-7 * np.linalg.norm(g_cpu)
    # the graph replays for new theta: the same as launching every operation anew
    eager = _on_cuda(obj, cuda_graph=False)
    rng = np.random.default_rng(3)
    for _ in range(3):
        theta_new = theta + 0.05 * rng.normal(size=theta.shape)
        (J_graph, g_graph), (J_eager, g_eager) = cuda(theta_new), eager(theta_new)
        assert abs(J_graph - J_eager) <= 1e-12 * abs(J_eager)
        assert np.linalg.norm(g_graph - g_eager) <= 1e-10 * np.linalg.norm(g_eager)


@CUDA
def test_a_failed_factorisation_on_cuda_raises_as_on_the_cpu() -> None:
    obj = _degenerate(_objective("rbf-two-controls"))
    cuda = _on_cuda(obj)
    with pytest.raises(torch.linalg.LinAlgError):
        cuda(obj.get_flat())


@CUDA
def test_gp_training_on_cuda_matches_the_cpu() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(120, 4))
    y = np.sin(x[:, :3]) + 0.01 * rng.normal(size=(120, 3))
    settings = dict(sparse_threshold=80, num_pseudo=40, max_evals_full=60, max_evals_fitc=30)
    cpu = GPModel(**settings).fit(x, y, seed=2)
    gpu_model = GPModel(**settings, device="cuda")
    gpu = gpu_model.fit(x, y, seed=2)
    assert gpu_model.posterior().beta.device.type == "cuda"
    assert gpu.nll == pytest.approx(cpu.nll, rel=1e-3) and gpu.fitc_nll == pytest.approx(cpu.fitc_nll, rel=1e-3)


@CUDA
def test_pilco_runs_on_cuda() -> None:
    result = run_on_cuda("pilco", {"num_centres": "5", "policy_max_evaluations": "10", "gp_max_evals": "30", "plots": "false"})
    assert result.trials == 2
    assert [h["cuda_graph"] for h in result.history] == [1.0, 1.0]  # J + dJ replayed as a CUDA graph in both searches
