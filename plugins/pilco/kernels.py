"""Squared-exponential ARD kernel and guarded Cholesky factorisation (float64 torch).

Conventions used throughout ``plugins.pilco``:

* ``E`` outputs (one GP per output), ``n`` training points, ``d`` input dimensions.
* SE-ARD kernel  k_a(x, x') = alpha_a^2 exp(-1/2 (x - x')^T Lambda_a^-1 (x - x')),
  Lambda_a = diag(ell_a^2); parameters are stored as logs: ``log_ell (E, d)``, ``log_alpha (E,)``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch

from harness.errors import NumericalError

#: jitter added on the diagonal, escalating by x10 per retry
JITTER_START = 1e-9
JITTER_RETRIES = 7


def se_ard(x1: torch.Tensor, x2: torch.Tensor, log_ell: torch.Tensor, log_alpha: torch.Tensor) -> torch.Tensor:
    """Batched SE-ARD Gram matrices.

    Args:
        x1: ``(n, d)`` or ``(E, n, d)``.
        x2: ``(m, d)`` or ``(E, m, d)``.
        log_ell: ``(E, d)`` log length-scales.
        log_alpha: ``(E,)`` log signal standard deviations.

    Returns:
        ``(E, n, m)`` with ``K[a, i, j] = k_a(x1_i, x2_j)``.
    """
    inv_ell = torch.exp(-log_ell)  # (E, d)
    a = x1 * inv_ell[:, None, :]  # (E, n, d), broadcasting a shared (n, d)
    b = x2 * inv_ell[:, None, :]  # (E, m, d)
    sq = (a * a).sum(-1)[:, :, None] + (b * b).sum(-1)[:, None, :] - 2.0 * a @ b.transpose(-1, -2)
    sq = sq.clamp_min(0.0)
    return torch.exp(2.0 * log_alpha)[:, None, None] * torch.exp(-0.5 * sq)


_deferred = threading.local()


@contextmanager
def deferred_checks() -> Iterator[list[torch.Tensor]]:
    """Factorisations inside the block do not stop to check for failure: each appends its ``info``
    tensor (non-zero where it failed) to the yielded list instead of reading it on the host.

    A check reads a GPU value on the host, which waits for the GPU (a host-device synchronisation
    per check) and cannot be captured in a CUDA graph. Inside this block the factorisations of the
    policy objective (:func:`cholesky`, :func:`cholesky_checked`) return their factor as is; the
    caller reads every ``info`` once at the end (:func:`any_failed`) and, if one failed, redoes the
    computation outside the block, where the checks raise (or retry with jitter) as usual. Results
    are the same whenever nothing failed: the factor is the one the checked path would return.
    """
    outer = getattr(_deferred, "flags", None)
    flags: list[torch.Tensor] = []
    _deferred.flags = flags
    try:
        yield flags
    finally:
        _deferred.flags = outer


def deferred_flags() -> list[torch.Tensor] | None:
    """The list of :func:`deferred_checks` in force (in this thread), or ``None`` outside one."""
    return getattr(_deferred, "flags", None)


def any_failed(flags: list[torch.Tensor], like: torch.Tensor) -> torch.Tensor:
    """0-d bool tensor (on ``like``'s device, no host read): did any factorisation of :func:`deferred_checks` fail?"""
    if not flags:
        return torch.zeros((), dtype=torch.bool, device=like.device)
    return torch.cat([f.reshape(-1) for f in flags]).ne(0).any()  # a few kernels, not two per factorisation


def capture_cuda_graph(device: torch.device, compute: Callable[[], torch.Tensor]) -> tuple[torch.cuda.CUDAGraph, torch.Tensor]:
    """``compute()`` captured as a CUDA graph on ``device``: ``(graph, output)``, where ``graph.replay()``
    recomputes ``output`` in place from the tensors ``compute`` reads (written in place between replays).

    Two launched warm-up calls run first on a side stream, as CUDA graphs require. If capturing fails
    (e.g. an operation that reads a GPU value on the host), the device is synchronised and the
    ``RuntimeError`` propagates; :func:`capture_failure` turns it into the one line the objectives keep.
    """
    stream = torch.cuda.Stream(device)
    stream.wait_stream(torch.cuda.current_stream(device))
    try:
        with torch.cuda.stream(stream):
            for _ in range(2):
                compute()
        torch.cuda.current_stream(device).wait_stream(stream)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            output = compute()
    except RuntimeError:
        torch.cuda.synchronize(device)
        raise
    return graph, output


def capture_failure(exc: BaseException) -> str:
    """Why capturing failed, in one line (``type: first line of the message``)."""
    return f"{type(exc).__name__}: {str(exc).splitlines()[0]}"


def cholesky_checked(matrix: torch.Tensor) -> torch.Tensor:
    """``torch.linalg.cholesky`` (raises :class:`torch.linalg.LinAlgError` on failure), or inside
    :func:`deferred_checks` the same factor with the failure recorded instead."""
    flags = deferred_flags()
    if flags is None:
        return torch.linalg.cholesky(matrix)
    chol, info = torch.linalg.cholesky_ex(matrix)
    flags.append(info)
    return chol


def cho_solve(chol: torch.Tensor, rhs: torch.Tensor, triangular: bool | None = None) -> torch.Tensor:
    """``A^-1 rhs`` from the lower Cholesky factor ``chol`` of ``A`` (``torch.cholesky_solve``).

    Off the CPU: two triangular solves (cuBLAS). ``torch.cholesky_solve`` and
    ``torch.cholesky_inverse`` run MAGMA's batched routines on a GPU, which wait for the host and
    cannot be captured in a CUDA graph; the triangular solves round differently by a few ulps.
    ``triangular``: force either way (``None``: by device)."""
    if not (chol.device.type != "cpu" if triangular is None else triangular):
        return torch.cholesky_solve(rhs, chol)
    half = torch.linalg.solve_triangular(chol, rhs, upper=False)
    return torch.linalg.solve_triangular(chol.mT, half, upper=True)


def cho_inverse(chol: torch.Tensor, triangular: bool | None = None) -> torch.Tensor:
    """``A^-1`` from the lower Cholesky factor ``chol`` of ``A`` (``torch.cholesky_inverse``; off the
    CPU ``L^-T L^-1`` by a triangular solve, see :func:`cho_solve`)."""
    if not (chol.device.type != "cpu" if triangular is None else triangular):
        return torch.cholesky_inverse(chol)
    eye = torch.eye(chol.shape[-1], dtype=chol.dtype, device=chol.device).expand(chol.shape)
    inv_l = torch.linalg.solve_triangular(chol, eye, upper=False)
    return inv_l.mT @ inv_l


def cholesky(matrix: torch.Tensor, what: str = "matrix") -> torch.Tensor:
    """Lower Cholesky factor of a (batch of) symmetric positive-definite matrices.

    Tries the plain factorisation, then adds jitter ``1e-9 * mean(diag)``, escalating by x10 up to
    ``1e-3 * mean(diag)``. Raises :class:`NumericalError` naming ``what`` if all attempts fail.
    Differentiable (the jitter is treated as a constant). Inside :func:`deferred_checks`: the plain
    factorisation only, its failure recorded (the caller redoes the work with the retries if so).
    """
    chol, info = torch.linalg.cholesky_ex(matrix)
    flags = deferred_flags()
    if flags is not None:
        flags.append(info)
        return chol
    if not bool(torch.any(info)):
        return chol
    eye = torch.eye(matrix.shape[-1], dtype=matrix.dtype, device=matrix.device)
    scale = matrix.diagonal(dim1=-2, dim2=-1).mean(-1).abs().clamp_min(1e-12).detach()
    jitter = JITTER_START
    for _ in range(JITTER_RETRIES):
        chol, info = torch.linalg.cholesky_ex(matrix + (jitter * scale)[..., None, None] * eye)
        if not bool(torch.any(info)):
            return chol
        jitter *= 10.0
    raise NumericalError(
        f"Cholesky of the {what} failed even with jitter {jitter / 10:.0e} x mean diagonal; "
        "the data are degenerate (duplicated inputs with zero noise?) - raise the noise floor"
    )
