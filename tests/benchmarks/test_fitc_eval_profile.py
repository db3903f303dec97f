"""benchmarks/fitc_eval_profile.py: the counted multiply-adds agree with torch's own count, and the report is written."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from benchmarks.fitc_eval_profile import main, multiply_adds
from plugins.pilco.sparse import fitc_nll_and_pseudo_gradient


def _problem(num_outputs=2, n=50, m=12, d=3):
    g = torch.Generator().manual_seed(0)
    r = lambda *shape: torch.randn(*shape, dtype=torch.float64, generator=g)  # noqa: E731
    return (r(n, d), r(n, num_outputs), r(m, d), torch.zeros(num_outputs, d, dtype=torch.float64),
            torch.zeros(num_outputs, dtype=torch.float64), torch.full((num_outputs,), -2.0, dtype=torch.float64))


def test_products_match_torch_flop_count():
    """torch's FlopCounterMode counts batched products exactly (2 flops per multiply-add; not the solves):
    its baddbmm calls are the two M x n x M products and K_mn's cross term (n M d)."""
    for num_outputs, n, m, d in [(2, 50, 12, 3), (3, 37, 20, 5), (1, 64, 9, 7)]:
        with FlopCounterMode(display=False) as counter:
            fitc_nll_and_pseudo_gradient(*_problem(num_outputs, n, m, d))
        baddbmm = {str(k): v for k, v in counter.get_flop_counts()["Global"].items()}["aten.baddbmm"]
        assert baddbmm == 2 * (multiply_adds(num_outputs, n, m, d)["M x n x M products"] + num_outputs * n * m * d)


def test_report(tmp_path):
    x, y, z, log_ell, log_alpha, log_sigma = (t.numpy() for t in _problem(2, 60, 15, 3))
    np.savez(tmp_path / "gp.npz", x=x, y=y, pseudo_inputs=z, log_ell=log_ell, log_alpha=log_alpha, log_sigma=log_sigma)
    main(["--data", str(tmp_path / "gp.npz"), "--repeats", "2", "--out", str(tmp_path / "out.md")])
    text = (tmp_path / "out.md").read_text()
    assert "n = 60 transitions, M = 15 pseudo-inputs" in text and "aten::linalg_solve_triangular" in text
