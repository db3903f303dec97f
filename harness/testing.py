"""Conformance checks for plugin authors (in the spirit of GPyTorch's base test cases).

Use them from pytest by subclassing; every ``test_*`` method is inherited::

    from harness.testing import LearnerConformance, TaskConformance

    class TestMyTask(TaskConformance):
        task_cls = MyTask            # options: task_options = {"horizon": 20}

    class TestMyLearner(LearnerConformance):
        learner_cls = MyLearner      # task_name = "cartpole"; learner_options = {...}

or call the ``check_*`` functions directly; each raises ``AssertionError`` with a message naming
the broken part of the contract.
"""

from __future__ import annotations

import warnings
from typing import Any, ClassVar

import numpy as np

from harness.errors import BudgetExhaustedError, InvalidActionError
from harness.interaction import Interaction
from harness.learner import Learner
from harness.task import Episode, Task, TaskSpec


def _rollout_random(env, spec: TaskSpec, seed: int, steps: int) -> list[tuple[np.ndarray, float, bool, bool, dict]]:
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    out = []
    for _ in range(steps):
        u = rng.uniform(spec.action_low, spec.action_high)
        step = env.step(u)
        out.append(step)
        if step[2] or step[3]:
            break
    return out


def check_task_spec(task: Task) -> None:
    """The spec is self-consistent and the cost is finite and in [0, 1) near the start."""
    spec = task.spec
    assert isinstance(spec, TaskSpec), f"{type(task).__name__}.spec must be a TaskSpec"
    assert spec.name == type(task).name, f"spec.name {spec.name!r} differs from the plugin name {type(task).name!r}"
    assert np.allclose(spec.init_cov, spec.init_cov.T), "init_cov must be symmetric"
    assert np.all(np.linalg.eigvalsh(spec.init_cov) >= -1e-12), "init_cov must be positive semi-definite"
    assert all(0 <= i < spec.state_dim for i in spec.angle_indices), "angle_indices out of range"
    samples = np.random.default_rng(0).multivariate_normal(spec.init_mean, spec.init_cov, size=64)
    costs = spec.cost(samples)
    assert np.all(np.isfinite(costs)) and np.all((costs >= 0) & (costs < 1)), "cost must lie in [0, 1)"


def check_task_env(task: Task, steps: int = 30) -> None:
    """The environment follows the contract of :mod:`harness.task`."""
    spec = task.spec
    env = task.make_env()
    try:
        assert env.observation_space.shape == (spec.state_dim,), (
            f"observation_space shape {env.observation_space.shape} != ({spec.state_dim},)"
        )
        assert env.action_space.shape == (spec.action_dim,), f"action_space shape {env.action_space.shape} != ({spec.action_dim},)"
        assert np.allclose(env.action_space.low, spec.action_low) and np.allclose(env.action_space.high, spec.action_high), (
            "action_space bounds differ from spec.action_low/high"
        )
        obs, info = env.reset(seed=123)
        assert np.shape(obs) == (spec.state_dim,), "reset must return an observation of shape (D,)"
        assert "state" in info, "reset's info must carry the true state under 'state'"
        for obs, reward, terminated, truncated, info in _rollout_random(env, spec, 123, steps):
            assert np.all(np.isfinite(obs)), "observation must be finite"
            assert "state" in info and "action_clipped" in info, "step's info must carry 'state' and 'action_clipped'"
            expected = -float(spec.cost(np.asarray(info["state"])))
            assert abs(float(reward) - expected) <= 1e-9, f"reward {reward} != -cost(info['state']) = {expected}"
        # seeding: same seed, same episode
        first = [np.asarray(s[0]) for s in _rollout_random(env, spec, 7, 10)]
        second = [np.asarray(s[0]) for s in _rollout_random(env, spec, 7, 10)]
        assert len(first) == len(second) and all(np.array_equal(a, b) for a, b in zip(first, second)), (
            "reset(seed=s) followed by the same actions must reproduce the episode"
        )
        # invalid actions
        env.reset(seed=0)
        for bad in (np.full(spec.action_dim, np.nan), np.zeros(spec.action_dim + 1)):
            try:
                env.step(bad)
            except InvalidActionError:
                pass
            else:
                raise AssertionError(f"step({bad!r}) must raise harness.errors.InvalidActionError")
        env.reset(seed=0)
        _, _, _, _, info = env.step(spec.action_high * 10.0)
        assert info["action_clipped"], "an out-of-bound action must be clipped and flagged in info['action_clipped']"
        # horizon
        env.reset(seed=1)
        n, done = 0, False
        while not done and n < spec.horizon + 5:
            _, _, terminated, truncated, _ = env.step(np.zeros(spec.action_dim))
            n += 1
            done = terminated or truncated
        assert done and n <= spec.horizon, f"episodes must end by the horizon ({spec.horizon} steps); ran {n}"
    finally:
        env.close()


def check_gymnasium_api(task: Task) -> None:
    """gymnasium's own environment checker passes."""
    from gymnasium.utils.env_checker import check_env

    env = task.make_env()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            check_env(env, skip_render_check=True)
    finally:
        env.close()


def check_task_success(task: Task) -> None:
    """``success`` returns a plain bool for a real (random) episode."""
    from harness.interaction import run_episode

    env = task.make_env()
    try:
        spec = task.spec
        rng = np.random.default_rng(0)
        episode = run_episode(env, spec, lambda _: rng.uniform(spec.action_low, spec.action_high), seed=0)
    finally:
        env.close()
    assert isinstance(episode, Episode)
    result = task.success(episode)
    assert isinstance(result, (bool, np.bool_)), f"success must return a bool, got {type(result).__name__}"


def check_learner(
    learner_cls: type[Learner],
    task: Task,
    options: dict[str, Any] | None = None,
    seed: int = 0,
    handover_budget_episodes: int = 50,
) -> None:
    """The learner hands over a usable policy within ``handover_budget_episodes`` episodes, acts
    only through the interaction, is seeded, and lets the budget stop it."""
    spec = task.spec

    def first_policy_outputs(seed: int) -> tuple[np.ndarray, int]:
        learner = learner_cls(spec, options, seed=seed)
        budget = handover_budget_episodes * spec.episode_seconds
        interaction = Interaction(task.make_env(), spec, budget_seconds=budget, seed=seed)
        generator = learner.learn(interaction)
        try:
            try:
                policy = next(generator)
            except BudgetExhaustedError:
                raise AssertionError(f"the learner handed over no policy within {handover_budget_episodes} episodes") from None
            probes = np.random.default_rng(1).multivariate_normal(spec.init_mean, spec.init_cov, size=5)
            actions = np.array([np.asarray(policy(x), dtype=np.float64).reshape(-1) for x in probes])
            assert actions.shape == (5, spec.action_dim), f"policy must map (D,) observations to ({spec.action_dim},) actions"
            assert np.all(np.isfinite(actions)), "policy returned non-finite actions"
            counted = sum(ep.steps for ep in interaction.episodes)
            assert interaction.steps == counted, "every step must go through the interaction"
            return actions, interaction.steps
        finally:
            generator.close()
            interaction.close()

    a1, steps1 = first_policy_outputs(seed)
    a2, steps2 = first_policy_outputs(seed)
    assert steps1 == steps2 and np.array_equal(a1, a2), "same seed must give the same first policy"

    learner = learner_cls(spec, options, seed=seed)
    interaction = Interaction(task.make_env(), spec, budget_seconds=spec.dt * 3, seed=seed)
    generator = learner.learn(interaction)
    try:
        for _ in range(1000):
            next(generator)
    except BudgetExhaustedError:
        pass
    except StopIteration:
        pass
    else:
        raise AssertionError("a learner must not swallow BudgetExhaustedError")
    finally:
        generator.close()
        interaction.close()
    assert interaction.steps <= 3, "the budget must bound the learner's steps"


def data_difference(a: Any, b: Any, where: str = "value") -> str | None:
    """Where plain data ``b`` first differs from ``a`` (types, shapes, dtypes, values bit for bit), or ``None``.

    Mappings compare as mappings (a ``dict`` equals an ``OrderedDict`` with the same items in the same order).
    """
    import struct
    from collections.abc import Mapping

    import torch

    if isinstance(a, Mapping):
        if not isinstance(b, Mapping) or list(a) != list(b):
            return f"{where}: keys {list(a)} became {list(b) if isinstance(b, Mapping) else type(b).__name__}"
        return next((d for k in a if (d := data_difference(a[k], b[k], f"{where}[{k!r}]"))), None)
    if isinstance(a, torch.Tensor):
        if not isinstance(b, torch.Tensor) or a.dtype != b.dtype or a.shape != b.shape:
            return f"{where}: tensor {a.dtype} {tuple(a.shape)} became {b!r:.80}"
        a, b = a.detach().cpu().numpy(), b.detach().cpu().numpy()
    if isinstance(a, (np.ndarray, np.generic)):
        if type(a) is not type(b) or a.dtype != b.dtype or np.shape(a) != np.shape(b) or a.tobytes() != b.tobytes():
            return f"{where}: {type(a).__name__} {a.dtype} {np.shape(a)} became {b!r:.80}"
        return None
    if isinstance(a, (list, tuple)):
        if type(a) is not type(b) or len(a) != len(b):
            return f"{where}: {type(a).__name__} of {len(a)} became {type(b).__name__} {b!r:.80}"
        return next((d for i, (x, y) in enumerate(zip(a, b)) if (d := data_difference(x, y, f"{where}[{i}]"))), None)
    if isinstance(a, float) and type(b) is float:
        return None if struct.pack("<d", a) == struct.pack("<d", b) else f"{where}: {a!r} became {b!r}"
    if type(a) is not type(b) or a != b:
        return f"{where}: {a!r:.80} became {b!r:.80}"
    return None


def check_policy_round_trip(learner_cls: type[Learner], task: Task, options: dict[str, Any] | None = None, seed: int = 0) -> None:
    """The first handed-over policy, saved as data (``save_policy``) and loaded back (``load_policy``), acts
    exactly as the live one did; a changed file is refused; a resumable learner's ``state_dict()`` is plain
    data that a checkpoint gives back exactly (:mod:`harness.datafile`)."""
    import tempfile
    from pathlib import Path

    from harness import datafile

    spec = task.spec
    probes = np.random.default_rng(2).multivariate_normal(spec.init_mean, spec.init_cov + np.eye(spec.state_dim), size=6)
    learner = learner_cls(spec, options, seed=seed)
    interaction = Interaction(task.make_env(), spec, seed=seed)
    generator = learner.learn(interaction)
    with tempfile.TemporaryDirectory(prefix="harness-conformance-") as tmp:
        try:
            policy = next(generator)
            path = learner_cls.save_policy(policy, Path(tmp) / "policy_trial001")
            live = np.array([np.asarray(policy(x), dtype=np.float64) for x in probes])
            if learner_cls.supports_resume:
                state = learner.state_dict()
                try:
                    _, back = datafile.loads(datafile.dumps("checkpoint", state), "checkpoint", "state")
                except datafile.NotPlainDataError as exc:
                    raise AssertionError(f"state_dict() must be plain data: {exc}") from None
                difference = data_difference(state, back, "state_dict()")
                assert difference is None, f"state_dict() does not come back from a checkpoint as it was: {difference}"
        finally:
            generator.close()
            interaction.close()
        assert path.suffix == datafile.POLICY_SUFFIX, f"save_policy must write {datafile.POLICY_SUFFIX}, wrote {path.name}"
        loaded = learner_cls.load_policy(path, spec)
        again = np.array([np.asarray(loaded(x), dtype=np.float64) for x in probes])
        assert np.array_equal(live, again), "the loaded policy must act exactly as the saved one did"
        blob = bytearray(path.read_bytes())
        blob[-1] ^= 1
        path.write_bytes(bytes(blob))
        try:
            learner_cls.load_policy(path, spec)
        except datafile.DataFileError:
            pass
        else:
            raise AssertionError("load_policy must refuse a changed file")


class TaskConformance:
    """pytest base class: set ``task_cls`` (and optionally ``task_options``)."""

    task_cls: ClassVar[type[Task]]
    task_options: ClassVar[dict[str, Any]] = {}

    def make_task(self) -> Task:
        return self.task_cls(**self.task_options)

    def test_spec(self) -> None:
        check_task_spec(self.make_task())

    def test_env_contract(self) -> None:
        check_task_env(self.make_task())

    def test_gymnasium_api(self) -> None:
        check_gymnasium_api(self.make_task())

    def test_success_predicate_returns_bool(self) -> None:
        check_task_success(self.make_task())


class LearnerConformance:
    """pytest base class: set ``learner_cls`` (and optionally ``task_name``, ``learner_options``)."""

    learner_cls: ClassVar[type[Learner]]
    task_name: ClassVar[str] = "cartpole"
    task_options: ClassVar[dict[str, Any]] = {}
    learner_options: ClassVar[dict[str, Any]] = {}

    def test_learner_contract(self) -> None:
        from harness.discovery import load_task

        check_learner(self.learner_cls, load_task(self.task_name)(**self.task_options), self.learner_options)

    def test_policy_round_trip(self) -> None:
        from harness.discovery import load_task

        check_policy_round_trip(self.learner_cls, load_task(self.task_name)(**self.task_options), self.learner_options)
