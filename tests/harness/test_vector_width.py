"""harness.vector_width: numba's CPU target without LLVM's 256-bit preference where the CPU has AVX-512.

The setting is per process (numba's target is created once), so each case runs in a fresh
interpreter. The J + dJ check compares the two widths' results against each other and against the
torch reference path.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from harness import vector_width

pytest.importorskip("numba")

ROOT = Path(__file__).resolve().parents[2]


def _python(code: str, **env: str) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in (vector_width.ENV, "NUMBA_CPU_FEATURES", "NUMBA_CPU_NAME")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                          env={**clean, "OMP_NUM_THREADS": "1", **env}, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip().splitlines()[-1]


def _host_features() -> str:
    """The feature string numba builds its target from (LLVM's host query: it creates no numba target here)."""
    from numba.core.codegen import get_host_cpu_features

    return get_host_cpu_features()


def _host_has_avx512() -> bool:
    return "+avx512f" in _host_features().split(",")


STATE = ("import json, plugins.pilco.fused as f; from numba.core import registry; "
         "tm = registry.cpu_target.target_context.codegen()._tm_features; "
         "print(json.dumps([f.VECTOR_WIDTH, tm.endswith(',-prefer-256-bit')]))")


def test_requested_reads_the_variable_and_names_the_fix_for_a_bad_value(monkeypatch):
    for value, want in (("", "widest"), ("512", "widest"), ("widest", "widest"), ("256", "256"), (" 256 ", "256")):
        monkeypatch.setenv(vector_width.ENV, value)
        assert vector_width.requested() == want
    monkeypatch.delenv(vector_width.ENV)
    assert vector_width.requested() == "widest"
    monkeypatch.setenv(vector_width.ENV, "128")
    with pytest.raises(ValueError, match=r"HARNESS_VECTOR_WIDTH='128' .* use 256 .* unset it"):
        vector_width.requested()


def test_the_kernels_module_sets_the_target_before_numba_compiles_anything():
    width, dropped = json.loads(_python(STATE))
    if _host_has_avx512():
        assert (width, dropped) == ("512", True)
    else:
        assert (width, dropped) == ("default", False)


def test_256_and_numbas_own_variables_keep_llvms_tuning():
    assert json.loads(_python(STATE, HARNESS_VECTOR_WIDTH="256")) == ["default", False]
    assert json.loads(_python(STATE, NUMBA_CPU_FEATURES=_host_features())) == ["default", False]


def test_too_late_when_numba_compiled_a_function_first():
    code = ("import json, numba; numba.njit(lambda x: x + 1)(1); from harness.vector_width import configure; "
            "from numba.core import registry; tm = registry.cpu_target.target_context.codegen()._tm_features; "
            "print(json.dumps([configure(), tm.endswith(',-prefer-256-bit')]))")
    want = "too late" if _host_has_avx512() else "default"
    assert json.loads(_python(code)) == [want, False]


OBJECTIVE = """
import json, sys, numpy as np, torch
torch.set_num_threads(1)
sys.path.insert(0, '.')
from benchmarks.bench_objective import dynamics_posterior, make_objective
from plugins.pilco.moments import MomentMatchingGP
obj = make_objective(dynamics_posterior(60, None))
obj.dynamics = MomentMatchingGP(obj.posterior, kernel='{kernel}')
J, g = obj(obj.get_flat())
print(json.dumps([float(J), np.asarray(g).tolist()]))
"""


def test_both_widths_agree_with_each_other_and_the_torch_reference():
    import numpy as np

    wide = json.loads(_python(OBJECTIVE.format(kernel="fused")))
    narrow = json.loads(_python(OBJECTIVE.format(kernel="fused"), HARNESS_VECTOR_WIDTH="256"))
    reference = json.loads(_python(OBJECTIVE.format(kernel="torch")))
    for J, g in (wide, narrow):
        assert abs(J - reference[0]) <= 1e-10 * abs(reference[0])
        assert np.linalg.norm(np.subtract(g, reference[1])) <= 1e-7 * np.linalg.norm(reference[1])
