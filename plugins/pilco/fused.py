"""The ``Q`` contraction of moment matching with compiled loops (numba; extra ``fast``).

Moment matching spends most of its time on one contraction per output pair ``p``
(:mod:`plugins.pilco.moments`; ``P`` pairs, ``n`` basis points, ``d`` GP inputs)::

    Q_p[i, j] = exp(u_p[i] + v_p[j] + A_p[i] . B_p[j])                          (n, n)
    quad_p    = w_l[p] . Q_p w_r[p],   trace_a = sum_ij inv_k_a[i, j] Q_a[i, j]   (a < E')

and, in the backward pass, on the products of ``G_p = Q_p * (g_quad_p w_l w_r^T + g_trace_p inv_k)``::

    gA_p = G_p B_p,  gu_p = G_p 1,  gB_p = G_p^T A_p,  gv_p = G_p^T 1,  g_w_r = g_quad_p Q_p^T w_l.

The torch reference (``moments._contract_forward`` / ``_contract_backward``) forms ``G`` and
``inv_k * Q`` as ``n x n`` matrices and streams ``Q`` through five thin matrix products, two of
them for constant columns whose gradient nobody reads. Here:

* ``Q`` is formed one of two ways (``inline``, the kernel names of :mod:`plugins.pilco.moments`):
  by torch and NumPy, a block of pairs at a time (a batched product and NumPy's SIMD ``exp``;
  kernel ``numba``), or inside the compiled loops, two rows at a time, never stored (kernel
  ``fused``: each row is the ``d + 2`` multiply-adds of its exponent and :func:`exp_inline`, a
  vectorisable ``exp``, so ``Q`` never goes through memory and no product is streamed twice);
* the forward sums read each block once while it is in cache (:func:`reduce_rows`), or take each
  row as it is formed (``kernels(d).forward_q``);
* the backward kernel (``kernels(d).backward``, ``backward_q``) reads ``Q`` once, two rows at a time,
  forms ``G``'s rows on the fly and accumulates all four products and ``g_w_r`` in the same sweep;
  only the columns that carry a gradient are computed, and ``G`` and ``inv_k * Q`` never exist;
* with the fused kernel, a forward pass that a backward pass will follow (``jacobian``) does that
  backward's products already, from the rows it has just formed: ``quad_p`` and ``trace_p`` are
  scalars, so ``G_p = g_quad_p Q_p (w_l w_r^T) + g_trace_p Q_p inv_k`` and every gradient is
  ``g_quad_p`` times that of ``quad_p`` plus ``g_trace_p`` times that of ``trace_p``. ``forward_jac``
  computes those two (the products with ``(g_quad, g_trace) = (1, 0)`` and ``(0, 1)``, ``(P, n, 2d + 3)``
  numbers per step) and :func:`backward` only scales and adds them: ``Q`` is formed once per J + dJ,
  not twice (J + dJ 1.24-1.26x faster at the unicycle's and the double pendulum's sizes,
  ``results/benchmarks/objective_gradient_before_after_saved_gradients.md``);
* where the backward pass needs no gradient by basis point (the dynamics GP in a policy search: its basis
  points are fixed), ``G^T A`` is needed only summed over the basis points, and that sum is ``A^T (G 1)``,
  which the rows' sums already give: ``forward_jac_rows`` (``forward``'s ``columns=False``) saves only the
  row products ``G B``, ``G 1`` and the column sums ``G^T 1``, half the multiply-adds of ``forward_jac``'s
  sweep and no ``(d, n)`` column accumulators in cache (J + dJ 1.21x on the double pendulum and 1.23x on the
  unicycle on one thread, 1.12x on two, ``results/benchmarks/ab_objective_lean_jacobian*.md``);
* the diagonal pairs ``(a, a)`` (``forward``'s ``symmetric``) have a symmetric ``Q``, equal weights and
  ``A = B M``: ``forward_q_sym`` / ``forward_jac_sym`` form only its upper triangle (each element
  stands for its mirror too, the diagonal counts half), so half the ``exp``; their ``G^T A`` is
  ``G B M``, a ``(n, d) x (d, d)`` product in the driver instead of a second sweep (a diagonal pair 1.5-1.7x
  cheaper, about what an off-diagonal one costs: ``results/benchmarks/fused_pair_cost.md``; J + dJ 1.05-1.09x,
  ``results/benchmarks/ab_objective_symmetric_pairs.md``);
* the saved-gradient sweeps of ``forward_jac_sym`` and ``forward_jac_rows`` take :data:`PASS_COLUMNS` columns
  of ``B`` per pass over a pair of rows, so that a pass's accumulators (and the mirror weights) fit the vector
  registers.

Around the contraction, moment matching's own per-step work on the ``G = E + 2P`` groups of ``(n, d)``
scaled differences (``Z``, ``Z W``, the kernel's factors; in the backward pass the sums that take the
contraction's gradients to ``m`` and ``S``) is two more compiled sweeps, :func:`pair_factors` and
:func:`input_gradients`, instead of ~30 torch operations on ``(G, n, d)`` temporaries (the dynamics GP
with the fused kernel; ``MomentMatchingGP(compiled_glue=False)`` keeps the torch operations). They lay
the groups out with the basis points last, so that every loop runs over them: J + dJ 1.10x, 1.23x and
1.16x faster on the double pendulum, the unicycle and cart-pole (one thread,
``results/benchmarks/ab_objective_compiled_glue.md``).

The backward kernel is generated per input dimension ``d``: its inner loop runs over ``j``
(contiguous, vectorised by LLVM) with ``2 d`` multiply-add accumulators in registers, which needs
``2 d`` scalar variables in the source. :func:`kernels` writes the source for one ``d`` (the same
template for every ``d``) to a file in :func:`cache_dir` and imports it, so that numba's on-disk
cache keeps the compiled code across processes: a machine compiles it once per ``d`` (seconds).

numba's CPU target is set up for the CPU's widest vectors before the first kernel is compiled
(:mod:`harness.vector_width`: on Intel's AVX-512 server CPUs LLVM's tuning would keep the loops at 256
bits; 512 measured J + dJ 1.21-1.22x faster there at the double pendulum's and the unicycle's sizes, 0.9x
at cart-pole's n = 100, ``results/benchmarks/objective_gradient_vector_width.md``).

The kernels are compiled with :class:`NoAliasCompiler`, which tells LLVM that their array
arguments do not overlap (the drivers allocate every array a kernel writes). Without it LLVM must
check at run time whether the ~20 rows a loop reads and writes overlap, gives up above 8 such
checks, and leaves the loop scalar (3x slower, measured).

Threads: :func:`forward` and :func:`backward` split the pairs into ``threads`` contiguous groups
that run on a pool of Python threads (torch single-threaded in each; the kernels release the GIL).
Each pair is computed by one thread in a fixed order, so results do not depend on ``threads``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import inspect
import os
import sys
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from pathlib import Path
from types import ModuleType

import numpy as np
import torch
from numba import njit, types
from numba.core.compiler import CompilerBase, DefaultPassBuilder
from numba.core.compiler_machinery import FunctionPass, register_pass
from numba.core.untyped_passes import TranslateByteCode
from numba.extending import intrinsic

from harness.vector_width import configure as _configure_vector_width
from harness.vector_width import host_has_avx512

#: 512-bit vectors where the CPU has AVX-512 (LLVM's tuning would keep the kernels at 256 bits on Intel's
#: server CPUs); before the first ``@njit`` below, which creates numba's CPU target (:mod:`harness.vector_width`)
VECTOR_WIDTH = _configure_vector_width()


#: columns of ``B`` per pass of the saved-gradient sweeps of ``forward_jac_sym`` and ``forward_jac_rows``
#: (:func:`source`): each column needs two row accumulators in registers, and in the symmetric kernels two
#: mirror weights, ``4 d`` in all with every column in one pass (36 at the double pendulum's d = 9, 2 d in
#: the rows kernel), against the 16 vector registers of AVX2; a further pass re-reads the rows of ``Q`` and
#: forms ``G``'s again (two multiplies). With 4 on an AMD EPYC Zen 3 (AVX2), in isolation, the symmetric
#: kernel ran 1.2-1.3x and the rows kernel 1.05x (d = 9) and 1.2x (d = 11) faster than with one pass; in
#: J + dJ the unicycle 1.08x and the double pendulum 1.01x, within this machine's noise
#: (``results/benchmarks/ab_objective_pass_columns_zen3.md``); the same products, summed in another order (the
#: saved gradients move by ~1e-15 relative). On CPUs with AVX-512 (32 registers) the passes are unmeasured,
#: so there it stays 1000: every column in one pass, as before
PASS_COLUMNS = 1000 if host_has_avx512() else 4

#: fast-math flags of the kernels: reassociation (vectorised sums) and contraction (FMA); no
#: assumptions about NaN or infinity, so a NaN in the inputs still shows in the results
FASTMATH = {"contract", "reassoc", "nsz", "arcp"}


@register_pass(mutates_CFG=False, analysis_only=True)
class _ArgumentsDoNotAlias(FunctionPass):
    """Sets numba's ``noalias`` flag: LLVM may assume the function's array arguments do not overlap."""

    _name = "pilco_arguments_do_not_alias"

    def __init__(self) -> None:
        FunctionPass.__init__(self)

    def run_pass(self, state) -> bool:
        state.flags.noalias = True
        return False


class NoAliasCompiler(CompilerBase):
    """numba's nopython pipeline with :class:`_ArgumentsDoNotAlias` (numba sets the same flag on the
    loop bodies of ``parallel=True`` functions whose arrays it proves distinct)."""

    def define_pipelines(self):
        pm = DefaultPassBuilder.define_nopython_pipeline(self.state)
        pm.add_pass_after(_ArgumentsDoNotAlias, TranslateByteCode)
        pm.finalize()
        return [pm]


@intrinsic
def _bits_as_float(typingctx, bits):
    """The float64 whose IEEE-754 bit pattern is the int64 ``bits`` (a free register move, vectorisable)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], context.get_value_type(types.float64))
    return types.float64(types.int64), codegen


@intrinsic
def _float_as_bits(typingctx, x):
    """The int64 bit pattern of the float64 ``x``."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], context.get_value_type(types.int64))
    return types.int64(types.float64), codegen


_LOG2_E = 1.4426950408889634
#: ln 2 in two parts (Cody-Waite): ``k ln2_hi`` is exact for ``|k| < 2^11``
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
#: 1.5 * 2^52: adding it rounds a float of magnitude < 2^51 to an integer held in the low mantissa bits
_ROUND = 6755399441055744.0


@njit(fastmath={"contract"}, nogil=True, cache=True)
def exp_inline(x: float) -> float:
    """``exp(x)`` in straight-line arithmetic that LLVM vectorises inside the kernels' loops (a call to
    libm's ``exp`` would keep them scalar; numba's pip wheels have no vector maths library).

    ``x = k ln2 + r``, ``|r| <= ln2 / 2``; ``exp(r)`` by its Taylor polynomial of degree 12 (remainder
    below 2e-16 relative), times ``2^k`` built from its bit pattern in two factors so that results down
    to the smallest subnormal come out right. Within 2 ulp of NumPy's ``exp`` (tested), including
    0 below -745.2, ``inf`` above 709.8 and NaN for NaN (``x`` is clamped to [-746, 710] first, which
    keeps ``k`` in range). Compiled without reassociation, which would undo the rounding and the
    two-part reduction.
    """
    y = min(max(x, -746.0), 710.0)
    t = y * _LOG2_E + _ROUND
    k = t - _ROUND
    r = y - k * _LN2_HI
    r = r - k * _LN2_LO
    p = 1.0 / 479001600.0
    p = p * r + 1.0 / 39916800.0
    p = p * r + 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    ki = _float_as_bits(t) - _float_as_bits(_ROUND)
    k1 = ki >> 1
    return p * _bits_as_float((k1 + 1023) << 52) * _bits_as_float((ki - k1 + 1023) << 52)


@njit(fastmath=FASTMATH, nogil=True, cache=True, pipeline_class=NoAliasCompiler)
def reduce_rows(Q, first, wl, wr, inv_k, quad, trace, q_wr):
    """The forward sums of pairs ``first .. first + len(Q) - 1`` (one read of their ``Q``).

    ``q_wr[p] = Q_p w_r[p]`` ``(n,)``, ``quad[p] = w_l[p] . q_wr[p]`` and, for ``p < len(inv_k)``,
    ``trace[p] = sum_ij inv_k[p, i, j] Q_p[i, j]``.
    """
    n = Q.shape[1]
    ntrace = inv_k.shape[0]
    for pb in range(Q.shape[0]):
        p = first + pb
        sq = 0.0
        st = 0.0
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += Q[pb, i, j] * wr[p, j]
            q_wr[p, i] = s
            sq += wl[p, i] * s
            if p < ntrace:
                t = 0.0
                for j in range(n):
                    t += Q[pb, i, j] * inv_k[p, i, j]
                st += t
        quad[p] = sq
        if p < ntrace:
            trace[p] = st


@njit(fastmath=FASTMATH, nogil=True, cache=True, inline="always")
def _group_products(ZT, T, g, out):
    """``out[g] = ZT[g] T^T``: ``(d, n) x (n, d)``, each entry a sum over the ``n`` basis points."""
    d, n = T.shape
    for a in range(d):
        for b in range(d):
            s = 0.0
            for i in range(n):
                s += ZT[g, a, i] * T[b, i]
            out[g, a, b] = s


@njit(fastmath=FASTMATH, nogil=True, cache=True, pipeline_class=NoAliasCompiler)
def input_gradients(ZT, ZWT, W, first, second, lb, w, gM, gA, gu, gBv, hA, hu, hBv, g_quad, g_trace,
                    g_W, g_Z_sum, g_hl, g_logk):
    """Moment matching's backward pass from the contraction's gradients to ``W`` and ``m`` in one sweep
    (``moments.MomentMatchingGP._backward`` where no basis point needs its gradient: the dynamics GP).

    Inputs as ``_backward`` names them, the groups transposed as :func:`pair_factors` leaves them:
    ``ZT, ZWT (G, d, n)``, ``W (G, d, d)`` (``G = E + 2P``: mean groups, pair left groups, pair right
    groups), the pairs' outputs ``first, second (P,)``, ``lb (E, n)``, ``w (E, d)`` (the gradient wrt
    ``lbt``), ``gM (E,)`` (wrt ``M``, with ``V``'s ``- M M^T`` folded in), the contraction's saved
    gradients ``gA, gu, gBv`` of every ``quad_p`` and ``hA, hu, hBv`` of every ``trace_p`` (:func:`forward`'s
    ``jacobian``) and their weights ``g_quad (P,)``, ``g_trace (E',)``.

    Outputs (written): ``g_W (G, d, d)``, ``g_Z_sum (G, d)`` (the gradient wrt ``Z`` summed over the ``n``
    basis points, all that ``m`` needs) and ``g_hl (E + P,)`` (wrt half the log-determinants);
    ``g_logk (E, n)`` must be zero on entry (scratch: the pairs' gradients wrt each output's ``log k``). With the pairs' gradients ``g_uv`` (wrt ``u``, ``v``, here
    ``g_zwz``) and ``g_ZW`` (``2 G B`` on the left groups, ``lb w`` on the mean groups), the sums over ``i`` of::

        g_Z_i = 2 g_zwz_i ZW_i + g_ZW_i W (+ the right groups' G^T A, - g_logk Z on the mean groups)
        g_W  += Z_i^T (g_zwz_i Z_i + g_ZW_i)

    the same arithmetic as the torch path without its ``(G, n, d)`` temporaries, every loop over ``i``.
    The pairs run first, since a mean group's ``g_logk`` sums the ``g_uv`` of every pair with its output.
    A right group's ``G^T A`` is needed only summed over its basis points, and that sum is
    ``A^T (G 1)`` with ``A = 2 ZW`` of the left group and ``G 1`` its ``g_uv``: ``gBv`` and ``hBv`` are read
    in their last row (``G^T 1``) only, so the kernel need not make the others (``forward_jac_rows``).
    """
    G, d, n = ZT.shape
    e = lb.shape[0]
    p = first.shape[0]
    nt = g_trace.shape[0]
    guv = np.empty(n)
    g_lb = np.empty(n)
    T = np.empty((d, n))
    szw = np.empty(d)
    sa = np.empty(d)
    for pp in range(p):
        gq = g_quad[pp]
        gt = g_trace[pp] if pp < nt else 0.0
        for side in range(2):
            g = e + pp + side * p
            if side == 0:
                for i in range(n):
                    guv[i] = gq * gu[pp, i]
                if pp < nt:
                    for i in range(n):
                        guv[i] += gt * hu[pp, i]
            else:
                for i in range(n):
                    guv[i] = gq * gBv[pp, d, i]
                if pp < nt:
                    for i in range(n):
                        guv[i] += gt * hBv[pp, d, i]
            out = first[pp] if side == 0 else second[pp]
            hl = 0.0
            for i in range(n):
                g_logk[out, i] += guv[i]
                hl += guv[i]
            for k in range(d):
                s = 0.0
                for i in range(n):
                    s += guv[i] * ZWT[g, k, i]
                g_Z_sum[g, k] = 2.0 * s
                if side == 0:
                    sa[k] = 2.0 * s  # A^T (G 1), A = 2 ZW: the right group's summed G^T A
            if side == 0:
                g_hl[e + pp] = -hl
                for i in range(n):
                    for k in range(d):
                        T[k, i] = 2.0 * gq * gA[pp, i, k]
                if pp < nt:
                    for i in range(n):
                        for k in range(d):
                            T[k, i] += 2.0 * gt * hA[pp, i, k]
                for k in range(d):
                    s = 0.0
                    for i in range(n):
                        s += T[k, i]
                    szw[k] = s
                for k in range(d):
                    s = 0.0
                    for b in range(d):
                        s += szw[b] * W[g, b, k]
                    g_Z_sum[g, k] += s
                for k in range(d):
                    for i in range(n):
                        T[k, i] += guv[i] * ZT[g, k, i]
            else:
                for k in range(d):
                    g_Z_sum[g, k] += sa[k]
                for k in range(d):
                    for i in range(n):
                        T[k, i] = guv[i] * ZT[g, k, i]
            _group_products(ZT, T, g, g_W)
    for a in range(e):
        for i in range(n):
            g_lb[i] = gM[a]
        for k in range(d):
            for i in range(n):
                g_lb[i] += ZWT[a, k, i] * w[a, k]
        hl = 0.0
        slb = 0.0
        for i in range(n):
            glq = g_lb[i] * lb[a, i]
            hl += glq
            guv[i] = -0.5 * glq
            slb += lb[a, i]
        g_hl[a] = -hl
        for k in range(d):
            s1 = 0.0
            s2 = 0.0
            for i in range(n):
                s1 += guv[i] * ZWT[a, k, i]
                s2 += g_logk[a, i] * ZT[a, k, i]
            s = 2.0 * s1 - s2
            for b in range(d):
                s += slb * w[a, b] * W[a, b, k]
            g_Z_sum[a, k] = s
        for k in range(d):
            for i in range(n):
                T[k, i] = guv[i] * ZT[a, k, i] + lb[a, i] * w[a, k]
        _group_products(ZT, T, a, g_W)


@njit(fastmath=FASTMATH, nogil=True, cache=True, pipeline_class=NoAliasCompiler)
def pair_factors(XzT, scale, m, W, log_alpha2, half_logdet, first, second, ZT, ZWT, zwz, log_k, L, Rt):
    """Moment matching's scaled differences and the fused kernel's factors in one compiled sweep
    (``moments.MomentMatchingGP._forward`` with the fused kernel).

    Inputs: ``XzT (G, d, n)`` (``X_z`` transposed: every group's scaled basis points), ``scale (G, d)``,
    the input mean ``m (d,)``, ``W (G, d, d)``, ``log_alpha2 (E,)``, ``half_logdet (E + P,)`` and the
    pairs' outputs ``first, second (P,)``. Outputs (written), the groups transposed so that every loop
    runs over the ``n`` basis points (contiguous)::

        ZT  = (X_z - m scale)^T        (G, d, n)      ZWT = (Z W)^T  (G, d, n)
        zwz = rowsum(Z * ZW)           (G, n)         log_k = log alpha^2 - |Z_mean|^2 / 2   (E, n)

    and for pair ``p`` (left group ``E + p``, right group ``E + P + p``) the kernel's ``left``
    ``L = [2 ZW_l, u, 1]`` ``(P, n, d + 2)``, ``right`` transposed ``Rt = [Z_r, 1, v]^T``
    ``(P, d + 2, n)``, with ``u = log_k[first] + zwz_l - half_logdet[E + p]`` and ``v = log_k[second] + zwz_r``.
    """
    G, d, n = XzT.shape
    e = log_alpha2.shape[0]
    p = first.shape[0]
    for g in range(G):
        for k in range(d):
            c = m[k] * scale[g, k]
            for i in range(n):
                ZT[g, k, i] = XzT[g, k, i] - c
        for i in range(n):
            zwz[g, i] = 0.0
        for b in range(d):
            for i in range(n):
                ZWT[g, b, i] = 0.0
            for a in range(d):
                w = W[g, a, b]
                for i in range(n):
                    ZWT[g, b, i] += w * ZT[g, a, i]
            for i in range(n):
                zwz[g, i] += ZWT[g, b, i] * ZT[g, b, i]
    for a in range(e):
        for i in range(n):
            log_k[a, i] = 0.0
        for k in range(d):
            for i in range(n):
                log_k[a, i] += ZT[a, k, i] * ZT[a, k, i]
        for i in range(n):
            log_k[a, i] = log_alpha2[a] - 0.5 * log_k[a, i]
    for pp in range(p):
        gl = e + pp
        gr = e + p + pp
        hl = half_logdet[e + pp]
        for k in range(d):
            for i in range(n):
                Rt[pp, k, i] = ZT[gr, k, i]
        for i in range(n):
            Rt[pp, d, i] = 1.0
            Rt[pp, d + 1, i] = log_k[second[pp], i] + zwz[gr, i]
        for i in range(n):
            for k in range(d):
                L[pp, i, k] = 2.0 * ZWT[gl, k, i]
            L[pp, i, d] = log_k[first[pp], i] + zwz[gl, i] - hl
            L[pp, i, d + 1] = 1.0


_HEADER = '''"""Generated by plugins/pilco/fused.py for input dimension d = {d}: do not edit."""
# exp_inline's source: {exp_digest} (numba's cache of this file does not see changes to what it
# imports; a new exp_inline changes this line, so the file's name, so the cache)
from numba import njit, uint64

from plugins.pilco.fused import NoAliasCompiler, exp_inline

FASTMATH = {fastmath}
'''

_BACKWARD = '''
@njit(fastmath=FASTMATH, nogil=True, cache=True, pipeline_class=NoAliasCompiler)
def {name}({source}, first, last, A, Bt, wl, wr, inv_k, g_quad, g_trace, need_wr, gA, gu, gBv, gwr):
    \"\"\"Gradients of pairs first .. last - 1 through G = Q * (g_quad w_l w_r^T + g_trace inv_k),
    two rows of Q at a time ({what}). Writes their gA (n, d), gu (n,), gBv (d + 1, n) = [gB^T; gv]
    and, when need_wr, gwr (n,).\"\"\"
    n = gA.shape[1]
    ntrace = inv_k.shape[0]
    for p in range(first, last):
{pb}
        for c in range({d} + 1):
            for j in range(n):
                gBv[p, c, j] = 0.0
        for j in range(n):
            gwr[p, j] = 0.0
        gq = g_quad[p]
        gt = g_trace[p] if p < ntrace else 0.0
        for i0 in range(0, n, 2):
            # the second row of the last pair of rows of an odd n repeats the first with weight 0
            two = i0 + 1 < n
            i1 = i0 + 1 if two else i0
            c0 = gq * wl[p, i0]
            c1 = gq * wl[p, i1] if two else 0.0
            t1 = gt if two else 0.0
{load_a01}
{zero_acc}
{rows}
            su0 = 0.0
            su1 = 0.0
            if p < ntrace:
                for j in range(n):
                    g0 = {q0} * (c0 * wr[p, j] + gt * inv_k[p, i0, j])
                    g1 = {q1} * (c1 * wr[p, j] + t1 * inv_k[p, i1, j])
{body}
            else:
                for j in range(n):
                    w = wr[p, j]
                    g0 = {q0} * (c0 * w)
                    g1 = {q1} * (c1 * w)
{body}
{store_acc}
            gu[p, i0] = su0
            if two:
                gu[p, i1] = su1
            if need_wr:
                w0 = wl[p, i0]
                w1 = wl[p, i1] if two else 0.0
                for j in range(n):
                    gwr[p, j] += {q0} * w0 + {q1} * w1
        if need_wr:
            for j in range(n):
                gwr[p, j] *= gq
'''

#: the lines both forward templates share: the trace gradients' zeroing and the start of a pair's loop over rows
_PAIR_START = '''        if p < ntrace:
            for c in range({d} + 1):
                for j in range(n):
                    hBv[p, c, j] = 0.0
#JAC-END
        sq = 0.0
        st = 0.0
        for i0 in range(0, n, 2):
            # the second row of the last pair of rows of an odd n is i0 again, with weight 0
            two = i0 + 1 < n
            i1 = i0 + 1 if two else i0
'''

#: the saved gradients' sweeps both forward templates share (``.format``-ed with the columns a row runs
#: over): the gradient of quad_p (row weights c0, c1) and, traced pairs, of trace_p
_JAC_QUAD = '''{{zero_acc}}
            su0 = 0.0
            su1 = 0.0
            for j in {cols}:
                w = wr[p, j]
                g0 = q0[j] * (c0 * w)
                g1 = q1[j] * (c1 * w)
{{body_g}}
{{store_g}}
            gu[p, i0] = su0
            if two:
                gu[p, i1] = su1'''

_JAC_TRACE = '''{{zero_acc_h}}
                su0 = 0.0
                su1 = 0.0
                for j in {cols}:
                    g0 = q0[j] * inv_k[p, i0, j]
                    g1 = q1[j] * {inv_k_i1}
{{body_h}}
{{store_h}}
                hu[p, i0] = su0
                if two:
                    hu[p, i1] = su1'''

#: forward_jac_rows' saved gradients: G's row products gA = G B, hu = G 1 and its column sums G^T 1 only. With
#: G = Q w_l w_r^T the row weight c0 = w_l[i0] is applied once per row (gA's sums run over Q w_r); hu is the
#: forward sum r0, and gu = w_l * q_wr is left to the driver: c0 * s0 here would share its product with
#: sq's multiply-add, which LLVM then no longer fuses, and J would no longer be forward_q's to the bit
_JAC_ROWS = '''{passes_rows}
            if p < ntrace:
                t1 = 1.0 if two else 0.0
{zero_acc_h}
                for j in range(n):
                    g0 = q0[j] * inv_k[p, i0, j]
                    g1 = q1[j] * inv_k[p, i1, j]
{body_rows_h}
{store_h}
                hu[p, i0] = r0
                if two:
                    hu[p, i1] = r1'''

_FORWARD = '''
@njit(fastmath=FASTMATH, nogil=True, cache=True, pipeline_class=NoAliasCompiler)
def {signature}:
    \"\"\"{doc}\"\"\"
    n = L.shape[1]
    ntrace = inv_k.shape[0]
    for p in range(first, last):
#JAC-BEGIN
        for c in range({d} + 1):
            for j in range(n):
                gBv[p, c, j] = 0.0
#COLS-BEGIN
        for j in range(n):
            gwr[p, j] = 0.0
#COLS-END
''' + _PAIR_START + '''{rows}
            s0 = 0.0
            s1 = 0.0
            if p < ntrace:
                r0 = 0.0
                r1 = 0.0
                for j in range(n):
                    s0 += q0[j] * wr[p, j]
                    s1 += q1[j] * wr[p, j]
                    r0 += q0[j] * inv_k[p, i0, j]
                    r1 += q1[j] * inv_k[p, i1, j]
                st += r0 + r1 if two else r0
            else:
                for j in range(n):
                    s0 += q0[j] * wr[p, j]
                    s1 += q1[j] * wr[p, j]
            q_wr[p, i0] = s0
            sq += wl[p, i0] * s0
            if two:
                q_wr[p, i1] = s1
                sq += wl[p, i1] * s1
#JAC-BEGIN
            c0 = wl[p, i0]
            c1 = wl[p, i1] if two else 0.0
#COLS-BEGIN
{load_a01}
''' + _JAC_QUAD.format(cols='range(n)') + '''
            for j in range(n):
                gwr[p, j] += q0[j] * c0 + q1[j] * c1
            if p < ntrace:
                t1 = 1.0 if two else 0.0
''' + _JAC_TRACE.format(cols='range(n)', inv_k_i1='(t1 * inv_k[p, i1, j])') + '''
#COLS-END
#ROWS-BEGIN
''' + _JAC_ROWS + '''
#ROWS-END
#JAC-END
        quad[p] = sq
        if p < ntrace:
            trace[p] = st
'''

_FORWARD_SYM = """
@njit(fastmath=FASTMATH, nogil=True, cache=True, pipeline_class=NoAliasCompiler)
def {signature}:
    \"\"\"{doc}\"\"\"
    n = L.shape[1]
    ntrace = inv_k.shape[0]
    # unsigned column indices: numba then omits the negative-index wrap-around, which for a loop that
    # starts at i0 it cannot prove unneeded and which keeps LLVM from vectorising it (2x, measured)
    nu = uint64(n)
    for p in range(first, last):
        for j in range(n):
            q_wr[p, j] = 0.0
#JAC-BEGIN
        for c in range({d} + 1):
            for j in range(n):
                gBv[p, c, j] = 0.0
""" + _PAIR_START + """            i0u = uint64(i0)
{rows}
            # the upper triangle j >= i, each element standing for itself and its mirror: the diagonal halved
            q0[i0] *= 0.5
            q1[i0] = 0.0
            if two:
                q1[i1] *= 0.5
            c0 = wl[p, i0]
            c1 = wl[p, i1]
            s0 = 0.0
            s1 = 0.0
            if p < ntrace:
                r0 = 0.0
                r1 = 0.0
                for j in range(i0u, nu):
                    w = wr[p, j]
                    s0 += q0[j] * w
                    s1 += q1[j] * w
                    q_wr[p, j] += q0[j] * c0 + q1[j] * c1
                    r0 += q0[j] * inv_k[p, i0, j]
                    r1 += q1[j] * inv_k[p, i1, j]
                st += r0 + r1
            else:
                for j in range(i0u, nu):
                    w = wr[p, j]
                    s0 += q0[j] * w
                    s1 += q1[j] * w
                    q_wr[p, j] += q0[j] * c0 + q1[j] * c1
            q_wr[p, i0] += s0
            sq += c0 * s0
            if two:
                q_wr[p, i1] += s1
                sq += c1 * s1
#JAC-BEGIN
{load_b01}
{passes_g}
            if p < ntrace:
{passes_h}
#JAC-END
        quad[p] = 2.0 * sq
        if p < ntrace:
            trace[p] = 2.0 * st
"""

#: the two kernels :data:`_FORWARD` makes: forward_q (its lines between ``#JAC-BEGIN`` and ``#JAC-END`` left
#: out) and forward_jac; their shared lines are the same code, so their J agree bit for bit
_FORWARD_KERNELS = {
    "forward_q": ("forward_q(L, Rt, q0, q1, first, last, wl, wr, inv_k, quad, trace, q_wr)",
                  "Sums of pairs first .. last - 1 (quad, trace, q_wr as reduce_rows) with Q_p[i, j] = exp(L[p, i] . "
                  "Rt[p, :, j]) formed two rows at a time into q0, q1 (L (P, n, d + 2), Rt (P, d + 2, n)); Q is never stored."),
    "forward_jac": ("forward_jac(L, Rt, q0, q1, first, last, A, Bt, wl, wr, inv_k, quad, trace, q_wr, gA, gu, gBv, gwr, hA, hu, hBv)",
                    "forward_q's sums and, from the same rows of Q, what the backward pass needs: the gradient of quad_p, "
                    "i.e. backward's products with g_quad = 1, g_trace = 0 (gA, gu, gBv and gwr = Q^T w_l), and for "
                    "p < len(inv_k) that of trace_p, g_quad = 0, g_trace = 1 (hA, hu, hBv). Both are scalars per pair, "
                    "so the backward pass only scales and adds these."),
    "forward_jac_rows": ("forward_jac_rows(L, Rt, q0, q1, first, last, Bt, wl, wr, inv_k, quad, trace, q_wr, gA, gBv, hA, hu, hBv)",
                         "forward_jac without the gradients by basis point of the right factor: gA and gv = gBv[:, d] "
                         "(hA, hu, hBv[:, d]) only (gu = w_l * q_wr: the driver); gBv[:, :d] (hBv) is left zero and no gwr is made. For moment matching's "
                         "compiled backward pass (input_gradients), which needs G^T A only summed over the basis points, "
                         "and that sum is A^T (G 1) = A^T gu. Its sweep has half the multiply-adds of forward_jac's: "
                         "hu is the forward sum, w_l[i] scales gA's rows once."),
}


#: the same two for the pairs whose ``Q`` is symmetric (moment matching's diagonal pairs ``(a, a)``): they
#: form the upper triangle only and accumulate each element's mirror by column (see :func:`forward`)
_FORWARD_SYM_KERNELS = {
    "forward_q_sym": ("forward_q_sym(L, Rt, q0, q1, first, last, wl, wr, inv_k, quad, trace, q_wr)",
                      "forward_q's sums for pairs whose Q_p is symmetric (w_l[p] = w_r[p], inv_k symmetric), from "
                      "the upper triangle j >= i of Q only, formed two rows at a time into q0, q1; the diagonal "
                      "counts half, and each element adds to q_wr by row and, for its mirror, by column."),
    "forward_jac_sym": ("forward_jac_sym(L, Rt, q0, q1, first, last, Bt, wl, wr, inv_k, quad, trace, q_wr, gA, gu, gBv, hA, hu, hBv)",
                        "forward_q_sym's sums and, from the same upper triangle, G B and G 1 of the symmetric "
                        "G = Q w_l w_r^T (and, for p < len(inv_k), G = Q * inv_k): their rows' part j >= i in "
                        "gA (n, d), gu (n,) (hA, hu) and their mirrors' part in gBv (d + 1, n) (hBv), which the "
                        "driver adds (_symmetric_jacobian)."),
}


def _forward_source(name: str, **fields) -> str:
    if name in _FORWARD_SYM_KERNELS:
        signature, doc = _FORWARD_SYM_KERNELS[name]
        text = _FORWARD_SYM.format(signature=signature, doc=doc, **fields)
    else:
        signature, doc = _FORWARD_KERNELS[name]
        text = _FORWARD.format(signature=signature, doc=doc, **fields)
    # forward_q* leave out the lines between #JAC-BEGIN and #JAC-END (the saved gradients), forward_jac_rows
    # those between #COLS-BEGIN and #COLS-END (forward_jac's), the others those between #ROWS-BEGIN and #ROWS-END
    skips = {"#JAC": name in ("forward_q", "forward_q_sym"), "#COLS": name == "forward_jac_rows",
             "#ROWS": name != "forward_jac_rows"}
    inside = dict.fromkeys(skips, False)  # the #COLS blocks lie inside #JAC ones
    kept = []
    for line in text.split("\n"):
        marker, _, end = line.partition("-")
        if marker in skips and end in ("BEGIN", "END"):
            inside[marker] = end == "BEGIN"
        elif not any(inside[m] and skips[m] for m in skips):
            kept.append(line)
    return "\n".join(kept)


def source(d: int, pass_columns: int | None = None) -> str:
    """The kernels' Python source for input dimension ``d``: ``forward_q``, ``forward_jac`` (its sums and
    the gradients of each pair's two outputs, for a backward pass that then only scales and adds),
    ``backward`` (reads a stored block ``Q`` holding pairs ``first .. last - 1``) and ``backward_q``
    (forms two rows of ``Q`` at a time into the scratch rows ``q0, q1 (n,)`` from ``L, Rt``, as
    ``forward_jac`` does). ``pass_columns``: see :data:`PASS_COLUMNS` (default)."""
    if d < 1:
        raise ValueError(f"input dimension must be >= 1, got {d}")
    per_pass = PASS_COLUMNS if pass_columns is None else int(pass_columns)
    if per_pass < 1:
        raise ValueError(f"pass_columns must be >= 1, got {pass_columns}")
    cs, ks = range(d), range(d + 2)

    def lines(template: str, indent: int, over=cs) -> str:
        return "\n".join(" " * indent + template.format(c=c) for c in over)

    def exponent(row: str) -> str:
        return " + ".join(f"l{row}{c} * Rt[p, {c}, j]" for c in ks)

    def times_b(indent: int) -> list[str]:
        """Loop-body lines accumulating G's rows g0, g1 times B into s0_c, s1_c."""
        return ([" " * indent + f"b{c} = Bt[p, {c}, j]" for c in cs]
                + [" " * indent + f"s0_{c} += g0 * b{c}" for c in cs]
                + [" " * indent + f"s1_{c} += g1 * b{c}" for c in cs])

    def products(out: str, indent: int) -> str:
        """The loop body accumulating G's rows g0, g1 times B (into s0_c, s1_c, su0, su1) and A (into ``out``)."""
        return "\n".join(
            times_b(indent)
            + [" " * indent + f"{out}[p, {c}, j] += g0 * a0_{c} + g1 * a1_{c}" for c in cs]
            + [" " * indent + "su0 += g0", " " * indent + "su1 += g1", " " * indent + f"{out}[p, {d}, j] += g0 + g1"]
        )

    def store(out: str, indent: int) -> str:
        return (lines(out + "[p, i0, {c}] = s0_{c}", indent) + "\n" + " " * indent + "if two:\n"
                + lines(out + "[p, i1, {c}] = s1_{c}", indent + 4))

    body = products("gBv", 20)
    common = dict(
        d=d, body=body,
        load_a01=lines("a0_{c} = A[p, i0, {c}]", 12) + "\n" + lines("a1_{c} = A[p, i1, {c}]", 12),
        zero_acc=lines("s0_{c} = 0.0", 12) + "\n" + lines("s1_{c} = 0.0", 12),
        store_acc=store("gA", 12),
    )
    rows = "\n".join([
        lines("l0{c} = L[p, i0, {c}]", 12, ks), lines("l1{c} = L[p, i1, {c}]", 12, ks),
        " " * 12 + "for j in range(n):",
        " " * 16 + f"q0[j] = exp_inline({exponent('0')})",
        " " * 16 + f"q1[j] = exp_inline({exponent('1')})",
    ])
    forward_fields = dict(d=d, load_a01=common["load_a01"], zero_acc=common["zero_acc"],
                          zero_acc_h=lines("s0_{c} = 0.0", 16) + "\n" + lines("s1_{c} = 0.0", 16),
                          body_g=products("gBv", 16), store_g=store("gA", 12),
                          body_h=products("hBv", 20), store_h=store("hA", 16))

    def row_products(out: str, indent: int, w0: str, w1: str) -> str:
        """forward_jac_rows' loop body: g0, g1 times B into s0_c, s1_c and their column sums into ``out[p, d]``."""
        return "\n".join(times_b(indent) + [" " * indent + f"{out}[p, {d}, j] += g0 * {w0} + g1 * {w1}"])

    forward_fields.update(body_rows_h=row_products("hBv", 20, "1.0", "t1"))
    def passes(out: str, acc: str, indent: int, g_lines: list[str], cols: str, mirror: bool, first: list[str],
               scale: tuple[str, str] = ("", ""), sums: str | None = None) -> str:
        """A saved-gradient sweep over the columns ``cols`` of rows i0, i1, ``per_pass`` columns of B a pass (each
        pass forms G's two rows again with ``g_lines``): G's rows times B into ``acc``'s rows (times ``scale``), with
        ``mirror`` also the mirrors' part into ``out``'s columns; ``first``: loop lines of the first pass only;
        ``sums``: the array that takes G's row sums (``G 1``), summed in the first pass."""
        pad, body = " " * indent, " " * (indent + 4)
        text = [pad + "su0 = 0.0", pad + "su1 = 0.0"] if sums else []
        first = ["su0 += g0", "su1 += g1", *first] if sums else first
        for k, start in enumerate(range(0, d, per_pass)):
            cc = range(start, min(start + per_pass, d))
            text += [pad + f"s{r}_{c} = 0.0" for r in (0, 1) for c in cc]
            text += [pad + f"for j in {cols}:"] + [body + line for line in g_lines]
            text += [body + f"b{c} = Bt[p, {c}, j]" for c in cc]
            text += [body + f"s{r}_{c} += g{r} * b{c}" for r in (0, 1) for c in cc]
            if mirror:
                text += [body + f"{out}[p, {c}, j] += g0 * a0_{c} + g1 * a1_{c}" for c in cc]
            if k == 0:
                text += [body + line for line in first]
            text += [pad + f"{acc}[p, i0, {c}] = {scale[0]}s0_{c}" for c in cc] + [pad + "if two:"]
            text += [body + f"{acc}[p, i1, {c}] = {scale[1]}s1_{c}" for c in cc]
        if sums:
            text += [pad + f"{sums}[p, i0] = su0", pad + "if two:", body + f"{sums}[p, i1] = su1"]
        return "\n".join(text)

    forward_fields.update(passes_rows=passes("gBv", "gA", 12, ["w = wr[p, j]", "g0 = q0[j] * w", "g1 = q1[j] * w"], "range(n)",
                                             False, [f"gBv[p, {d}, j] += g0 * c0 + g1 * c1"], ("c0 * ", "c1 * ")))
    # the symmetric kernels loop over columns j >= i0 and multiply the mirrors' part by B's rows i0, i1
    # (there A = B M: the driver maps G B to G A)
    sym_fields = dict(forward_fields, rows=rows.replace("for j in range(n):", "for j in range(i0u, nu):"),
                      load_b01=lines("a0_{c} = Bt[p, {c}, i0]", 12) + "\n" + lines("a1_{c} = Bt[p, {c}, i1]", 12),
                      passes_g=passes("gBv", "gA", 12, ["w = wr[p, j]", "g0 = q0[j] * (c0 * w)", "g1 = q1[j] * (c1 * w)"],
                                      "range(i0u, nu)", True, [f"gBv[p, {d}, j] += g0 + g1"], sums="gu"),
                      passes_h=passes("hBv", "hA", 16, ["g0 = q0[j] * inv_k[p, i0, j]", "g1 = q1[j] * inv_k[p, i1, j]"],
                                      "range(i0u, nu)", True, [f"hBv[p, {d}, j] += g0 + g1"], sums="hu"))
    return (
        _HEADER.format(d=d, fastmath="{" + ", ".join(repr(f) for f in sorted(FASTMATH)) + "}",
                       exp_digest=hashlib.sha256(inspect.getsource(exp_inline.py_func).encode()).hexdigest()[:12])
        + "".join(_forward_source(name, rows=rows, **forward_fields) for name in _FORWARD_KERNELS)
        + "".join(_forward_source(name, **sym_fields) for name in _FORWARD_SYM_KERNELS)
        + _BACKWARD.format(name="backward", source="Q", what="Q[p - first] read from a stored block", rows="", pb=" " * 8 + "pb = p - first",
                           q0="Q[pb, i0, j]", q1="Q[pb, i1, j]", **common)
        + _BACKWARD.format(name="backward_q", source="L, Rt, q0, q1", what="formed from L and Rt into q0, q1",
                           rows=rows, pb="", q0="q0[j]", q1="q1[j]", **common)
    )


def cache_dir() -> Path:
    """Where the generated sources (and numba's cache of them) live: ``$HARNESS_KERNEL_CACHE``, else
    ``$XDG_CACHE_HOME/pilco-harness/kernels`` (``~/.cache/...``)."""
    if os.environ.get("HARNESS_KERNEL_CACHE"):
        return Path(os.environ["HARNESS_KERNEL_CACHE"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "pilco-harness" / "kernels"


_modules: dict[tuple[int, int], ModuleType] = {}
_lock = threading.Lock()


def kernels(d: int, pass_columns: int | None = None) -> ModuleType:
    """The compiled kernels (``forward``, ``backward``) for input dimension ``d`` (and the saved-gradient sweeps'
    columns of ``B`` per pass, default :data:`PASS_COLUMNS`: :func:`source`).

    The source is written once per ``d`` under :func:`cache_dir` (named by its hash, so a change of
    the template makes a new file) and imported; numba compiles it at the first call and caches the
    machine code next to it.
    """
    key = (d, PASS_COLUMNS if pass_columns is None else int(pass_columns))
    with _lock:
        module = _modules.get(key)
        if module is not None:
            return module
        text = source(*key)
        digest = hashlib.sha256(text.encode()).hexdigest()[:12]
        folder = cache_dir()
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"qkernel_d{d}_{digest}.py"
        if not path.exists():
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(text)
            os.replace(tmp, path)  # atomic: concurrent processes write the same text
        name = f"_pilco_qkernel_d{d}_{digest}"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        _modules[key] = module
        return module



# ---------------------------------------------------------------------------------------------
# drivers: the arguments and results of moments._contract_forward / _contract_backward
# ---------------------------------------------------------------------------------------------

_pools: dict[int, ThreadPoolExecutor] = {}

#: the fewest entries of ``Q`` (pairs x n x n) one contraction must form before a second thread takes part:
#: below it, handing pairs to a pool thread costs more than it saves. Measured with two threads against one
#: (``benchmarks/ab_objective.py --a kernel=fused --b kernel=fused,threads=2``): cart-pole n = 100 (10 pairs,
#: 0.1 M entries) 0.88x on Zen 1 and 0.86-0.90x on Zen 5; n = 300 (0.9 M) 1.09x and 0.85-1.10x; the double pendulum
#: (21 pairs, n = 400: 3.4 M) and the unicycle (55 pairs, n = 300: 5.0 M) 1.14-1.56x
#: (``results/benchmarks/ab_objective_threads_*.md``)
MIN_PARALLEL_WORK = 500_000


def useful_threads(threads: int, num_pairs: int, n: int, min_work: int = MIN_PARALLEL_WORK) -> int:
    """``threads``, or 1 where a contraction of ``num_pairs`` pairs over ``n`` basis points forms fewer than
    ``min_work`` entries of ``Q`` (:data:`MIN_PARALLEL_WORK`)."""
    return int(threads) if num_pairs * n * n >= min_work else 1


def _run(groups: Sequence[tuple[int, int]], work) -> None:
    """``work(g, start, stop)`` for every group of pairs: inline for one group, else on a pool of
    ``len(groups)`` threads (each with single-threaded torch)."""
    if len(groups) == 1:
        work(0, *groups[0])
        return
    with _lock:
        pool = _pools.get(len(groups))
        if pool is None:
            pool = _pools[len(groups)] = ThreadPoolExecutor(
                len(groups), thread_name_prefix="pilco-contraction", initializer=torch.set_num_threads, initargs=(1,))
    for future in [pool.submit(work, g, s, t) for g, (s, t) in enumerate(groups)]:
        future.result()


@lru_cache(maxsize=64)
def pair_groups(num_pairs: int, num_traced: int, threads: int, num_symmetric: int = 0) -> tuple[tuple[int, int], ...]:
    """At most ``threads`` contiguous ranges covering ``0 .. num_pairs - 1`` with about equal work (a
    pair with a trace term, ``p < num_traced``, counts 1.5: it also reads ``inv_k``; a symmetric one,
    ``p < num_symmetric``, 0.6 of that: the kernels form half its ``Q``; a traced symmetric pair measured
    0.9-1.1 times an ordinary one, ``results/benchmarks/fused_pair_cost.md``). Cached: a rollout asks
    for the same split at every step of both passes (0.1 ms of NumPy each time)."""
    groups = max(1, min(int(threads), num_pairs))
    index = np.arange(num_pairs)
    cost = np.cumsum(np.where(index < num_traced, 1.5, 1.0) * np.where(index < num_symmetric, 0.6, 1.0))
    cuts = [0] + [int(np.searchsorted(cost, cost[-1] * g / groups)) + 1 for g in range(1, groups)] + [num_pairs]
    cuts = sorted(set(min(max(c, 0), num_pairs) for c in cuts))
    return tuple((a, b) for a, b in zip(cuts[:-1], cuts[1:]) if a < b)


def _block_size(block, n: int, itemsize: int) -> int:
    """``block``: pairs per block, or a function ``(n, itemsize) -> pairs``; the same with several
    groups (threads): each group forms its ``Q`` a block at a time, so that it is contracted while in
    cache. Forming a group's whole ``Q`` at once, as before, left a second thread without gain on this
    project's 2-core machine (torch at 1 thread, 2 pair-group threads: 0.96-1.0x the one-thread wall
    time); blocked, 1.12x on the double pendulum and 1.27x on the unicycle
    (``results/benchmarks/threads_objective.md``).
    """
    return max(1, int(block(n, itemsize) if callable(block) else block))


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().numpy()


def exp_bilinear(left: torch.Tensor, right: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``out = exp(left @ right^T)`` as :func:`plugins.pilco.moments._exp_bilinear`, the exponential
    by NumPy: its SIMD exp (AVX-512/AVX2) took 0.7-1.0 G elements/s against torch's 0.45-0.54 on this
    project's machine at the ``(b, 400, 400)`` blocks of the double pendulum, both within 1 ulp of
    libm; the exp was the largest part of J + dJ (``results/benchmarks/objective_gradient_numpy_exp_tasks.md``)."""
    torch.bmm(left, right.mT, out=out)
    q = _numpy(out)
    np.exp(q, out=q)
    return out


def _symmetric_jacobian(j: dict, q_wr: np.ndarray, M: np.ndarray, first: int, last: int, columns: bool = True) -> None:
    """Completes what ``forward_jac_sym`` left in ``j`` for pairs ``first .. last - 1`` (symmetric ``G``):
    ``G B`` and ``G 1`` are their rows' part plus their mirrors' part, and, with ``A_p = B_p M_p``,
    ``G^T A = G B M``, ``G^T 1 = G 1`` and ``Q^T w_l = Q w_r = q_wr`` (without ``columns``, ``G^T A`` is left
    zero and ``Q^T w_l`` is not copied, as ``forward_jac_rows`` does for the other pairs)."""
    d = M.shape[1]
    for g, u, v in (("gA", "gu", "gBv"), ("hA", "hu", "hBv")):
        stop = min(last, j[g].shape[0])
        if first >= stop:
            continue
        s = slice(first, stop)
        gA = j[g][s] + j[v][s, :d].transpose(0, 2, 1)  # (k, n, d)
        gu = j[u][s] + j[v][s, d]
        j[g][s], j[u][s] = gA, gu
        j[v][s, :d] = np.matmul(gA, M[s]).transpose(0, 2, 1) if columns else 0.0
        j[v][s, d] = gu
    if columns:
        j["gwr"][first:last] = q_wr[first:last]


def forward(left, right, w_left, w_right, inv_k, workspace, out=None, threads: int = 1, block=1,
            inline: bool = False, jacobian: dict | None = None, symmetric=None, columns: bool = True,
            min_parallel_work: int = MIN_PARALLEL_WORK, pass_columns: int | None = None):
    """``quad (P,)``, ``trace (E',)``, ``Q w_right (P, n)``; ``Q`` into ``out`` (kept) if given.

    ``threads`` pair groups run side by side where the contraction forms at least ``min_parallel_work``
    entries of ``Q`` (:func:`useful_threads`), else one.

    ``left, right (P, n, d + 2)`` with ``Q_p = exp(left_p right_p^T)``, formed ``block`` pairs at a
    time (a number or a function ``(n, itemsize) -> pairs``) into ``out`` or the workspace's scratch;
    ``inline``: formed two rows at a time inside the compiled loop instead (``kernels(d).forward_q``; no
    ``Q`` is stored, so ``out`` must be ``None``). ``jacobian`` (with ``inline``): a dict that
    receives the gradients of every ``quad_p`` and ``trace_p`` (``kernels(d).forward_jac``), for
    :func:`backward` to scale instead of forming ``Q`` again.

    ``symmetric`` (with ``inline``): ``M (S, d, d)`` for pairs ``0 .. S - 1`` whose ``Q_p`` is symmetric,
    ``w_left[p] = w_right[p]``, ``inv_k[p]`` symmetric and ``left[p, :, :d] = right[p, :, :d] M_p``
    (moment matching's diagonal pairs ``(a, a)``: ``M = 2 T``). Their kernels form only the upper
    triangle of ``Q`` (half the ``exp``), and their ``G^T A`` is ``G B M``, no product of its own.
    ``pass_columns``: the saved-gradient sweeps' columns of ``B`` per pass (:data:`PASS_COLUMNS`).

    ``columns=False`` (with ``jacobian``): the saved gradients without those by basis point of the right
    factor (``G^T A`` and ``Q^T w_l``; ``jacobian["columns"]`` says so), ``kernels(d).forward_jac_rows``:
    for a backward pass that needs ``G^T A`` only summed over the basis points, ``A^T (G 1)``
    (:func:`input_gradients`). :func:`backward` cannot use such a jacobian."""
    p, n = left.shape[0], left.shape[1]
    e = inv_k.shape[0]
    quad, trace, q_wr = np.empty(p), np.empty(e), np.empty((p, n))
    wl, wr, ik = _numpy(w_left), _numpy(w_right), _numpy(inv_k)
    nsym = 0 if symmetric is None or not inline else int(symmetric.shape[0])
    groups = pair_groups(p, e, useful_threads(threads, p, n, min_parallel_work), nsym)
    size = _block_size(block, n, left.element_size())
    if inline:
        M = _numpy(symmetric) if nsym else None
        if out is not None:
            raise ValueError("inline forms Q without storing it: no Q can be kept (out must be None)")
        d = left.shape[2] - 2
        module = kernels(d, pass_columns)
        L, Rt = _numpy(left.contiguous()), _numpy(right.mT.contiguous())
        if jacobian is not None:
            # forward_jac reads A = left[..., :d] and Bt = right[..., :d]^T by index, A[p, i, c] and Bt[p, c, j]
            # with c < d, which are L's and Rt's own entries: no copies (both are only read; the kernels'
            # no-alias promise concerns the arrays they write). The dict keeps just what the backward pass reads
            A, Bt = L, Rt
            jacobian.update(gA=np.empty((p, n, d)), gu=np.empty((p, n)), gBv=np.empty((p, d + 1, n)), gwr=np.empty((p, n)),
                            hA=np.empty((e, n, d)), hu=np.empty((e, n)), hBv=np.empty((e, d + 1, n)), columns=bool(columns))
            j = jacobian
    elif jacobian is not None:
        raise ValueError("jacobian needs inline (the fused kernel)")

    def work(g: int, start: int, stop: int) -> None:
        mid = min(max(start, nsym), stop)  # symmetric pairs start .. mid - 1, the others mid .. stop - 1
        if inline and jacobian is None:
            if start < mid:
                module.forward_q_sym(L, Rt, np.empty(n), np.empty(n), start, mid, wl, wr, ik, quad, trace, q_wr)
            module.forward_q(L, Rt, np.empty(n), np.empty(n), mid, stop, wl, wr, ik, quad, trace, q_wr)
            return
        if inline:
            if start < mid:
                module.forward_jac_sym(L, Rt, np.empty(n), np.empty(n), start, mid, Bt, wl, wr, ik, quad, trace, q_wr,
                                       j["gA"], j["gu"], j["gBv"], j["hA"], j["hu"], j["hBv"])
                _symmetric_jacobian(j, q_wr, M, start, mid, columns)
            if columns:
                module.forward_jac(L, Rt, np.empty(n), np.empty(n), mid, stop, A, Bt, wl, wr, ik, quad, trace, q_wr,
                                   j["gA"], j["gu"], j["gBv"], j["gwr"], j["hA"], j["hu"], j["hBv"])
            else:
                module.forward_jac_rows(L, Rt, np.empty(n), np.empty(n), mid, stop, Bt, wl, wr, ik, quad, trace, q_wr,
                                        j["gA"], j["gBv"], j["hA"], j["hu"], j["hBv"])
                np.multiply(wl[mid:stop], q_wr[mid:stop], out=j["gu"][mid:stop])  # G 1 = w_l * (Q w_r)
            return
        for s in range(start, stop, size):
            t = min(s + size, stop)
            Q = out[s:t] if out is not None else workspace.buffer(f"Q{g}", (t - s, n, n), left.dtype)
            exp_bilinear(left[s:t], right[s:t], Q)
            reduce_rows(_numpy(Q), s, wl, wr, ik, quad, trace, q_wr)

    _run(groups, work)
    return torch.from_numpy(quad), torch.from_numpy(trace), torch.from_numpy(q_wr)


def backward(left, right, w_left, w_right, inv_k, q_wr, g_quad, g_trace, workspace, needs, Q=None,
             threads: int = 1, block=1, inline: bool = False, jacobian: dict | None = None,
             min_parallel_work: int = MIN_PARALLEL_WORK):
    """Gradients wrt ``(left, right, w_left, w_right, inv_k)`` as ``moments._contract_backward``
    returns them (``None`` where not needed; the constant columns of ``left``/``right`` get 0).
    ``threads`` and ``min_parallel_work`` as in :func:`forward`.

    ``Q``: the forward pass's kept ``Q (P, n, n)``, or ``None`` to recompute it: ``block`` pairs at a
    time into the workspace's scratch or, with ``inline``, two rows at a time inside the compiled loop
    (``kernels(d).backward_q``). ``jacobian``: what :func:`forward` filled in; then no ``Q`` is formed
    at all, the gradients are ``g_quad`` and ``g_trace`` times the pairs' own."""
    p, n, k = left.shape
    d = k - 2
    e = inv_k.shape[0] if g_trace is not None else 0
    wl, wr, ik = _numpy(w_left), _numpy(w_right), _numpy(inv_k[:e])
    gq = _numpy(g_quad) if g_quad is not None else np.zeros(p)
    gt = _numpy(g_trace[:e]) if e > 0 else np.zeros(0)
    need_wr = bool(needs[3])
    if jacobian is not None and not jacobian.get("columns", True):
        raise ValueError("this jacobian was saved without the gradients by basis point (forward(columns=False)): "
                         "backward needs forward's default, columns=True, or no jacobian")
    if jacobian is not None and Q is None:
        # quad_p and trace_p are scalars: their gradients scale (g_quad, g_trace) and add
        j = jacobian
        gA, gu, gBv = gq[:, None, None] * j["gA"], gq[:, None] * j["gu"], gq[:, None, None] * j["gBv"]
        gA[:e] += gt[:, None, None] * j["hA"][:e]
        gu[:e] += gt[:, None] * j["hu"][:e]
        gBv[:e] += gt[:, None, None] * j["hBv"][:e]
        gwr = gq[:, None] * j["gwr"]
    else:
        module = kernels(d)
        A = np.ascontiguousarray(_numpy(left)[..., :d])  # numba's loops over strided arrays are ~3x slower
        Bt = _numpy(right[..., :d].transpose(1, 2).contiguous())
        gA, gu, gBv, gwr = np.empty((p, n, d)), np.empty((p, n)), np.empty((p, d + 1, n)), np.empty((p, n))
        groups = pair_groups(p, e, useful_threads(threads, p, n, min_parallel_work))
        size = _block_size(block, n, left.element_size())
        if inline and Q is None:
            L, Rt = _numpy(left.contiguous()), _numpy(right.mT.contiguous())

        def work(g: int, start: int, stop: int) -> None:
            args = (A, Bt, wl, wr, ik, gq, gt, need_wr, gA, gu, gBv, gwr)
            if Q is not None:
                module.backward(_numpy(Q[start:stop]), start, stop, *args)
            elif inline:
                module.backward_q(L, Rt, np.empty(n), np.empty(n), start, stop, *args)
            else:
                for s in range(start, stop, size):
                    t = min(s + size, stop)
                    Qb = workspace.buffer(f"Q{g}", (t - s, n, n), left.dtype)
                    exp_bilinear(left[s:t], right[s:t], Qb)
                    module.backward(_numpy(Qb), s, t, *args)

        _run(groups, work)
    grad_left = torch.zeros(p, n, k, dtype=left.dtype)
    grad_left[..., :d] = torch.from_numpy(gA)
    grad_left[..., d] = torch.from_numpy(gu)
    grad_right = torch.zeros(p, n, k, dtype=left.dtype)
    grad_right[..., :d] = torch.from_numpy(gBv[:, :d]).mT
    grad_right[..., d + 1] = torch.from_numpy(gBv[:, d])
    grad_wl = torch.as_tensor(q_wr) * torch.from_numpy(gq)[:, None] if needs[2] else None
    grad_wr = torch.from_numpy(gwr) if need_wr else None
    grad_inv = None
    if e > 0 and needs[4]:  # dJ/d inv_k = g_trace * Q on the traced pairs (posteriors with gradients only)
        grad_inv = torch.empty(inv_k.shape, dtype=left.dtype)
        for a in range(e):
            Qa = Q[a] if Q is not None else exp_bilinear(left[a : a + 1], right[a : a + 1], torch.empty(1, n, n, dtype=left.dtype))[0]
            torch.mul(Qa, g_trace[a], out=grad_inv[a])
    return grad_left, grad_right, grad_wl, grad_wr, grad_inv
