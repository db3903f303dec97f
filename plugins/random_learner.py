"""The ``random`` learner: uniform random controls, a floor every learner must beat."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from harness.interaction import Interaction
from harness.learner import Learner, Policy
from harness.options import Option
from harness.task import TaskSpec


class UniformRandomPolicy:
    """u ~ U[scale * action_low, scale * action_high], independently at every step.

    Its generator is part of its state (:meth:`RandomLearner.policy_state`): a saved policy draws
    what the live one would have drawn next.
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

    @classmethod
    def policy_state(cls, policy: Policy) -> dict[str, Any]:
        """Bounds ``low``, ``high`` ``(F,)`` and the generator's state (a PCG64 state dict)."""
        if not isinstance(policy, UniformRandomPolicy):
            raise TypeError(f"a random learner's policy is a UniformRandomPolicy, not a {type(policy).__name__}")
        return {"low": policy.low.copy(), "high": policy.high.copy(), "rng": policy.rng.bit_generator.state}

    @classmethod
    def policy_from_state(cls, state: dict[str, Any], spec: TaskSpec) -> UniformRandomPolicy:
        low, high = np.asarray(state["low"], dtype=np.float64), np.asarray(state["high"], dtype=np.float64)
        if low.shape != (spec.action_dim,) or high.shape != (spec.action_dim,):
            raise ValueError(f"bounds of shape {low.shape} for {spec.action_dim} controls")
        policy = UniformRandomPolicy(low, high, seed=0)
        policy.rng.bit_generator.state = state["rng"]
        return policy
