"""The SIMD width of numba-compiled code: the widest the CPU has, decided once per process.

numba compiles for the host CPU, but LLVM's tuning for Intel's AVX-512 server CPUs (Skylake-SP to
Emerald Rapids: the ``prefer-256-bit`` tuning flag) keeps its loop vectoriser at 256-bit vectors, a
guard against the clock drop of early AVX-512 chips. The PILCO kernels (:mod:`plugins.pilco.fused`)
are long loops of multiply-adds and an inlined ``exp`` over the basis points, where 512-bit vectors
measured J + dJ 1.21-1.22x faster on an Emerald Rapids Xeon at the double pendulum's and the unicycle's
sizes, but 0.9x at cart-pole's n = 100 (probably its short rows: more of each is left to the loops'
remainders; ``results/benchmarks/objective_gradient_vector_width*.md``). :func:`configure` removes the preference
for numba's CPU target, which every numba function of the process shares; it must run before the
first function is compiled (``plugins.pilco.fused`` and the unicycle's simulator call it before theirs).

Results change only where LLVM may reorder arithmetic (the kernels' fast-math sums: J to ~1e-11
relative, within the 1-2 ulp change of theta's own ~2e-9); code without fast-math (the unicycle's
simulator) computes the same bits. numba's on-disk cache is keyed by the target's features, so both
widths' machine code can sit side by side.

``HARNESS_VECTOR_WIDTH=256`` keeps LLVM's own choice (to reproduce older numbers); numba's own
``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES``, if set, are left alone.
"""

from __future__ import annotations

import os

#: environment variable: ``256`` keeps LLVM's tuning as it is; unset, empty or ``widest``: the CPU's widest
ENV = "HARNESS_VECTOR_WIDTH"

#: LLVM's x86 tuning flag that limits the loop vectoriser to 256-bit vectors on AVX-512 CPUs
_PREFER_256 = "prefer-256-bit"

_state: str | None = None


def requested() -> str:
    """``"widest"`` or ``"256"`` from :data:`ENV`; ``ValueError`` (one line, with the fix) for anything else."""
    value = os.environ.get(ENV, "").strip().lower()
    if value in ("", "widest", "512"):
        return "widest"
    if value == "256":
        return "256"
    raise ValueError(f"{ENV}={os.environ[ENV]!r} is not a vector width the harness knows: use 256 (LLVM's default "
                     f"tuning) or unset it (the CPU's widest)")


def host_has_avx512() -> bool:
    """Whether the CPU numba compiles for has AVX-512 (``+avx512f`` in its host features), whatever the vector
    width chosen: AVX-512 also doubles the vector registers to 32 (:data:`plugins.pilco.fused.PASS_COLUMNS`)."""
    from numba.core.codegen import get_host_cpu_features

    return "+avx512f" in get_host_cpu_features().split(",")  # what numba would use: "+avx512f,-xop,..."


def configure() -> str:
    """Lets numba's CPU target use 512-bit vectors where the CPU has AVX-512; idempotent.

    Returns what holds for this process: ``"512"`` (preference removed), ``"default"`` (no AVX-512,
    ``HARNESS_VECTOR_WIDTH=256``, or the user set numba's own CPU variables) or ``"too late"`` (numba
    had compiled a function before the first call: its target keeps LLVM's tuning; results are
    still right, only slower on such CPUs). Raises ``ValueError`` for a bad :data:`ENV`.
    """
    global _state
    if _state is not None:
        return _state
    want = requested()
    from numba.core import config, registry

    if want == "256" or config.CPU_NAME is not None or config.CPU_FEATURES is not None:
        _state = "default"
        return _state
    from numba.core.codegen import get_host_cpu_features

    if not host_has_avx512():
        _state = "default"
    elif "_toplevel_target_context" in vars(registry.cpu_target):  # a numba function exists already
        _state = "too late"
    else:
        config.CPU_FEATURES = f"{get_host_cpu_features()},-{_PREFER_256}"
        _state = "512"
    return _state
