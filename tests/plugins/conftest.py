"""Fixtures shared by the learner plugins' tests."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def fit_inputs(monkeypatch) -> list[np.ndarray]:
    """The training inputs of every ``GPModel.fit`` a run makes from now on, in order (the learners import
    ``GPModel`` at first use, so the recording class replaces it for them)."""
    import plugins.pilco.gp as gp_module

    fits: list[np.ndarray] = []

    class Recording(gp_module.GPModel):
        def fit(self, inputs, targets, **kwargs):
            fits.append(np.array(inputs, dtype=float))
            return super().fit(inputs, targets, **kwargs)

    monkeypatch.setattr(gp_module, "GPModel", Recording)
    return fits
