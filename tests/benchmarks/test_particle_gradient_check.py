"""benchmarks/particle_gradient_check.py: its directional derivatives are those of the particle estimate."""

from __future__ import annotations

import re

import pytest
import torch

from benchmarks.mc_pilco_step import particle_objectives
from benchmarks.particle_gradient_check import STEPS, directional_derivatives, main


def test_directional_derivative_is_the_gradient_along_the_direction_and_differences_converge_to_it() -> None:
    """A 3-step horizon from the spread controller (smooth there): every difference agrees with autograd,
    and autograd's value is the gradient's inner product with the direction, computed here separately."""
    objective = next(iter(particle_objectives("cartpole", {}, 60, (20,), 16, learner_options={"centres": "spread"},
                                              full=False)[0].values()))
    objective.horizon = 3
    params = objective.parameters()
    direction = [torch.full_like(p, 1.0 / sum(q.numel() for q in params) ** 0.5) for p in params]
    exact, differences = directional_derivatives(objective, direction, seed=5)
    draws = objective.draw(torch.Generator().manual_seed(5), 0.0)
    grads = torch.autograd.grad(objective.rollout_drawn(draws, 0.0)[1].sum(), params)
    assert exact == pytest.approx(float(sum(g.sum() for g in grads)) / sum(q.numel() for q in params) ** 0.5, rel=1e-12)
    assert len(differences) == len(STEPS)
    for difference in differences[1:]:
        assert difference == pytest.approx(exact, rel=1e-4, abs=1e-9)


def test_report_has_a_row_per_initialisation_and_horizon_and_a_search_each(tmp_path) -> None:
    out = tmp_path / "check.md"
    main(["--n", "60", "--basis", "20", "--particles", "16", "--horizons", "2", "3", "--steps", "4", "--out", str(out)])
    text = out.read_text()
    rows = [line for line in text.splitlines() if re.match(r"\| (initial|spread) \| [0-9.e+]+ \| [23] \|", line)]
    assert len(rows) == 4
    searches = [line for line in text.splitlines() if re.match(r"\| (initial|spread) \| 40 \| ", line)]
    assert len(searches) == 2
