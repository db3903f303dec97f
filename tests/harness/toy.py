"""A tiny task and learners for testing the harness itself (no physics, fast).

``toy-reach``: x_{t+1} = x_t + u dt with x, u scalar, dt = 0.5 s, horizon 8; start N(1, 0.01);
success when |x| < 0.1 at the end. The proportional controller u = -x / (2 dt) solves it.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from harness.learner import Learner
from harness.options import Option
from harness.progress import SilentProgress
from harness.task import Episode, SaturatingCost, Task, TaskSpec, check_action


class ToyReachEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, spec: TaskSpec) -> None:
        self.spec_ = spec
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float64)
        self.action_space = gym.spaces.Box(spec.action_low, spec.action_high, (1,), np.float64)
        self.x = np.zeros(1)
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = self.np_random.normal(self.spec_.init_mean, np.sqrt(np.diag(self.spec_.init_cov)))
        self.t = 0
        return self.x.copy(), {"state": self.x.copy()}

    def step(self, action):
        u, clipped = check_action(action, self.spec_)
        self.x = self.x + u * self.spec_.dt
        self.t += 1
        reward = -float(self.spec_.cost(self.x))
        return self.x.copy(), reward, False, self.t >= self.spec_.horizon, {"state": self.x.copy(), "action_clipped": clipped}


class ToyReach(Task):
    name = "toy-reach"
    description = "1-D reach (harness self-test)"
    options = (Option("horizon", int, 8, "steps per episode", low=1),)

    @property
    def spec(self) -> TaskSpec:
        cost = SaturatingCost(np.zeros((0, 1)), np.eye(1), np.zeros(1), 0.5)
        return TaskSpec(
            name=self.name, state_names=("x [m]",), action_names=("u [m/s]",), dt=0.5,
            horizon=self.options["horizon"], action_low=[-2.0], action_high=[2.0],
            init_mean=[1.0], init_cov=[[0.01]], angle_indices=(), cost=cost,
            measurement_noise_std=[0.0], options=dict(self.options),
        )

    def make_env(self, render_mode=None):
        return ToyReachEnv(self.spec)

    def success(self, episode: Episode) -> bool:
        return bool(abs(episode.states[-1, 0]) < 0.1)


class Proportional:
    def __init__(self, gain: float) -> None:
        self.gain = gain

    def __call__(self, obs):
        return np.array([-self.gain * obs[0]])


class BadThenGood(Learner):
    """Hands over a useless policy ``bad_trials`` times (one episode each), then the solution."""

    name = "bad-then-good"
    description = "test learner"
    options = (Option("bad_trials", int, 2, "useless hand-overs first", low=0),)

    @classmethod
    def policy_state(cls, policy):
        return {"gain": policy.gain}

    @classmethod
    def policy_from_state(cls, state, spec):
        return Proportional(float(state["gain"]))

    def learn(self, interaction):
        for k in range(self.options["bad_trials"]):
            self.report_status(f"useless rollout {k + 1}")
            interaction.rollout(Proportional(0.0))
            self.metrics = {"J_after": 1.0}
            yield Proportional(0.0)
        while True:
            interaction.rollout(Proportional(1.0))
            yield Proportional(1.0)


class Greedy(Learner):
    """Steps without end, never hands over (to test the budget)."""

    name = "greedy"
    description = "test learner"

    def learn(self, interaction):
        while True:
            interaction.rollout(Proportional(0.0))
        yield  # pragma: no cover


class NaNLearner(Learner):
    name = "nan"
    description = "test learner"

    def learn(self, interaction):
        yield lambda obs: np.array([np.nan])


class Crashing(Learner):
    name = "crashing"
    description = "test learner"

    def learn(self, interaction):
        interaction.rollout(Proportional(0.0))
        yield Proportional(0.0)
        raise RuntimeError("boom at trial 2")


class RecordingProgress(SilentProgress):
    """What a run shows (its learner's statuses and the hand-overs), in order, in ``events``."""

    def __init__(self) -> None:
        self.events: list[str] = []

    def status(self, text: str) -> None:
        self.events.append(text)

    def update(self, record, completed: float) -> None:
        self.events.append(f"hand-over {record['trial']}")
