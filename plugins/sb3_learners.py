"""Model-free baselines: the ``sac`` and ``ppo`` learners, wrapping stable-baselines3 (MlpPolicy, CPU).

Both act **only** through the harness's :class:`~harness.interaction.Interaction`: its
``as_env()`` view is the environment SB3 trains on, so every step SB3 takes (random warm-up
included) is counted and converted to seconds of system time exactly like PILCO's. What the
networks see and emit:

* observations: the task's observation with every angle ``spec.angle_indices`` replaced by its
  ``sin`` and ``cos`` (:func:`angle_features`), as the GP sees them;
* actions: in ``[-1, 1]`` per dimension (SB3's advice for Gaussian / squashed policies), mapped
  affinely to ``[action_low, action_high]`` (:func:`to_bounds`);
* rewards: ``-cost``, and where an episode terminates early (the unicycle fell) the terminating
  step also carries the cost the episode would have gone on paying in its absorbing region up to
  the horizon (:class:`HeldCostAtTermination`), so that falling sooner is not cheaper for the agent
  than for the evaluation (:meth:`~harness.task.Episode.horizon_cost`).

Hand-over: ``model.learn(K, reset_num_timesteps=False)`` in a loop, ``K = eval_every_steps``
counted steps per hand-over (SAC: 5 episodes by default; it trains once per episode, so each
chunk is whole episodes, at least ``K`` steps; PPO: whole updates of ``n_steps``, by default a
whole number of episodes), then the deterministic policy (:class:`SB3Policy`, the mean action)
is yielded to the harness, which evaluates it on its own, uncounted environment. The yielded policy
holds the live model: it is the policy *at* the hand-over and keeps learning afterwards, which is
what the harness needs (it evaluates and saves it before asking for the next one).

When the interaction's budget is used up, :class:`~harness.errors.BudgetExhaustedError` raised
inside SB3's ``env.step`` propagates out of :meth:`learn`, and the runner ends the run as
unsolved (``stop_reason == "budget"``), with the budget as a lower bound.

Hyperparameters: named presets per task (:data:`SAC_PRESETS`, :data:`PPO_PRESETS`, keyed by
``spec.name`` with a ``"default"`` fallback), each value overridable with ``--set``; the resolved
values are attached to the run as ``sb3_hyperparameters.json`` at the first hand-over.
stable-baselines3 and torch are imported inside :meth:`SB3Learner.learn`, so ``harness list``
stays fast.

Resume: both are checkpointed at a hand-over on an episode boundary (SAC always; PPO unless an
early-terminated episode puts its rollout's end inside an episode) at most every 5 minutes of wall
time, and when stopped with ``kill -USR1``; they continue exactly as the uninterrupted run
(:meth:`SB3Learner.state_dict`; the store keeps the two newest checkpoints).
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import tempfile
import time
from abc import abstractmethod
from collections import deque
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from harness.errors import OptionError
from harness.interaction import Interaction
from harness.learner import Learner, Policy
from harness.options import Option
from harness.task import TaskSpec

# ---------------------------------------------------------------------------------------------
# observation and action maps (pure functions)
# ---------------------------------------------------------------------------------------------


def angle_features(observation: np.ndarray, angle_indices: Sequence[int]) -> np.ndarray:
    """``(..., D)`` observation -> ``(..., D + K)`` features for the networks.

    The ``K = len(angle_indices)`` angle entries (radians) are removed and ``sin`` of them, then
    ``cos`` of them, are appended: ``[x_non_angles, sin(x_angles), cos(x_angles)]``.
    With no angles the observation is returned unchanged (as a float64 copy).
    """
    x = np.asarray(observation, dtype=np.float64)
    idx = list(angle_indices)
    if not idx:
        return x.copy()
    keep = [i for i in range(x.shape[-1]) if i not in set(idx)]
    angles = x[..., idx]
    return np.concatenate([x[..., keep], np.sin(angles), np.cos(angles)], axis=-1)


def feature_dim(state_dim: int, angle_indices: Sequence[int]) -> int:
    """Length of :func:`angle_features` for a ``state_dim`` observation: ``D + K``."""
    return int(state_dim) + len(tuple(angle_indices))


def to_bounds(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Map a normalised action ``a in [-1, 1]^F`` to ``low + (a + 1) (high - low) / 2`` (control units).

    ``a`` is clipped to ``[-1, 1]`` first, so the result always lies in ``[low, high]``.
    """
    a = np.clip(np.asarray(action, dtype=np.float64).reshape(np.shape(low)), -1.0, 1.0)
    low = np.asarray(low, dtype=np.float64)
    high = np.asarray(high, dtype=np.float64)
    return low + (a + 1.0) * (high - low) / 2.0


def from_bounds(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_bounds` on ``[low, high]``: ``2 (u - low) / (high - low) - 1``."""
    u = np.asarray(action, dtype=np.float64)
    low = np.asarray(low, dtype=np.float64)
    high = np.asarray(high, dtype=np.float64)
    return 2.0 * (u - low) / (high - low) - 1.0


def feature_space(dim: int) -> gym.spaces.Box:
    """What the networks see: an unbounded float32 ``Box`` of ``dim`` features."""
    return gym.spaces.Box(-np.inf, np.inf, shape=(int(dim),), dtype=np.float32)


def normalised_action_space(shape: tuple[int, ...]) -> gym.spaces.Box:
    """What the networks emit: a float32 ``Box`` ``[-1, 1]^shape``."""
    return gym.spaces.Box(-1.0, 1.0, shape=tuple(shape), dtype=np.float32)


class AngleFeatures(gym.ObservationWrapper):
    """Observations -> :func:`angle_features` (float32, unbounded ``Box`` of ``D + K`` entries)."""

    def __init__(self, env: gym.Env, angle_indices: Sequence[int]) -> None:
        super().__init__(env)
        self.angle_indices = tuple(int(i) for i in angle_indices)
        self.observation_space = feature_space(feature_dim(env.observation_space.shape[0], self.angle_indices))

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return angle_features(observation, self.angle_indices).astype(np.float32)


class NormalisedActions(gym.ActionWrapper):
    """The agent acts in ``[-1, 1]^F``; the wrapped env receives :func:`to_bounds` of it."""

    def __init__(self, env: gym.Env, low: np.ndarray, high: np.ndarray) -> None:
        super().__init__(env)
        self.low = np.asarray(low, dtype=np.float64)
        self.high = np.asarray(high, dtype=np.float64)
        self.action_space = normalised_action_space(self.low.shape)

    def action(self, action: np.ndarray) -> np.ndarray:
        return to_bounds(action, self.low, self.high)


class HeldCostAtTermination(gym.Wrapper):
    """An early-terminated episode's held cost, on its terminating step's reward.

    A task whose episode terminates before the horizon (the unicycle fell) leaves a region that is
    absorbing: the system would stay there, paying its last cost ``c_T`` at every step up to the
    horizon ``H``, and the harness scores the episode that way (:meth:`~harness.task.Episode.horizon_cost`).
    Ended early without that, the agent's return would be the cost of the ``T`` steps taken only,
    so the sooner it fell the less it would pay (SAC and PPO then learn to fall at once). Here the
    terminating step's reward is ``-c_T (1 + gamma + ... + gamma^(H - T))``: the agent's discounted
    return equals that of the episode continued in the absorbing region to the horizon (with
    ``gamma = 1``: minus the evaluation's ``horizon_cost``). Episodes that reach the horizon
    (truncated) are unchanged. Only the agent's view changes; the interaction records the true costs.
    """

    def __init__(self, env: gym.Env, horizon: int, gamma: float) -> None:
        super().__init__(env)
        self.horizon = int(horizon)
        self.gamma = float(gamma)
        self._steps = 0

    def reset(self, **kwargs):
        self._steps = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._steps += 1
        if terminated:
            missing = max(self.horizon - self._steps, 0)
            weight = missing if self.gamma == 1.0 else self.gamma * (1.0 - self.gamma ** missing) / (1.0 - self.gamma)
            reward = float(reward) * (1.0 + weight)
        return obs, reward, terminated, truncated, info


def make_agent_env(env: gym.Env, spec: TaskSpec, gamma: float = 1.0) -> gym.Env:
    """``env`` (the interaction's view) as the agent sees it: sin/cos features, actions in [-1, 1],
    an early termination's held cost discounted with the agent's ``gamma`` (:class:`HeldCostAtTermination`)."""
    held = HeldCostAtTermination(env, spec.horizon, gamma)
    return AngleFeatures(NormalisedActions(held, spec.action_low, spec.action_high), spec.angle_indices)


class SB3Policy:
    """The deterministic policy of an SB3 policy network: observation ``(D,)`` -> action ``(F,)`` in control units.

    ``u = to_bounds(network.predict(angle_features(x), deterministic=True))``, ``network`` an SB3
    ``BasePolicy`` (a model's ``model.policy``, which ``model.predict`` calls: same actions).
    """

    def __init__(self, network: Any, spec: TaskSpec) -> None:
        self.network = network
        self.angle_indices = tuple(spec.angle_indices)
        self.low = np.asarray(spec.action_low, dtype=np.float64)
        self.high = np.asarray(spec.action_high, dtype=np.float64)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        features = angle_features(observation, self.angle_indices).astype(np.float32)
        action, _ = self.network.predict(features, deterministic=True)
        return to_bounds(action, self.low, self.high)


# ---------------------------------------------------------------------------------------------
# hyperparameter presets
# ---------------------------------------------------------------------------------------------

#: SAC presets. Base: rl-baselines3-zoo ``sac.yml`` "Pendulum-v1" (the zoo's swing-up task with a
#: short, fixed horizon): SB3 defaults (256x256 nets, batch 256, tau 0.005, gamma 0.99, learning
#: starts 100, ``ent_coef="auto"``) with ``learning_rate=1e-3``. One deviation everywhere:
#: training once per episode with as many gradient steps as the episode had steps
#: (``train_freq=0`` here = SB3's ``(1, "episode")``, ``gradient_steps=-1``; the zoo's
#: "donkey" and "NeckEnvRelative" presets do the same). The ratio of gradient steps to env steps
#: stays 1, the policy is fixed within an episode, the loop is faster (measured in
#: results/benchmarks/sb3_throughput.md), and every hand-over falls on an episode boundary.
#: The zoo's closer match, "InvertedPendulumSwingupBulletEnv-v0", waits 10^4 steps (10^3 s of
#: cart-pole) before learning, which would dominate a data-efficiency comparison; not used.
#: ``unicycle`` / ``double-pendulum`` / ``dmc-cartpole`` have no comparable zoo task: same settings.
SAC_PRESETS: dict[str, dict[str, Any]] = {
    "default": {
        "learning_rate": 1e-3,
        "batch_size": 256,
        "buffer_size": 1_000_000,
        "learning_starts": 100,
        "train_freq": 0,
        "gradient_steps": -1,
        "gamma": 0.99,
        "tau": 0.005,
        "ent_coef": "auto",
        "net_width": 256,
        "net_layers": 2,
    },
    "cartpole": {},
    "dmc-cartpole": {},
    "double-pendulum": {},
    "unicycle": {},
}

#: PPO presets. Base: rl-baselines3-zoo ``ppo.yml`` "Pendulum-v1": n_steps 1024 and batch 64
#: (16 minibatches per epoch), 10 epochs, gae_lambda 0.95, learning_rate 1e-3, clip 0.2,
#: ent_coef 0, gSDE with sde_sample_freq 4. Deviations: one environment (the harness's
#: interaction is one system; the zoo uses 4); ``n_steps`` a whole number of episodes near 1024,
#: a multiple of 16 episodes (:func:`whole_episode_rollout`: cart-pole 32 x 40 = 1280, 10 s
#: tasks 16 x 100 = 1600, unicycle 16 x 67 = 1072), and ``batch_size = n_steps / 16``, so
#: minibatches divide the rollout and updates and hand-overs fall on episode boundaries (unless
#: an episode terminates early); ``gamma = 0.98`` (0.99 for the 10 s tasks) instead of 0.9, which
#: looks only ~1 s ahead at dt = 0.1 s, too short for a swing-up; SB3's default 64x64 nets; no
#: observation normalisation (sin/cos features instead).
PPO_PRESETS: dict[str, dict[str, Any]] = {
    "default": {
        "learning_rate": 1e-3,
        "batch_size": None,
        "n_steps": None,
        "n_epochs": 10,
        "gamma": 0.98,
        "gae_lambda": 0.95,
        "clip_range": 0.2,
        "ent_coef": 0.0,
        "use_sde": True,
        "sde_sample_freq": 4,
        "net_width": 64,
        "net_layers": 2,
    },
    "cartpole": {},
    "dmc-cartpole": {"gamma": 0.99},
    "double-pendulum": {"gamma": 0.99},
    "unicycle": {"gamma": 0.99},
}

#: PPO minibatches per epoch (zoo Pendulum-v1: 1024 / 64)
PPO_MINIBATCHES = 16


def whole_episode_rollout(horizon: int, target: int = 1024, minibatches: int = PPO_MINIBATCHES) -> int:
    """PPO ``n_steps``: ``E * horizon`` steps with ``E`` the multiple of ``minibatches`` (>= it) nearest
    ``target / horizon`` episodes. Cart-pole (40): 1280; 100-step tasks: 1600; unicycle (67): 1072."""
    episodes = minibatches * max(1, round(target / (minibatches * horizon)))
    return episodes * int(horizon)


def preset(presets: dict[str, dict[str, Any]], task_name: str) -> dict[str, Any]:
    """The ``"default"`` preset updated with the task's own entries (unknown tasks: the default)."""
    return {**presets["default"], **presets.get(task_name, {})}


_COMMON_OPTIONS = (
    Option("eval_every_steps", int, None, "counted env steps between hand-overs (default: 5 episodes; PPO: n_steps)", low=1),
    Option("learning_rate", float, None, "Adam learning rate (default: task preset)", low=0.0),
    Option("batch_size", int, None, "minibatch size (default: task preset)", low=1),
    Option("gamma", float, None, "discount factor (default: task preset)", low=0.0, high=1.0),
    Option("net_width", int, None, "hidden units per layer of actor and critic (default: task preset)", low=1),
    Option("net_layers", int, None, "hidden layers of actor and critic (default: task preset)", low=1),
    Option("torch_threads", int, 1, "torch CPU threads (1: one per worker; more oversubscribes shared cores)", low=1,
           execution=True),
    Option("progress_bar", bool, False, "show SB3's own progress bar during each learn() chunk"),
)


class SB3Learner(Learner):
    """Shared machinery of the SB3 learners: env wrapping, presets, hand-over loop, saving.

    Subclasses set ``algorithm`` (the SB3 class name), ``presets`` and implement
    :meth:`_algorithm_kwargs` (preset + options -> SB3 constructor arguments).
    """

    extra = "sb3"
    requires = ("stable_baselines3",)
    supports_resume = True
    keep_checkpoints = 2  # SAC's replay buffer: up to ~100 bytes per step of interaction
    #: hand-overs come every few seconds and a checkpoint holds every recorded episode (PPO on the double
    #: pendulum: 13 MB after 10^5 steps, every 2 s): one every 5 minutes of wall time
    checkpoint_every_seconds = 300.0
    default_max_trials = None
    algorithm: ClassVar[str] = ""
    presets: ClassVar[dict[str, dict[str, Any]]] = {}
    #: the top-level modules of SB3's policy that the deterministic policy uses (``None``: all); a saved
    #: policy holds only their tensors (:meth:`policy_state`)
    acting_modules: ClassVar[tuple[str, ...] | None] = None

    def __init__(self, spec: TaskSpec, options: dict[str, Any] | None = None, seed: int = 0) -> None:
        super().__init__(spec, options, seed)
        # the SB3 arguments' own checks (e.g. SAC's ent_coef) fail here, before the harness logs a run
        self._algorithm_kwargs(self.hyperparameters())

    # -- hyperparameters ------------------------------------------------------------------
    def hyperparameters(self) -> dict[str, Any]:
        """The task preset with every option that was set (not ``None``) applied on top."""
        hp = preset(self.presets, self.spec.name)
        for key in hp:
            if key in self.options and self.options[key] is not None:
                hp[key] = self.options[key]
        if "n_steps" in hp and hp["n_steps"] is None:
            hp["n_steps"] = whole_episode_rollout(self.spec.horizon)
        if "n_steps" in hp and hp["batch_size"] is None:
            hp["batch_size"] = max(1, int(hp["n_steps"]) // PPO_MINIBATCHES)
        hp["eval_every_steps"] = self._eval_every_steps(hp)
        return hp

    def _eval_every_steps(self, hp: dict[str, Any]) -> int:
        value = self.options.get("eval_every_steps")
        return int(value) if value is not None else 5 * self.spec.horizon

    def options_used(self) -> dict[str, Any]:
        """The options with the task preset's hyperparameters where they were left unset."""
        hp = self.hyperparameters()
        return {k: hp.get(k, v) if v is None else v for k, v in self.options.items()}

    @abstractmethod
    def _algorithm_kwargs(self, hp: dict[str, Any]) -> dict[str, Any]:
        """SB3 constructor keyword arguments (besides policy, env, seed, device) from ``hp``."""

    @staticmethod
    def _net_arch(hp: dict[str, Any]) -> list[int]:
        return [int(hp["net_width"])] * int(hp["net_layers"])

    @classmethod
    def _algorithm_class(cls) -> type:
        import stable_baselines3

        return getattr(stable_baselines3, cls.algorithm)

    # -- learning -------------------------------------------------------------------------
    def build_model(self, env: gym.Env, hp: dict[str, Any]) -> Any:
        """The SB3 model on ``env`` (already wrapped by :func:`make_agent_env`), seeded with ``self.seed``."""
        return self._algorithm_class()("MlpPolicy", env, seed=self.seed, device="cpu", verbose=0, **self._algorithm_kwargs(hp))

    def learn(self, interaction: Interaction) -> Iterator[Policy]:
        import torch

        from harness.checkpoint import global_rng_state, set_global_rng_state

        torch.set_num_threads(int(self.options["torch_threads"]))
        hp = self.hyperparameters()
        rng = global_rng_state()  # a resume's, restored by the harness: building the model reseeds
        model = self.build_model(make_agent_env(interaction.as_env(), self.spec, float(hp["gamma"])), hp)
        self._model = model
        if self._resume_state is not None:
            self._restore(model, self._resume_state)
            set_global_rng_state(rng)
        policy = SB3Policy(model.policy, self.spec)  # the live network: trained further after each hand-over
        hp_file = self._write_hyperparameters(hp)
        if self._resume_state is None:
            self.artifacts.append(hp_file)  # the harness attaches it after the first hand-over
        chunk = int(hp["eval_every_steps"])
        try:
            while True:
                steps_before, start = interaction.steps, time.perf_counter()
                model.learn(chunk, reset_num_timesteps=False, log_interval=None, progress_bar=bool(self.options["progress_bar"]))
                elapsed = time.perf_counter() - start
                self.metrics["sb3_steps_per_second"] = (interaction.steps - steps_before) / max(elapsed, 1e-9)
                self.metrics["sb3_num_timesteps"] = float(model.num_timesteps)
                self.metrics.update(_train_metrics(model))
                # SB3's Monitor: the last (up to 100) training episodes' undiscounted cost as the agent saw it (an
                # early termination's held cost included, discounted: HeldCostAtTermination)
                if model.ep_info_buffer:
                    self.metrics["sb3_train_episode_cost"] = -float(np.mean([ep["r"] for ep in model.ep_info_buffer]))
                yield policy
        finally:
            shutil.rmtree(hp_file.parent, ignore_errors=True)

    # -- resuming -------------------------------------------------------------------------
    # A checkpoint holds what SB3's own save/load_replay_buffer would, as plain data (harness.datafile;
    # no cloudpickle): the networks' and optimisers' state_dicts and SB3's torch variables
    # (``get_parameters`` / ``_get_torch_save_params``: SAC's log_ent_coef), the counters and
    # episode statistics ``learn`` continues from, the action space's RNG (SAC's random warm-up
    # actions) and SAC's replay buffer (the filled part). The global RNGs are the harness's; the
    # environment continues from the interaction's checkpoint: a hand-over on an episode boundary
    # (SAC always; PPO when its rollout ends one) leaves the next episode reset and not yet stepped,
    # and SB3's first ``env.reset()`` after the resume is given that episode again.

    _REPLAY_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")

    def state_dict(self) -> dict[str, Any]:
        """The SB3 model at its last hand-over (empty before the first); see the comment above."""
        model = getattr(self, "_model", None)
        if model is None:
            return {}
        from stable_baselines3.common.save_util import recursive_getattr

        _, variables = model._get_torch_save_params()
        state: dict[str, Any] = {
            "parameters": copy.deepcopy(model.get_parameters()),  # state_dicts: tensors without gradients
            "variables": {name: recursive_getattr(model, name).detach().clone() for name in variables},
            "num_timesteps": int(model.num_timesteps),
            "n_updates": int(model._n_updates),
            "episode_num": int(model._episode_num),
            "ep_info": [dict(info) for info in (model.ep_info_buffer or [])],
            "ep_success": list(model.ep_success_buffer or []),
            "action_space_rng": model.action_space.np_random.bit_generator.state,
            "replay": None,
        }
        buffer = getattr(model, "replay_buffer", None)
        if buffer is not None:
            filled = buffer.buffer_size if buffer.full else buffer.pos
            state["replay"] = {"pos": int(buffer.pos), "full": bool(buffer.full),
                               **{name: getattr(buffer, name)[:filled].copy() for name in self._REPLAY_ARRAYS}}
        return state

    def _restore(self, model: Any, state: dict[str, Any]) -> None:
        """Put :meth:`state_dict` into a freshly built ``model`` (same hyperparameters)."""
        import torch
        from stable_baselines3.common.save_util import recursive_getattr

        model.set_parameters(state["parameters"], exact_match=True, device="cpu")
        for name, value in state["variables"].items():
            with torch.no_grad():
                recursive_getattr(model, name).copy_(value)
        model.num_timesteps = int(state["num_timesteps"])
        model._n_updates = int(state["n_updates"])
        model._episode_num = int(state["episode_num"])
        model.ep_info_buffer = deque(state["ep_info"], maxlen=model._stats_window_size)
        model.ep_success_buffer = deque(state["ep_success"], maxlen=model._stats_window_size)
        model.action_space.np_random.bit_generator.state = state["action_space_rng"]
        replay = state["replay"]
        if replay is not None:
            buffer = model.replay_buffer
            filled = len(replay["rewards"])
            if filled > buffer.buffer_size:
                raise ValueError(f"a replay buffer of {filled} steps does not fit this run's buffer_size {buffer.buffer_size}")
            for name in self._REPLAY_ARRAYS:
                getattr(buffer, name)[:filled] = replay[name]
            buffer.pos, buffer.full = int(replay["pos"]), bool(replay["full"])

    def _write_hyperparameters(self, hp: dict[str, Any]) -> Path:
        directory = Path(tempfile.mkdtemp(prefix=f"harness-{self.name}-"))
        path = directory / "sb3_hyperparameters.json"
        path.write_text(json.dumps({"algorithm": self.algorithm, "task": self.spec.name, **hp}, indent=2, sort_keys=True))
        return path

    # -- saving ---------------------------------------------------------------------------
    @classmethod
    def _policy_class(cls) -> type:
        """SB3's policy class behind ``"MlpPolicy"`` (SAC: ``SACPolicy``, PPO: ``ActorCriticPolicy``)."""
        return cls._algorithm_class().policy_aliases["MlpPolicy"]

    @classmethod
    def policy_state(cls, policy: Policy) -> dict[str, Any]:
        """The tensors that act (``weights``: the network's ``state_dict``, only its :attr:`acting_modules`
        where set), the plain constructor arguments that rebuild it (``kwargs``: :data:`POLICY_KWARGS`),
        its input and output sizes. Not SB3's ``.zip``, whose metadata is cloudpickled (reading it runs code)."""
        if not isinstance(policy, SB3Policy):
            raise TypeError(f"an SB3 learner's policy is an SB3Policy, not a {type(policy).__name__}")
        network = policy.network
        arguments = network._get_constructor_parameters()
        return {
            "algorithm": cls.algorithm,
            "observation_dim": int(network.observation_space.shape[0]),
            "action_dim": int(network.action_space.shape[0]),
            "kwargs": {k: arguments[k] for k in POLICY_KWARGS if k in arguments},
            "weights": {k: v.detach().clone() for k, v in network.state_dict().items() if cls._acts(k)},
        }

    @classmethod
    def _acts(cls, key: str) -> bool:
        """Whether the ``state_dict`` entry ``key`` belongs to a module the deterministic policy uses."""
        return cls.acting_modules is None or key.split(".", 1)[0] in cls.acting_modules

    @classmethod
    def policy_from_state(cls, state: dict[str, Any], spec: TaskSpec) -> SB3Policy:
        if state["algorithm"] != cls.algorithm:
            raise ValueError(f"a {state['algorithm']} network, not {cls.algorithm}")
        features = feature_dim(spec.state_dim, spec.angle_indices)
        if (state["observation_dim"], state["action_dim"]) != (features, spec.action_dim):
            raise ValueError(f"a network for {state['observation_dim']} features and {state['action_dim']} controls; "
                             f"the task has {features} and {spec.action_dim}")
        kwargs = state["kwargs"]
        if not isinstance(kwargs, dict) or not set(kwargs) <= set(POLICY_KWARGS):
            raise ValueError(f"constructor arguments {sorted(kwargs)} beyond {list(POLICY_KWARGS)}")
        network = cls._policy_class()(feature_space(features), normalised_action_space((spec.action_dim,)), _no_learning, **kwargs)
        # every acting tensor must be there, nothing unknown may be (older saves also hold SAC's critics)
        missing, unexpected = network.load_state_dict(state["weights"], strict=False)
        missing = [k for k in missing if cls._acts(k)]
        if missing or unexpected:
            raise ValueError(f"a {cls.algorithm} network's tensors do not match: missing {missing}, unexpected {unexpected}")
        network.set_training_mode(False)
        return SB3Policy(network, spec)

    @classmethod
    def read_legacy_policy(cls, path: Path, spec: TaskSpec) -> Policy:
        """An older harness's policy: SB3's ``.zip`` (``model.save``; **reading it runs code**: its metadata is
        cloudpickled), else the base class's pickle. For ``harness store migrate`` only."""
        if Path(path).suffix != ".zip":
            return super().read_legacy_policy(path, spec)
        model = cls._algorithm_class().load(Path(path), device="cpu")
        return SB3Policy(model.policy, spec)


#: the constructor arguments of SB3's policies that :meth:`SB3Learner.policy_state` stores: plain values; the
#: others are classes (activation, features extractor, optimiser: SB3's defaults here), spaces and a schedule
POLICY_KWARGS = ("net_arch", "use_sde", "log_std_init", "use_expln", "clip_mean", "full_std", "squash_output", "ortho_init",
                 "n_critics", "share_features_extractor", "normalize_images")


def _no_learning(progress_remaining: float) -> float:
    """The learning-rate schedule of a rebuilt network (it is only evaluated)."""
    return 0.0


def _train_metrics(model: Any) -> dict[str, float]:
    """SB3's latest ``train/*`` values (losses, entropy coefficient, ...) as ``sb3_<name>`` floats."""
    out: dict[str, float] = {}
    for key, value in getattr(model.logger, "name_to_value", {}).items():
        if key.startswith("train/") and isinstance(value, (int, float, np.floating, np.integer)):
            out["sb3_" + key[len("train/"):]] = float(value)
    return out


def sac_entropy_coefficient(value: str | float) -> str | float:
    """SB3's ``ent_coef`` from the option: ``"auto"`` and ``"auto_X"`` (X > 0) as they are, a number
    X > 0 as a float; anything else raises :class:`OptionError` naming the accepted forms."""
    text = str(value).strip()
    if text == "auto":
        return text
    number = text.removeprefix("auto_")
    try:
        x = float(number)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise OptionError(f"option 'ent_coef' of learner 'sac' must be auto, auto_X or a number X > 0; got {value!r}")
    return text if number != text else x


class SACLearner(SB3Learner):
    """Soft actor-critic (stable-baselines3 ``SAC``, MlpPolicy, CPU); presets in :data:`SAC_PRESETS`.

    Default limit: 10^4 s of interaction (10^5 steps of cart-pole, 2.5 * 10^3 episodes), an order
    of magnitude above what SAC typically needs on comparable swing-ups (zoo Pendulum: 2 * 10^4
    steps) and more than 500x PILCO's cart-pole figure (~17.5 s), so a run that ends there is an
    honest "unsolved, > 10^4 s".
    """

    name = "sac"
    description = "soft actor-critic (stable-baselines3), sin/cos angle features, actions in [-1, 1]"
    algorithm = "SAC"
    presets = SAC_PRESETS
    #: the actor: the critics (two Q networks and their targets, ~4x the actor's tensors) do not act
    acting_modules = ("actor",)
    default_budget_seconds = 1.0e4
    options = _COMMON_OPTIONS + (
        Option("learning_starts", int, None, "random-action steps before learning starts (default: task preset)", low=0),
        Option("train_freq", int, None, "env steps between training phases; 0 = once per episode (preset)", low=0),
        Option("gradient_steps", int, None, "gradient steps per training phase; -1 = as many as env steps collected (preset)", low=-1),
        Option("buffer_size", int, None, "replay buffer capacity in steps (default: task preset)", low=1),
        Option("tau", float, None, "target network soft-update rate (default: task preset)", low=0.0, high=1.0),
        Option("ent_coef", str, None, "entropy coefficient: auto (tuned towards entropy -dim(u), starting at 1; preset), "
               "auto_X (tuned, starting at X) or a fixed number X > 0"),
    )

    def _algorithm_kwargs(self, hp: dict[str, Any]) -> dict[str, Any]:
        if int(hp["gradient_steps"]) == 0:
            raise OptionError("option 'gradient_steps' of learner 'sac' must be >= 1 or -1 (as many as env steps collected); got 0")
        return {
            "ent_coef": sac_entropy_coefficient(hp["ent_coef"]),
            "learning_rate": float(hp["learning_rate"]),
            "batch_size": int(hp["batch_size"]),
            "buffer_size": int(hp["buffer_size"]),
            "learning_starts": int(hp["learning_starts"]),
            "train_freq": (1, "episode") if int(hp["train_freq"]) == 0 else int(hp["train_freq"]),
            "gradient_steps": int(hp["gradient_steps"]),
            "gamma": float(hp["gamma"]),
            "tau": float(hp["tau"]),
            "policy_kwargs": {"net_arch": self._net_arch(hp)},
        }


class PPOLearner(SB3Learner):
    """Proximal policy optimisation (stable-baselines3 ``PPO``, MlpPolicy, CPU); presets in :data:`PPO_PRESETS`.

    A hand-over follows every PPO update (``n_steps`` counted steps) unless ``eval_every_steps``
    says otherwise (rounded up to a multiple of ``n_steps``). Default limit: 10^5 s of interaction
    (10^6 cart-pole steps), ten times SAC's: on-policy PPO reuses no old data and needs 5-10x
    SAC's samples on comparable tasks (zoo Pendulum: 10^5 vs 2 * 10^4 steps).
    """

    name = "ppo"
    description = "proximal policy optimisation (stable-baselines3), sin/cos angle features, actions in [-1, 1]"
    algorithm = "PPO"
    presets = PPO_PRESETS
    default_budget_seconds = 1.0e5
    options = _COMMON_OPTIONS + (
        Option("n_steps", int, None, "env steps per rollout / update (default: task preset)", low=2),
        Option("n_epochs", int, None, "optimisation epochs per update (default: task preset)", low=1),
        Option("gae_lambda", float, None, "GAE lambda (default: task preset)", low=0.0, high=1.0),
        Option("clip_range", float, None, "PPO clip range (default: task preset)", low=0.0),
        Option("ent_coef", float, None, "entropy bonus coefficient (default: task preset)", low=0.0),
        Option("use_sde", bool, None, "generalised state-dependent exploration (default: task preset)"),
    )

    def _eval_every_steps(self, hp: dict[str, Any]) -> int:
        n_steps = int(hp["n_steps"])
        value = self.options.get("eval_every_steps")
        wanted = n_steps if value is None else int(value)
        return -(-wanted // n_steps) * n_steps

    def _algorithm_kwargs(self, hp: dict[str, Any]) -> dict[str, Any]:
        return {
            "learning_rate": float(hp["learning_rate"]),
            "batch_size": int(hp["batch_size"]),
            "n_steps": int(hp["n_steps"]),
            "n_epochs": int(hp["n_epochs"]),
            "gamma": float(hp["gamma"]),
            "gae_lambda": float(hp["gae_lambda"]),
            "clip_range": float(hp["clip_range"]),
            "ent_coef": float(hp["ent_coef"]),
            "use_sde": bool(hp["use_sde"]),
            "sde_sample_freq": int(hp["sde_sample_freq"]),
            "policy_kwargs": {"net_arch": {"pi": self._net_arch(hp), "vf": self._net_arch(hp)}},
        }


__all__ = [
    "AngleFeatures",
    "HeldCostAtTermination",
    "NormalisedActions",
    "PPOLearner",
    "PPO_MINIBATCHES",
    "PPO_PRESETS",
    "SACLearner",
    "SAC_PRESETS",
    "SB3Learner",
    "SB3Policy",
    "angle_features",
    "feature_dim",
    "feature_space",
    "from_bounds",
    "make_agent_env",
    "normalised_action_space",
    "preset",
    "sac_entropy_coefficient",
    "to_bounds",
    "whole_episode_rollout",
]
