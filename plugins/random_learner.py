"""The ``random`` learner: uniform random controls, a floor every learner must beat."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from harness.interaction import Interaction
from harness.learner import Learner, Policy
from harness.options import Option


class UniformRandomPolicy:
    """u ~ U[scale * action_low, scale * action_high], independently at every step.

    Picklable (its generator is part of its state), so it can be saved like any policy.
    """

    def __init__(self, low: np.ndarray, high: np.ndarray, seed: int) -> None:
        self.low = np.asarray(low, dtype=np.float64)
        self.high = np.asarray(high, dtype=np.float64)
        self.rng = np.random.default_rng(seed)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self.rng.uniform(self.low, self.high)


class RandomLearner(Learner):
    """Applies uniform random controls for one episode per trial and hands over the random policy.

    This is the reference implementation's initial exploration (``rollout`` without a policy:
    ``u = maxU * (2 rand - 1)``), run forever; it solves nothing, which is the point.
    """

    name = "random"
    description = "uniform random controls in the bounds (a baseline that learns nothing)"
    options = (Option("scale", float, 1.0, "fraction of the control bounds to sample from", low=0.0, high=1.0),)
    default_max_trials = 10
    supports_resume = True

    def learn(self, interaction: Interaction) -> Iterator[Policy]:
        scale = self.options["scale"]
        self._policy = UniformRandomPolicy(scale * self.spec.action_low, scale * self.spec.action_high, self.seed)
        if self._resume_state is not None:
            self._policy.rng.bit_generator.state = self._resume_state["rng"]
        while True:
            interaction.rollout(self._policy)
            yield self._policy

    def state_dict(self) -> dict:
        return {"rng": self._policy.rng.bit_generator.state}
