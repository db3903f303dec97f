"""GP prediction at an uncertain (Gaussian) input by exact moment matching (paper eqs. 14-23).

Given ``E`` independent SE-ARD GPs (a :class:`~plugins.pilco.posterior.GPPosterior`) and a test
input ``x ~ N(m, S)`` (``m (d,)``, ``S (d, d)``), :func:`predict_uncertain` returns the exact mean
``M (E,)`` and covariance ``V (E, E)`` of ``f(x)`` (latent function values, no observation noise)
and the input-output cross-covariance in the reference implementation's convention::

    C = S^-1 cov[x, f(x)]        shape (d, E),   i.e.  cov[x, f(x)] = S @ C.

This convention lets cross-covariances chain through a sequence of maps: if ``x`` is a block of a
larger jointly Gaussian vector ``y`` with ``cov[y, x] = S_yx``, then ``cov[y, f(x)] = S_yx @ C``
(exact for jointly Gaussian ``(y, x)``). It never needs ``S^-1`` itself, so singular ``S`` is fine.

Notation (paper, reference ``gp0``): ``Lambda_a = diag(ell_a^2)``, ``nu_i = X_i - m``,
``q_ai = alpha_a^2 |S Lambda_a^-1 + I|^-1/2 exp(-1/2 nu_i^T (S + Lambda_a)^-1 nu_i)``,
``M_a = beta_a^T q_a`` and, with ``R = S (Lambda_a^-1 + Lambda_b^-1) + I`` and
``z_ij = Lambda_a^-1 nu_i + Lambda_b^-1 nu_j``::

    Q_ij  = k_a(X_i, m) k_b(X_j, m) |R|^-1/2 exp(1/2 z_ij^T R^-1 S z_ij)
    V_ab  = beta_a^T Q beta_b - M_a M_b + delta_ab (alpha_a^2 - tr(inv_k_a Q_aa)).

``mean_only=True`` drops the model-uncertainty term ``alpha_a^2 - tr(inv_k_a Q_aa)``: the moments
of the GP *mean function* under the input distribution. That is the RBF controller's form
(reference ``gp2``) and the deterministic-GP-mean ablation.

Implementation notes (all float64, vectorised over outputs and basis points):

* ``|B|`` and ``B^-1`` only for the symmetric positive-definite ``B = D S D + I`` (``D`` diagonal),
  via Cholesky: ``R^-1 S = D^-1 (I - B^-1) D^-1`` with ``D^2 = Lambda_a^-1 + Lambda_b^-1`` and
  ``|R| = |B|``; ``B >= I`` so the factorisation cannot fail.
* The ``Q`` exponent uses the expanded bilinear form
  ``z^T T z = a^T T a + b^T T b + 2 a^T T b`` (``T = R^-1 S / 2``) evaluated for all ``(i, j)`` as
  one matrix product of augmented factors ``[2 T a_i, u_i, 1] . [b_j, 1, v_j]``; no
  ``(n, n, E, E, d)`` tensor is ever formed.
* Only the ``E (E + 1) / 2`` output pairs ``a <= b`` are computed (``Q_ba = Q_ab^T``), the ``E``
  diagonal pairs first so that ``Q_aa`` is a view for the trace term.
* The backward pass is hand-derived (:meth:`MomentMatchingGP._backward`; only thin
  ``(pairs, n, d)`` intermediates are kept) and tested equal to autograd through the same forward
  to 1e-11. Policy evaluation is dominated by the number of small operator calls, and autograd
  needs about three times as many.
* Three implementations of the ``Q`` contraction (``kernel``, :func:`resolve_kernel`): ``torch``
  (:func:`_contract_forward`, :func:`_contract_backward`: the reference, always available),
  ``numba`` (:mod:`plugins.pilco.fused`: the same forward, a compiled backward pass that reads
  ``Q`` once instead of through five thin products) and ``fused`` (the same compiled passes with
  ``Q`` formed two rows at a time inside them, never stored; the default where numba is installed). They
  agree to round-off (J 1e-11, dJ 5e-8 relative on the double pendulum); ``threads`` > 1 runs
  groups of output pairs in parallel with the compiled kernels, with the same results.
* With the fused kernel the glue around the contraction is compiled too (``compiled_glue``:
  :meth:`MomentMatchingGP._compiled_factors` forms ``Z``, ``Z W`` and the kernel's factors in one sweep,
  :meth:`MomentMatchingGP._backward_compiled` takes the kernel's saved gradients to ``m`` and ``S`` in
  another where nothing else needs a gradient); tested against the torch operations to 1e-12.
* A rollout whose gradient will be taken can keep each step's ``Q`` in a buffer of its own
  (:meth:`_Workspace.keep`, up to :data:`KEEP_Q_BYTES` per GP, default 0) so that the backward pass
  does not recompute it (one product and one ``exp`` per step); wherever a kept ``Q`` was
  overwritten since its forward pass, the backward pass recomputes ``Q`` into scratch instead.
* Both passes walk the output pairs in blocks whose ``Q`` fits a core's L2 cache
  (:data:`BLOCK_BYTES`): a block is produced, and every product that reads it runs, before the next
  block, so that only the first touch of ``Q`` goes to memory (the arithmetic is unchanged: J and
  dJ are bit-identical to the unblocked passes; 1.1-1.2x less CPU per J + dJ at the unicycle's and
  the double pendulum's sizes, ``results/benchmarks/objective_gradient_before_after_blocks.md``).
"""

from __future__ import annotations

import functools
import importlib.util
import math
import os
from functools import lru_cache

import numpy as np
import torch

from plugins.pilco.kernels import cho_inverse, cholesky_checked
from plugins.pilco.posterior import GPPosterior

#: implementations of the Q contraction: ``torch`` (the reference, always available), ``numba``
#: (:mod:`plugins.pilco.fused`: compiled backward pass, ``Q`` formed by BLAS and NumPy) and ``fused``
#: (the compiled passes forming ``Q`` inside their loops); the compiled ones need the extra ``fast``
KERNELS = ("torch", "numba", "fused")

#: the kernels that run compiled code on the CPU (their own threads; torch single-threaded inside)
COMPILED_KERNELS = ("numba", "fused")


def numba_available() -> bool:
    """Whether the compiled kernels can be used (numba installed, ``HARNESS_NO_JIT`` unset)."""
    return not os.environ.get("HARNESS_NO_JIT") and importlib.util.find_spec("numba") is not None


#: environment variable naming the kernel that ``auto`` means (for benchmarks and users comparing them)
KERNEL_ENV = "HARNESS_PILCO_KERNEL"


def resolve_kernel(kernel: str | None, device: torch.device | str | None = None) -> str:
    """``None``/``"auto"``: ``$HARNESS_PILCO_KERNEL`` if set, else ``fused`` where numba is available
    (on the CPU; ``torch`` on a GPU ``device``), else ``torch``; a named kernel is checked and
    returned. Raises ``ValueError`` with the fix."""
    on_cpu = device is None or torch.device(device).type == "cpu"
    if kernel in (None, "auto"):
        kernel = os.environ.get(KERNEL_ENV) or ("fused" if numba_available() and on_cpu else "torch")
    if kernel in COMPILED_KERNELS and not on_cpu:
        raise ValueError(f"kernel {kernel!r} runs on the CPU, the model is on {device} (use kernel torch or auto)")
    if kernel not in KERNELS:
        raise ValueError(f"unknown kernel {kernel!r}; expected auto or one of {KERNELS}")
    if kernel in COMPILED_KERNELS and not numba_available():
        raise ValueError(f"kernel {kernel!r} needs numba (pip install '.[fast]') and HARNESS_NO_JIT unset")
    return kernel


@lru_cache(maxsize=32)
def _pair_indices(num_outputs: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Output pairs ``(a, b)``, ``a <= b``: diagonal pairs first, then ``a < b``.

    Returns ``(first (P,), second (P,), full (E*E,))``; ``full[a * E + b]`` is the pair index of
    ``(min(a, b), max(a, b))``, used to expand pair results to a symmetric ``(E, E)`` matrix.
    """
    e = num_outputs
    pairs = [(a, a) for a in range(e)] + [(a, b) for a in range(e) for b in range(a + 1, e)]
    lookup = {p: k for k, p in enumerate(pairs)}
    full = [lookup[(min(a, b), max(a, b))] for a in range(e) for b in range(e)]
    as_long = lambda values: torch.tensor(values, dtype=torch.long, device="cpu")  # noqa: E731
    return as_long([p[0] for p in pairs]), as_long([p[1] for p in pairs]), as_long(full)


@lru_cache(maxsize=32)
def _pair_indices_on(num_outputs: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_pair_indices` on ``device``, copied there once (a copy from the host inside every J
    would be a host-device transfer per evaluation, and cannot be captured in a CUDA graph)."""
    return tuple(t.to(device) for t in _pair_indices(num_outputs))


#: memory one :class:`MomentMatchingGP` may hold for the ``Q`` of a rollout's steps between its
#: forward and backward pass; environment variable ``HARNESS_PILCO_KEEP_Q_MB``. Default 0: always
#: recompute. Keeping them (up to 2.65 GB for the unicycle's 67 steps at n = 300) streams every
#: ``Q`` through memory twice, and on this project's machines that measured slower than recomputing
#: it from cache: J + dJ 1.2-1.5x slower with the torch kernel, 1.07-1.14x with numba
#: (double pendulum and unicycle, benchmarks/compare_objective.py, 2026-11-25)
KEEP_Q_BYTES = int(float(os.environ.get("HARNESS_PILCO_KEEP_Q_MB", "0")) * 2**20)


class _Workspace:
    """Reusable buffers for the contraction: the scratch ``Q (P, n, n)`` and ``Q * inv_k (E, n, n)``,
    and the kept ``Q`` of each step of a rollout (:meth:`keep`).

    Fresh multi-megabyte tensors are expensive here (first-touch page faults cost about as much as
    the arithmetic), so every prediction with one :class:`MomentMatchingGP` writes into the same
    buffers. A kept ``Q`` carries a stamp; :meth:`kept` returns it only while its slot has not been
    written again (a later rollout reuses the slots).
    """

    def __init__(self, keep_bytes: int | None = None, device: torch.device | str | None = None) -> None:
        self.device = torch.device("cpu") if device is None else torch.device(device)
        self.buffers: dict[str, torch.Tensor] = {}
        self.keep_bytes = KEEP_Q_BYTES if keep_bytes is None else keep_bytes
        self.slots: list[torch.Tensor] = []
        self.stamps: list[int] = []
        self.writes = 0

    def keep(self, slot: int, shape: tuple[int, ...], dtype: torch.dtype) -> tuple[torch.Tensor, tuple[int, int]] | None:
        """The buffer for step ``slot``'s ``Q`` and its stamp ``(slot, stamp)``, or ``None`` when slots
        ``0..slot`` of this shape would exceed ``keep_bytes``."""
        if (slot + 1) * math.prod(shape) * torch.finfo(dtype).bits // 8 > self.keep_bytes:
            return None
        if self.slots and (self.slots[0].shape != shape or self.slots[0].dtype != dtype):
            self.slots, self.stamps = [], []
        while len(self.slots) <= slot:
            with torch.inference_mode(False):
                self.slots.append(torch.empty(shape, dtype=dtype, device=self.device))
            self.stamps.append(0)
        self.writes += 1
        self.stamps[slot] = self.writes
        return self.slots[slot], (slot, self.writes)

    def kept(self, token: tuple[int, int] | None) -> torch.Tensor | None:
        """The ``Q`` written under ``token`` (from :meth:`keep`) if it is still there, else ``None``."""
        if token is None:
            return None
        slot, stamp = token
        return self.slots[slot] if slot < len(self.stamps) and self.stamps[slot] == stamp else None

    def buffer(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """The scratch buffer ``name`` of this shape and dtype (made at first use, reused after). Inside
        ``torch.compile`` (``compile_step``) a fresh tensor instead: the compiled code allocates its own, and
        a Python-side cache would be guarded on (a recompilation whenever a buffer is made)."""
        if torch.compiler.is_compiling():
            return torch.empty(shape, dtype=dtype, device=self.device)
        buf = self.buffers.get(name)
        if buf is None or buf.shape != shape or buf.dtype != dtype:
            with torch.inference_mode(False):  # an ordinary tensor, usable in and out of inference mode
                buf = self.buffers[name] = torch.empty(shape, dtype=dtype, device=self.device)
        return buf


#: bytes of ``Q`` that one block of output pairs may take (about a core's L2 cache here: 1 MiB). The
#: contraction runs block by block so that every pass over a block's ``Q`` after the first finds it in
#: cache; on the whole ``(P, n, n)`` tensor each pass went to memory (the unicycle's ``Q`` is 40 MB per
#: step, the double pendulum's 27 MB). Environment variable ``HARNESS_PILCO_BLOCK_KB``.
BLOCK_BYTES = int(float(os.environ.get("HARNESS_PILCO_BLOCK_KB", "1024")) * 2**10)


def _pair_block_size(n: int, itemsize: int) -> int:
    """Pairs per block: as many ``(n, n)`` blocks of ``Q`` as fit :data:`BLOCK_BYTES` (at least one)."""
    return max(1, BLOCK_BYTES // max(1, n * n * itemsize))


def _pair_blocks(p: int, n: int, itemsize: int, device: torch.device | None = None) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` covering the ``p`` pairs, each block's ``Q`` at most :data:`BLOCK_BYTES`
    (at least one pair per block). On a GPU: one block (every pair in one batched product; a
    per-block loop there costs a kernel launch per block and buys no cache)."""
    if device is not None and torch.device(device).type != "cpu":
        return [(0, p)]
    size = _pair_block_size(n, itemsize)
    return [(s, min(s + size, p)) for s in range(0, p, size)]


def _exp_bilinear(left: torch.Tensor, right: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``out = exp(left @ right^T)`` ``(b, n, n)`` for ``left, right (b, n, k)``; returns ``out``."""
    return torch.bmm(left, right.mT, out=out).exp_()


def _contract_forward(left, right, w_left, w_right, inv_k, workspace: _Workspace, out: torch.Tensor | None = None):
    """``quad (P,)``, ``trace (E',)`` of :class:`_ExpBilinearContraction`, and ``Q w_right (P, n)``.

    ``Q`` is written to ``out`` (a kept buffer) if given, else to a block-sized scratch buffer, one
    block of pairs at a time (:func:`_pair_blocks`); each block is contracted while it is in cache."""
    p, n = left.shape[0], left.shape[1]
    e = inv_k.shape[0]
    q_wr = left.new_empty(p, n)
    trace = inv_k.new_empty(e)
    for s, t in _pair_blocks(p, n, left.element_size(), left.device):
        Q = _exp_bilinear(left[s:t], right[s:t], workspace.buffer("Q", (t - s, n, n), left.dtype) if out is None else out[s:t])
        # as a row-vector product: batched matrix-vector products with MKL are faster this way
        torch.bmm(w_right[s:t, None, :], Q.mT, out=q_wr[s:t, None, :])
        # sum_ij inv_k_a,ij Q_a,ij: one BLAS dot per output (a single read pass, no product tensor)
        for a in range(s, min(t, e)):
            trace[a] = torch.dot(inv_k[a].reshape(-1), Q[a - s].reshape(-1))
    quad = (q_wr * w_left).sum(-1)
    return quad, trace, q_wr


def _times_thin(Q: torch.Tensor, Y: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``out = Q @ Y`` ``(b, n, k)`` for a large ``Q (b, n, n)`` and a thin ``Y (b, n, k)``; returns ``out``.

    ``Y`` is copied to a ``(b, k, n)`` layout and handed to ``bmm`` as its transpose: MKL runs that
    1.4-2.4x faster than the same product with ``Y`` contiguous (measured at (P, n, k) = (10, 300, 8),
    (21, 400, 11), (55, 300, 13) on an AMD EPYC; ``benchmarks/compare_objective.py``).
    """
    return torch.bmm(Q, Y.mT.contiguous().mT, out=out)


def _contract_backward(left, right, w_left, w_right, inv_k, q_wr, g_quad, g_trace, workspace: _Workspace, needs,
                       Q: torch.Tensor | None = None):
    """Gradients of :func:`_contract_forward` wrt ``(left, right, w_left, w_right, inv_k)`` (``None`` where not needed).

    With ``a = g_quad w_left`` and ``H = Q[:E'] * inv_k``, the gradient wrt the exponent is
    ``G = Q * (a w_right^T) + g_trace * H`` (on the first ``E'`` pairs), and it is only needed
    through ``G @ right`` and ``G^T @ left``, which are formed without ``G``::

        G @ right   = a * (Q @ (w_right * right)) + g_trace * (H @ right)
        G^T @ left  = w_right * (Q^T @ (a * left)) + g_trace * (H^T @ left)

    (``Q^T w_left``, for ``w_right``, rides along as an extra column of the second product).
    ``Q``: the forward pass's ``Q`` if it was kept; ``None`` recomputes it (one product and one
    ``exp``) block by block into a scratch buffer. Either way every product that reads ``Q`` runs on
    one block of pairs at a time, while that block is in cache (:func:`_pair_blocks`).
    """
    p, n, k = left.shape
    e = inv_k.shape[0] if g_trace is not None else 0
    if g_quad is None:
        g_quad = left.new_zeros(p)
    a = w_left * g_quad[:, None]  # (P, n)
    thin_right = w_right[..., None] * right  # (P, n, k)
    thin_left = torch.cat([a[..., None] * left, w_left[..., None]], dim=-1).mT.contiguous()  # (P, k + 1, n)
    q_right = left.new_empty(p, n, k)  # Q @ (w_right * right)
    q_t_left = left.new_empty(p, k + 1, n)  # (Q^T @ [a * left, w_left])^T
    h_right = left.new_empty(e, n, k)  # H @ right
    h_t_left = left.new_empty(e, k, n)  # (H^T @ left)^T
    grad_inv = left.new_empty(inv_k.shape) if e > 0 and needs[4] else None
    for s, t in _pair_blocks(p, n, left.element_size(), left.device):
        if Q is None:
            Qb = _exp_bilinear(left[s:t], right[s:t], workspace.buffer("Q", (t - s, n, n), left.dtype))
        else:
            Qb = Q[s:t]
        _times_thin(Qb, thin_right[s:t], out=q_right[s:t])
        # Q^T Y computed as (Y^T Q)^T: batched products with a transposed large factor are ~1.5x slower
        torch.bmm(thin_left[s:t], Qb, out=q_t_left[s:t])
        m = min(t, e) - s  # pairs of this block that carry a trace term
        if m > 0:
            H = torch.mul(Qb[:m], inv_k[s : s + m], out=workspace.buffer("prod", (m, n, n), left.dtype))
            _times_thin(H, right[s : s + m], out=h_right[s : s + m])
            torch.bmm(left[s : s + m].mT, H, out=h_t_left[s : s + m])
            if grad_inv is not None:
                torch.mul(Qb[:m], g_trace[s : s + m, None, None], out=grad_inv[s : s + m])
    grad_left = a[..., None] * q_right  # (P, n, k)
    grad_right = w_right[..., None] * q_t_left[:, :k].mT
    grad_wr = g_quad[:, None] * q_t_left[:, k] if needs[3] else None
    if e > 0:
        g_tr = g_trace[:, None, None]
        grad_left[:e] += g_tr * h_right
        grad_right[:e] += g_tr * h_t_left.mT
    grad_wl = g_quad[:, None] * q_wr if needs[2] else None
    return grad_left, grad_right, grad_wl, grad_wr, grad_inv


class _ExpBilinearContraction(torch.autograd.Function):
    """``Q_p = exp(left_p @ right_p^T)`` contracted, with a hand-written backward.

    Inputs: ``left, right (P, n, k)``, ``w_left, w_right (P, n)``, ``inv_k (E', n, n)`` symmetric
    (``E' <= P``; ``E' = 0`` for no trace term) and a :class:`_Workspace`.
    Outputs: ``quad (P,) = w_left_p^T Q_p w_right_p`` and
    ``trace (E',) = sum_ij inv_k_a,ij Q_a,ij`` (= ``tr(inv_k_a Q_a)`` for symmetric ``Q_a``).

    Nothing of size ``n^2`` is stored for the backward pass: it recomputes ``Q`` into the
    workspace (see :func:`_contract_backward`).
    """

    @staticmethod
    def forward(ctx, left, right, w_left, w_right, inv_k, workspace):
        quad, trace, q_wr = _contract_forward(left, right, w_left, w_right, inv_k, workspace)
        ctx.save_for_backward(left, right, w_left, w_right, inv_k, q_wr)
        ctx.workspace = workspace
        return quad, trace

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_quad, g_trace):
        saved = ctx.saved_tensors
        grads = _contract_backward(*saved, g_quad, g_trace, ctx.workspace, ctx.needs_input_grad[:5])
        return (*grads, None)


#: the posterior-derived tensors of :class:`MomentMatchingGP` that gradients may flow to
_CONSTANTS = ("X_z", "scale_z", "scale_outer", "w_coef", "log_alpha2", "alpha2", "beta", "beta_a", "beta_b", "inv_k")


class MomentMatchingGP:
    """A :class:`GPPosterior` prepared for repeated moment matching (:meth:`predict`).

    Everything that depends only on the posterior (scales, pair selections, ``X Lambda^-1``) is
    computed once here, inside the autograd graph when the posterior has gradients (the RBF
    policy: build one per J so that gradients reach its parameters); then :meth:`predict` runs
    once per time step. Its backward pass is hand-derived (:meth:`_backward`, gradients wrt ``m``,
    ``S`` and the prepared tensors; autograd carries them on to the posterior's parameters once).
    It has a third of the operator calls of autograd through the same forward
    (:meth:`_forward` with ``contract=None``, kept as the reference the tests compare against).

    The three scaled differences every prediction needs are one stacked tensor of ``G = E + 2P``
    groups, ``Z = X_z - m scale_z`` (``(G, n, d)``)::

        Z[:E]        = iL_a nu_i          (mean and cross-covariance, and log k_a(X_i, m))
        Z[E:E+P]     = Lambda_a^-1 nu_i   (pair (a, b): left factor of Q)
        Z[E+P:]      = Lambda_b^-1 nu_j   (pair (a, b): right factor of Q)

    so that their quadratic forms are one batched product with ``W = [B_a^-1; T; T]``
    (``(G, d, d)``), formed from the batched ``B^-1`` as ``W = (w_offset - B^-1[w_index]) * w_coef``
    (``T = (I - B_ab^-1) * inv_dd / 2``: ``I - B^-1`` first, which is exact where it cancels).
    """

    def __init__(self, posterior: GPPosterior, kernel: str | None = None, threads: int = 1,
                 symmetric_pairs: bool = True, compiled_glue: bool = True, lean_jacobian: bool = True,
                 min_parallel_work: int | None = None, pass_columns: int | None = None) -> None:
        device = posterior.beta.device
        self.kernel = resolve_kernel(kernel, device)
        #: with the fused kernel, form the kernel's factors in one compiled sweep (:meth:`_compiled_factors`)
        #: and, where nothing but m and S needs a gradient, take the backward pass to them in another
        #: (:meth:`_backward_compiled`); False: the torch operations (kept for benchmarks/ab_objective.py)
        self.compiled_glue = bool(compiled_glue)
        self._factor_constants = None
        #: with the fused kernel, form half the symmetric Q of each diagonal pair (False: the whole Q, as
        #: before; kept for side-by-side benchmarks, benchmarks/ab_objective.py)
        self.symmetric_pairs = bool(symmetric_pairs)
        #: with the fused kernel and the compiled glue, where the posterior has no gradients (the dynamics GP
        #: during a policy search), save only what :meth:`_backward_compiled` reads: not the gradients by
        #: basis point of the right factor, whose sum is all it needs (plugins.pilco.fused.forward's
        #: ``columns``). False: the whole jacobian, as before (kept for benchmarks/ab_objective.py)
        self.lean_jacobian = bool(lean_jacobian)
        self.threads = max(1, int(threads))
        if self.kernel in COMPILED_KERNELS:
            from plugins.pilco import fused

            inline = self.kernel == "fused"
            #: with a compiled kernel, the fewest entries of Q a contraction forms before its pairs are split
            #: over ``threads`` threads (default ``fused.MIN_PARALLEL_WORK``; 0: always, as before)
            self.min_parallel_work = fused.MIN_PARALLEL_WORK if min_parallel_work is None else int(min_parallel_work)
            options = dict(threads=self.threads, block=_pair_block_size, inline=inline,
                           min_parallel_work=self.min_parallel_work)
            #: the fused kernel's saved-gradient sweeps, columns of B per pass (default fused.PASS_COLUMNS; kept
            #: for benchmarks/ab_objective.py: ``pass_columns=1000`` is every column in one pass, as before)
            self._contract_forward = functools.partial(fused.forward, pass_columns=pass_columns, **options)
            self._contract_backward = functools.partial(fused.backward, **options)
        else:
            self._contract_forward, self._contract_backward = _contract_forward, _contract_backward
        self.posterior = posterior
        beta = posterior.beta
        self.num_outputs = e = beta.shape[0]
        first, second, self.full = _pair_indices_on(e, torch.device(device))
        self.num_pairs = p = first.shape[0]
        X = posterior.inputs
        self.input_dim = d = X.shape[1]
        dtype = beta.dtype
        inv_ell = torch.exp(-posterior.log_ell)  # (E, d)
        inv_lam = inv_ell * inv_ell  # (E, d) diagonal of Lambda_a^-1
        self.log_alpha2 = 2.0 * posterior.log_alpha  # (E,)
        self.alpha2 = torch.exp(self.log_alpha2)
        self.scale_z = torch.cat([inv_ell, inv_lam[first], inv_lam[second]], dim=0)[:, None, :]  # (G, 1, d)
        self.X_z = X * self.scale_z  # (G, n, d)
        dh = torch.sqrt(inv_lam[first] + inv_lam[second])  # (P, d)
        half_inv_dd = 0.5 / (dh[:, :, None] * dh[:, None, :])  # (P, d, d)
        scale = torch.cat([inv_ell, dh], dim=0)  # (E + P, d)
        self.scale_outer = scale[:, :, None] * scale[:, None, :]  # (E + P, d, d)
        self.eye = torch.eye(d, dtype=dtype, device=device)
        # W = (w_offset - B^-1[w_index]) * w_coef:  [B_a^-1 (E); T (P); T (P)]
        self.w_index = torch.cat([torch.arange(e, device=device), torch.arange(e, e + p, device=device),
                                  torch.arange(e, e + p, device=device)])
        self.w_coef = torch.cat([-torch.ones(e, d, d, dtype=dtype, device=device), half_inv_dd, half_inv_dd])
        self.w_offset = torch.cat([torch.zeros(e, d, d, dtype=dtype, device=device), self.eye.expand(2 * p, d, d)])
        self.first, self.second = first, second
        # from the host's cached copy: a copy off the device here would break a CUDA graph's capture (the
        # policy's GP is built inside J)
        self._pair_outputs_numpy = tuple(t.numpy() for t in _pair_indices(e)[:2])
        self.pair_outputs = torch.cat([first, second])  # (2P,) output of each pair group of Z
        self.beta = beta
        self.beta_a, self.beta_b = beta[first], beta[second]
        self.inv_k = posterior.inv_k.contiguous()
        self.ones = torch.ones(p, X.shape[0], 1, dtype=dtype, device=device)
        self.workspace = _Workspace(device=device)
        self.constants = tuple(getattr(self, name) for name in _CONSTANTS)
        self.has_grad = any(t.requires_grad for t in self.constants)

    def predict(
        self, m: torch.Tensor, S: torch.Tensor, mean_only: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Moments of ``f(x)`` for ``x ~ N(m, S)``: ``M (E,)``, ``V (E, E)``, ``C (d, E)``.

        See :func:`predict_uncertain` for the meaning of the arguments and results.
        """
        if torch.is_grad_enabled() and (self.has_grad or m.requires_grad or S.requires_grad):
            return _MomentsFunction.apply(m, S, self, mean_only, *self.constants)
        return self._forward(m, S, mean_only, contract=self._contract_forward, for_backward=False)[0]

    def forward(self, m: torch.Tensor, S: torch.Tensor, mean_only: bool = False, slot: int | None = None):
        """:meth:`predict` without autograd, for callers with their own backward pass.

        Returns ``((M, V, C), saved)``; ``saved`` (thin ``(P, n, d + 2)`` intermediates) is what
        :meth:`backward` needs. ``slot``: keep this prediction's ``Q (P, n, n)`` for the backward pass
        in the workspace's buffer ``slot`` (one per time step of a rollout; see :class:`_Workspace`);
        given, it also tells the fused kernel that a backward pass follows, for which it saves the
        gradients of the contraction's outputs (without, :meth:`backward` forms ``Q`` again).
        """
        return self._forward(m, S, mean_only, contract=self._contract_forward, slot=slot, for_backward=slot is not None)

    def backward(self, saved, gM: torch.Tensor, gV: torch.Tensor, gC: torch.Tensor, mean_only: bool, needs):
        """Gradients wrt ``(m, S, *self.constants)`` of a loss with gradients ``gM (E,)``,
        ``gV (E, E)``, ``gC (d, E)`` wrt the results of :meth:`forward` (same ``mean_only``).
        ``needs``: ``2 + len(self.constants)`` booleans; ``None`` is returned where ``False``."""
        return self._backward(saved, gM, gV, gC, mean_only, needs)

    def _forward(self, m, S, mean_only, contract, slot: int | None = None, for_backward: bool = True):
        """The moment-matching arithmetic; ``contract=None`` uses the autograd Function for the
        exp-contraction (autograd reference path), otherwise the plain forward (``Q`` kept in the
        workspace's buffer ``slot`` if given and within its memory cap; with the fused kernel and
        ``for_backward``, the contraction's gradients saved instead, :func:`plugins.pilco.fused.forward`).
        Returns ``((M, V, C), intermediates for _backward)``."""
        e, p = self.num_outputs, self.num_pairs

        # One batched Cholesky for B_a = iL_a S iL_a + I (mean, cross-cov; E of them) and for
        # B_ab = D S D + I, D^2 = Lambda_a^-1 + Lambda_b^-1 (Q; P of them).
        chol = cholesky_checked(torch.addcmul(self.eye, self.scale_outer, S))
        b_inv = cho_inverse(chol)  # (E + P, d, d)
        half_logdet = chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)  # (E + P,)
        # W = [B_a^-1; T; T],  T = R^-1 S / 2 = D^-1 (I - B^-1) D^-1 / 2,  R = S (Lambda_a^-1 + Lambda_b^-1) + I
        W = (self.w_offset - b_inv[self.w_index]) * self.w_coef  # (G, d, d)

        # the fused kernel through this object's own forward (not the autograd reference, contract=None)
        fused_here = self.kernel == "fused" and contract is self._contract_forward
        compiled = self.compiled_glue and fused_here
        if compiled:
            Z, ZW, zwz, log_k, left, right = self._compiled_factors(m, W, half_logdet)
        else:
            Z = torch.addcmul(self.X_z, self.scale_z, m, value=-1.0)  # (G, n, d), see the class docstring
            ZW = torch.bmm(Z, W)  # (G, n, d): [B_a^-1 iL_a nu_i, Lambda_a^-1 nu_i T, Lambda_b^-1 nu_j T]
            zwz = (Z * ZW).sum(-1)  # (G, n)
        nu_s, t = Z[:e], ZW[:e]

        # ---- mean and cross-covariance --------------------------------------------------------
        q = torch.add((self.log_alpha2 - half_logdet[:e])[:, None], zwz[:e], alpha=-0.5).exp_()  # (E, n)
        lb = q * self.beta  # (E, n)  beta_ai q_ai
        M = lb.sum(-1)
        # S^-1 cov[x, f_a] = sum_i beta_ai q_ai (S + Lambda_a)^-1 nu_i,  (S + Lambda_a)^-1 nu_i = iL_a t_ai
        lbt = torch.bmm(lb[:, None, :], t)  # (E, 1, d)
        C = (lbt * self.scale_z[:e]).squeeze(1).T  # (d, E)

        # ---- second moments: Q for the pairs a <= b -------------------------------------------
        if not compiled:
            log_k = torch.add(self.log_alpha2[:, None], (nu_s * nu_s).sum(-1), alpha=-0.5)  # (E, n)  log k_a(X_i, m)
            # [u; v] with u = log_k[first] + zwz_a - 1/2 log|B_ab|,  v = log_k[second] + zwz_b  (2P, n)
            uv = log_k[self.pair_outputs] + zwz[e:]
            u = uv[:p] - half_logdet[e:, None]
            # exponent_ij = 2 a_i^T T b_j + u_i + v_j = log Q_ij  (expanded bilinear form, one product)
            left = torch.cat([2.0 * ZW[e : e + p], u[..., None], self.ones], dim=-1)  # (P, n, d + 2)
            right = torch.cat([Z[e + p :], self.ones, uv[p:, :, None]], dim=-1)  # (P, n, d + 2)
        inv_k = self.inv_k[:0] if mean_only else self.inv_k
        if contract is None:
            quad, trace = _ExpBilinearContraction.apply(left, right, self.beta_a, self.beta_b, inv_k, self.workspace)
            saved = None
        else:
            n = left.shape[1]
            # the fused kernel stores no Q, so it has none to keep for the backward pass
            keeps = slot is not None and self.kernel != "fused"
            kept = self.workspace.keep(slot, (p, n, n), left.dtype) if keeps else None
            # the fused kernel's own forward can save the contraction's gradients for the backward pass
            jac = {} if for_backward and fused_here else None
            # the diagonal pairs (a, a), first: Q symmetric, left's A = 2 Z T = right's B (2 T); the fused
            # kernel forms half of each (plugins.pilco.fused.forward's ``symmetric``)
            sym = {"symmetric": 2.0 * W[e : 2 * e]} if fused_here and self.symmetric_pairs else {}
            if kept is not None:
                quad, trace, q_wr = contract(left, right, self.beta_a, self.beta_b, inv_k, self.workspace, out=kept[0])
            elif jac is not None:
                columns = not (compiled and self.lean_jacobian and not self.has_grad)
                quad, trace, q_wr = contract(left, right, self.beta_a, self.beta_b, inv_k, self.workspace, jacobian=jac,
                                             columns=columns, **sym)
            else:
                quad, trace, q_wr = contract(left, right, self.beta_a, self.beta_b, inv_k, self.workspace, **sym)
            saved = (m, S, b_inv, W, Z, ZW, q, lb, lbt, left, right, inv_k, q_wr, None if kept is None else kept[1], jac, M)
        V = quad[self.full].view(e, e) - torch.outer(M, M)
        if not mean_only:
            V.diagonal().add_(self.alpha2 - trace)
        return (M, V, C), saved

    def _backward(self, saved, gM, gV, gC, mean_only, needs):
        """Hand-derived gradients of ``(M, V, C)`` wrt ``(m, S, *constants)`` (``None`` where not needed)."""
        m, S, b_inv, W, Z, ZW, q, lb, lbt, left, right, inv_k, q_wr, kept, jac, M = saved
        e, p, d = self.num_outputs, self.num_pairs, self.input_dim
        need_c = dict(zip(_CONSTANTS, needs[2:]))
        # V = quad[full] - M M^T + diag(alpha2 - trace)
        g_quad = gV.new_zeros(p).index_add_(0, self.full, gV.reshape(-1))
        g_trace = None if mean_only else -gV.diagonal()
        gM = gM - (gV + gV.T) @ M
        if jac is not None and self.compiled_glue and not any(need_c.values()):  # jac: the fused kernel saved it
            return self._backward_compiled(saved, gM, gC, g_quad, g_trace, needs)
        if jac is not None and not jac["columns"]:
            # a caller asks for gradients of constants that had none in the forward pass: the lean jacobian
            # lacks those by basis point, so the contraction's backward forms Q again (inline)
            jac = None
        grad_left, grad_right, g_beta_a, g_beta_b, g_inv_k = self._contract_backward(
            left, right, self.beta_a, self.beta_b, inv_k, q_wr, g_quad, g_trace, self.workspace,
            (True, True, need_c["beta_a"], need_c["beta_b"], need_c["inv_k"] and not mean_only),
            Q=self.workspace.kept(kept), **({} if jac is None else {"jacobian": jac}),
        )
        # left = [2 Z_a T, u, 1], right = [Z_b, 1, v];  [u; v] = log_k[pair_outputs] + zwz[E:] - [hl_p; 0]
        g_uv = torch.cat([grad_left[..., d], grad_right[..., d + 1]], dim=0)  # (2P, n)
        g_logk = g_uv.new_zeros(e, g_uv.shape[1]).index_add_(0, self.pair_outputs, g_uv)
        # mean part: C = (lbt * iL)^T, lbt_a = lb_a @ t_a,  M = sum lb,  lb = q beta
        w = gC.T * self.scale_z[:e, 0]  # (E, d)  dL/dlbt
        g_lb = torch.baddbmm(gM[:, None, None], ZW[:e], w[:, :, None]).squeeze(-1)  # (E, n)
        g_logq = g_lb * lb
        # gradients wrt zwz = sum(Z * ZW) and wrt ZW where it is used directly (lbt, left)
        g_zwz = torch.cat([-0.5 * g_logq, g_uv], dim=0)  # (G, n)
        g_ZW = torch.cat([lb[..., None] * w[:, None, :], 2.0 * grad_left[..., :d]], dim=0)  # (E + P, n, d)
        # ZW = Z W with W symmetric:  dZ = 2 g_zwz ZW + g_ZW W (+ direct uses),  dW = Z^T (g_ZW + g_zwz Z)
        g_Z = (2.0 * g_zwz)[..., None] * ZW
        g_Z[: e + p].baddbmm_(g_ZW, W[: e + p])
        g_Z[:e].addcmul_(g_logk[..., None], Z[:e], value=-1.0)  # log_k = la2 - 1/2 |Z_mean|^2
        g_Z[e + p :].add_(grad_right[..., :d])  # right = [Z_b, ...]
        g_W = torch.bmm(Z.mT, g_zwz[..., None] * Z)  # (G, d, d)
        g_W[: e + p].baddbmm_(Z[: e + p].mT, g_ZW)
        g_hl = -torch.cat([g_logq, g_uv[:p]], dim=0).sum(-1)  # (E + P,)  d/d(1/2 log|B|)
        g_Z_sum = g_Z.sum(1, keepdim=True)  # (G, 1, d);  Z = X_z - m scale_z
        grads = {"X_z": g_Z}
        if needs[0]:
            grads["m"] = -(g_Z_sum * self.scale_z).sum((0, 1))
        if needs[1] or need_c["scale_outer"]:
            g_B = self._grad_B(b_inv, g_W, g_hl)
            if needs[1]:
                grads["S"] = self._grad_S(g_B)
            if need_c["scale_outer"]:
                grads["scale_outer"] = g_B * S
        if need_c["scale_z"]:
            g_scale = -m * g_Z_sum
            g_scale[:e].add_(gC.T[:, None, :] * lbt)
            grads["scale_z"] = g_scale
        if need_c["w_coef"]:
            grads["w_coef"] = g_W * (self.w_offset - b_inv[self.w_index])
        grads["log_alpha2"] = g_logq.sum(-1) + g_logk.sum(-1)
        if need_c["alpha2"] and not mean_only:
            grads["alpha2"] = gV.diagonal().clone()
        grads["beta"] = g_lb * q
        grads["beta_a"], grads["beta_b"], grads["inv_k"] = g_beta_a, g_beta_b, g_inv_k
        out = [grads.get("m"), grads.get("S")]
        out += [grads.get(name) if need else None for name, need in need_c.items()]
        return out

    def _compiled_factors(self, m, W, half_logdet):
        """``Z, ZW (G, n, d)``, ``zwz (G, n)``, ``log_k (E, n)`` and the kernel's ``left, right (P, n, d + 2)`` as
        the torch operations of :meth:`_forward` make them, from one compiled sweep
        (:func:`plugins.pilco.fused.pair_factors`). ``Z``, ``ZW`` and ``right`` are transposed views of arrays laid
        out with the basis points last (``right``'s is the layout :func:`plugins.pilco.fused.forward` reads)."""
        from plugins.pilco import fused

        if self._factor_constants is None:  # the posterior's part, once (values only: the backward pass is by hand)
            self._factor_constants = tuple(
                t.detach().contiguous().numpy() for t in (self.X_z.transpose(1, 2), self.scale_z[:, 0], self.log_alpha2))
        XzT, scale, log_alpha2 = self._factor_constants
        e, p, d = self.num_outputs, self.num_pairs, self.input_dim
        groups, n = XzT.shape[0], XzT.shape[2]
        ZT, ZWT, zwz, log_k = np.empty((groups, d, n)), np.empty((groups, d, n)), np.empty((groups, n)), np.empty((e, n))
        L, Rt = np.empty((p, n, d + 2)), np.empty((p, d + 2, n))
        first, second = self._pair_outputs_numpy
        fused.pair_factors(XzT, scale, m.detach().contiguous().numpy(), W.detach().contiguous().numpy(), log_alpha2,
                           half_logdet.detach().contiguous().numpy(), first, second, ZT, ZWT, zwz, log_k, L, Rt)
        t = torch.from_numpy
        return t(ZT).mT, t(ZWT).mT, t(zwz), t(log_k), t(L), t(Rt).mT

    def _grad_B(self, b_inv, g_W, g_hl):
        """Gradient wrt ``B = scale_outer * S + I`` ``(E + P, d, d)`` from those wrt ``W (G, d, d)`` and
        ``1/2 log|B|`` ``(E + P,)``; ``W = (w_offset - B^-1[w_index]) * w_coef``."""
        g_binv = torch.zeros_like(b_inv).index_add_(0, self.w_index, g_W * self.w_coef, alpha=-1.0)
        return torch.baddbmm(0.5 * g_hl[:, None, None] * b_inv, b_inv @ g_binv, b_inv, alpha=-1.0)

    def _grad_S(self, g_B):
        """Gradient wrt ``S`` from that wrt every ``B``. ``S`` enters through a Cholesky factorisation,
        which reads it as symmetric: the symmetric gradient (torch's convention for linalg.cholesky,
        so every path agrees)."""
        g_S = (g_B * self.scale_outer).sum(0)
        return 0.5 * (g_S + g_S.T)

    def _backward_compiled(self, saved, gM, gC, g_quad, g_trace, needs):
        """:meth:`_backward` where only ``m`` and ``S`` need gradients and the fused kernel saved the
        contraction's (the dynamics GP during a policy search): :func:`plugins.pilco.fused.input_gradients`
        takes them to ``W``, ``1/2 log|B|`` and the summed ``Z`` in one compiled sweep, without the
        ``(G, n, d)`` temporaries or the contraction's ``(P, n, d + 2)`` gradients."""
        from plugins.pilco import fused

        m, S, b_inv, W, Z, ZW, q, lb, lbt, left, right, inv_k, q_wr, kept, jac, M = saved
        e, p, d = self.num_outputs, self.num_pairs, self.input_dim
        groups, n = Z.shape[0], Z.shape[1]
        traced = inv_k.shape[0] if g_trace is not None else 0
        gt = g_trace[:traced].contiguous().numpy() if traced else np.zeros(0)
        w = (gC.T * self.scale_z[:e, 0]).contiguous()  # (E, d)  dL/dlbt
        g_W, g_Z_sum = np.empty((groups, d, d)), np.empty((groups, d))
        g_hl, g_logk = np.empty(e + p), np.zeros((e, n))
        first, second = self._pair_outputs_numpy
        ZT, ZWT = (np.ascontiguousarray(t.mT.numpy()) for t in (Z, ZW))  # views of _compiled_factors' arrays: no copy
        fused.input_gradients(ZT, ZWT, W.contiguous().numpy(), first, second, lb.numpy(), w.numpy(), gM.contiguous().numpy(),
                              jac["gA"], jac["gu"], jac["gBv"], jac["hA"], jac["hu"], jac["hBv"], g_quad.numpy(), gt,
                              g_W, g_Z_sum, g_hl, g_logk)
        out = [None] * (2 + len(_CONSTANTS))
        if needs[0]:
            out[0] = -(torch.from_numpy(g_Z_sum) * self.scale_z[:, 0]).sum(0)
        if needs[1]:
            out[1] = self._grad_S(self._grad_B(b_inv, torch.from_numpy(g_W), torch.from_numpy(g_hl)))
        return out


class _MomentsFunction(torch.autograd.Function):
    """:meth:`MomentMatchingGP.predict` with the hand-derived backward pass.

    Inputs ``(m, S, gp, mean_only, *gp.constants)``; the constants are passed so that
    autograd routes their gradients to the posterior's parameters (e.g. the RBF policy's).
    """

    @staticmethod
    def forward(ctx, m, S, gp: MomentMatchingGP, mean_only: bool, *constants):
        (M, V, C), saved = gp._forward(m, S, mean_only, contract=gp._contract_forward)
        # ``ctx.saved`` is a plain attribute (not save_for_backward): holding the output M itself
        # would make a reference cycle through the C++ graph that Python's GC cannot free (it
        # leaked ~17 MB per J+dJ at n = 80 and OOM-killed a cart-pole run); keep a detached alias.
        saved = (*saved[:-1], saved[-1].detach())
        ctx.gp, ctx.mean_only, ctx.saved = gp, mean_only, saved
        return M, V, C

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gM, gV, gC):
        gp = ctx.gp
        e = gp.num_outputs
        gM = gp.beta.new_zeros(e) if gM is None else gM
        gV = gp.beta.new_zeros(e, e) if gV is None else gV
        gC = gp.beta.new_zeros(gp.input_dim, e) if gC is None else gC
        needs = ctx.needs_input_grad
        grads = gp._backward(ctx.saved, gM, gV, gC, ctx.mean_only, needs[:2] + needs[4:])
        return grads[0], grads[1], None, None, *grads[2:]


def predict_uncertain(
    posterior: GPPosterior, m: torch.Tensor, S: torch.Tensor, mean_only: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``f(x)`` for ``x ~ N(m, S)`` under ``E`` GPs (paper eqs. 14-16, 20-23).

    Args:
        posterior: the GPs (basis inputs ``(n, d)``, weights ``beta (E, n)``, ``inv_k (E, n, n)``
            symmetric).
        m: ``(d,)`` input mean.
        S: ``(d, d)`` input covariance (symmetric positive semi-definite; may be singular).
        mean_only: drop ``alpha_a^2 - tr(inv_k_a Q_aa)`` (moments of the GP mean function only).

    Returns:
        ``M (E,)`` predictive mean, ``V (E, E)`` predictive covariance (latent f, no observation
        noise), ``C (d, E)`` with ``cov[x, f(x)] = S @ C``.

    For repeated calls with one posterior use :class:`MomentMatchingGP` (same maths, the
    posterior-only work done once).
    """
    return MomentMatchingGP(posterior).predict(m, S, mean_only)
