"""harness.threads: the harness decides how many threads a run uses."""

from __future__ import annotations

import os

import pytest
import torch

from harness import threads


def test_run_threads_defaults_to_the_cores_and_follows_the_variable(monkeypatch) -> None:
    monkeypatch.delenv(threads.ENV, raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert threads.run_threads() == threads.available_cores() == len(os.sched_getaffinity(0))
    monkeypatch.setenv(threads.ENV, "3")
    assert threads.run_threads() == 3


@pytest.mark.parametrize("omp,expected", [("5", 5), ("4,2", 4), ("0", None), ("many", None), ("", None)])
def test_a_users_omp_num_threads_limits_a_run_unless_harness_threads_says_otherwise(monkeypatch, omp, expected) -> None:
    """Several hand-started runs on one machine, each with OMP_NUM_THREADS=3, take 3 threads each, not
    every core each (four runs on a 16-core GPU machine once took 64); a value the harness cannot read
    (0, a word) leaves the default."""
    monkeypatch.delenv(threads.ENV, raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", omp)
    assert threads.run_threads() == (expected or threads.available_cores())
    monkeypatch.setenv(threads.ENV, "2")
    assert threads.run_threads() == 2


@pytest.mark.parametrize("value", ["0", "-2", "two"])
def test_a_bad_value_is_one_line_naming_the_variable(monkeypatch, value) -> None:
    monkeypatch.setenv(threads.ENV, value)
    with pytest.raises(ValueError, match=rf"HARNESS_THREADS={value!r} is not a positive integer \(unset it"):
        threads.run_threads()


def test_single_threaded_sets_every_variable_and_torch(monkeypatch) -> None:
    for var in (threads.ENV, *threads.LIBRARY_ENV):
        monkeypatch.delenv(var, raising=False)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        threads.single_threaded()
        assert threads.run_threads() == 1 and torch.get_num_threads() == 1
        assert all(os.environ[v] == "1" for v in threads.LIBRARY_ENV)
    finally:
        torch.set_num_threads(before)


def test_torch_threads_restores_the_previous_setting() -> None:
    before = torch.get_num_threads()
    with threads.torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


def test_a_policy_is_stepped_on_one_thread_and_the_run_keeps_its_threads() -> None:
    """Evaluation and counted episodes apply the policy with one torch thread (its per-step operations
    are too small for threads); the run's own setting is back once the episode ends."""
    from harness.interaction import Interaction, run_episode
    from tests.harness import toy

    task = toy.ToyReach()
    seen: list[int] = []

    def policy(observation):
        seen.append(torch.get_num_threads())
        return [0.0]

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        run_episode(task.make_env(), task.spec, policy, seed=0)
        Interaction(task.make_env(), task.spec).rollout(policy)
        assert seen and set(seen) == {1}
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
