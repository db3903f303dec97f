"""The run loop: evaluation, interaction time to success, budget, failure handling."""

from __future__ import annotations

import numpy as np
import pytest
from rich.console import Console

from harness import runner
from harness.errors import InvalidActionError
from harness.interaction import Interaction
from harness.learner import Learner
from harness.progress import RichProgress
from harness.runner import RunConfig
from harness.task import Episode
from harness.testing import LearnerConformance, TaskConformance
from harness.tracking import MemoryTracker
from tests.harness import toy


@pytest.fixture
def toy_plugins(monkeypatch):
    learners = {c.name: c for c in (toy.BadThenGood, toy.Greedy, toy.NaNLearner, toy.Crashing)}
    monkeypatch.setattr(runner, "load_learner", lambda name: learners[name])
    monkeypatch.setattr(runner, "load_task", lambda name: toy.ToyReach)


def test_time_to_success_is_interaction_before_first_solved_evaluation(toy_plugins):
    result = runner.run(RunConfig("bad-then-good", "toy-reach", seed=3, max_trials=10, eval_episodes=5))
    assert result.solved and result.stop_reason == "solved"
    # two useless trials (8 steps x 0.5 s each), then the solving policy is handed over after its own
    # episode: 3 episodes = 12 s were consumed before the first solved evaluation
    assert result.interaction_time_to_success == pytest.approx(3 * 8 * 0.5)
    assert result.trials_to_success == 3
    assert result.trials == 3


def test_learner_status_and_evaluation_are_shown_between_hand_overs(toy_plugins):
    """Learner.report_status reaches the run's progress (``harness bench`` shows it beside the bar), and the
    runner says when it evaluates; each hand-over line comes after the trial's statuses."""
    shown = toy.RecordingProgress()
    runner.run(RunConfig("bad-then-good", "toy-reach", seed=0, max_trials=10, eval_episodes=3), progress=shown)
    assert shown.events == [
        "useless rollout 1", "evaluating the policy of trial 1 (3 episodes)", "hand-over 1",
        "useless rollout 2", "evaluating the policy of trial 2 (3 episodes)", "hand-over 2",
        "evaluating the policy of trial 3 (3 episodes)", "hand-over 3",
    ]


def test_rich_progress_shows_the_status_until_the_next_hand_over():
    console = Console(record=True, width=200, force_terminal=False)
    bar = RichProgress(console=console)
    bar.start("pilco on cartpole", 10, "trials")
    try:
        bar.status("policy search: 12/300 J + dJ, J [41.20]")  # brackets stay text (no rich markup)
        console.print(bar._progress.get_renderable())
        bar.update({"trial": 1, "interaction_seconds": 4.0, "eval_success_rate": 0.0, "eval_cost": 30.0, "wall_seconds": 5.0}, 1)
        console.print(bar._progress.get_renderable())
    finally:
        bar.finish("done")
    bars = [line for line in console.export_text().splitlines() if line.startswith("pilco on cartpole")]
    assert len(bars) == 2
    assert bars[0].rstrip().endswith("0/10 trials 0:00:00 policy search: 12/300 J + dJ, J [41.20]")
    assert "J + dJ" not in bars[1]
    Learner.report_status(toy.Greedy(toy.ToyReach().spec), "nowhere to go")  # no sink: nothing happens
    # on an 80-column terminal a long status is cut short; the elapsed time stays whole
    narrow = Console(record=True, width=80, force_terminal=False)
    bar = RichProgress(console=narrow)
    bar.start("pilco on double-pendulum", 40, "trials")
    bar.status("policy search: 120/300 J + dJ, J 41.20")
    narrow.print(bar._progress.get_renderable())
    bar.finish("done")
    line = narrow.export_text().splitlines()[0].rstrip()
    assert " 0/40 trials 0:00:00 policy search: " in line and line.endswith("…") and len(line) <= 80


def test_evaluation_steps_are_not_counted(toy_plugins):
    few = runner.run(RunConfig("bad-then-good", "toy-reach", seed=0, max_trials=10, eval_episodes=1))
    many = runner.run(RunConfig("bad-then-good", "toy-reach", seed=0, max_trials=10, eval_episodes=40))
    assert few.interaction_seconds == many.interaction_seconds == 12.0
    assert [h["interaction_seconds"] for h in few.history] == [4.0, 8.0, 12.0]


def test_unsolved_run_has_no_time_to_success(toy_plugins):
    result = runner.run(RunConfig("bad-then-good", "toy-reach", learner_options={"bad_trials": 5}, max_trials=2))
    assert not result.solved
    assert result.interaction_time_to_success is None and result.trials_to_success is None
    assert result.stop_reason == "max trials"


def test_budget_stops_a_learner_that_never_hands_over(toy_plugins):
    tracker = MemoryTracker()
    result = runner.run(RunConfig("greedy", "toy-reach", budget_seconds=10.0), tracker=tracker)
    assert result.stop_reason == "budget" and not result.solved
    assert result.interaction_seconds == 10.0  # 20 steps of 0.5 s, not one more
    assert tracker.status == "FINISHED" and tracker.tags["solved"] == "false"
    assert "interaction_time_to_success_seconds" not in tracker.metrics


def test_interaction_refuses_steps_beyond_budget():
    task = toy.ToyReach()
    interaction = Interaction(task.make_env(), task.spec, budget_seconds=1.0)
    interaction.reset()
    interaction.step([0.0])
    interaction.step([0.0])
    from harness.errors import BudgetExhaustedError

    with pytest.raises(BudgetExhaustedError, match="budget of 1 s"):
        interaction.step([0.0])
    assert interaction.steps == 2 and interaction.seconds == 1.0
    assert len(interaction.episodes) == 1 and interaction.episodes[0].steps == 2


def test_interaction_as_env_counts_every_step():
    task = toy.ToyReach()
    interaction = Interaction(task.make_env(), task.spec)
    env = interaction.as_env()
    env.reset()
    for _ in range(5):
        env.step(np.array([0.1]))
    assert interaction.steps == 5


def test_nan_policy_fails_the_run_with_a_clear_error(toy_plugins):
    tracker = MemoryTracker()
    with pytest.raises(InvalidActionError, match="NaN"):
        runner.run(RunConfig("nan", "toy-reach", max_trials=1), tracker=tracker)
    assert tracker.status == "FAILED"


def test_crash_marks_run_failed_and_keeps_what_was_logged(toy_plugins):
    tracker = MemoryTracker()
    with pytest.raises(RuntimeError, match="boom"):
        runner.run(RunConfig("crashing", "toy-reach", max_trials=5), tracker=tracker)
    assert tracker.status == "FAILED"
    assert [step for step, _ in tracker.metrics["eval_success_rate"]] == [1]
    assert any(a == "episodes" for _, a in tracker.artifacts)


def test_learner_metrics_are_logged_per_trial(toy_plugins):
    tracker = MemoryTracker()
    runner.run(RunConfig("bad-then-good", "toy-reach", max_trials=10), tracker=tracker)
    assert tracker.metrics["J_after"] == [(1, 1.0), (2, 1.0)]
    # where the wall time goes: the harness times each trial's evaluation
    assert [step for step, _ in tracker.metrics["eval_seconds"]] == [step for step, _ in tracker.metrics["wall_seconds"]]
    assert all(0.0 < v < tracker.metrics["wall_seconds"][-1][1] for _, v in tracker.metrics["eval_seconds"])
    assert tracker.params["learner.bad_trials"] == "2"


def test_same_seed_same_history(toy_plugins):
    a = runner.run(RunConfig("bad-then-good", "toy-reach", seed=11, max_trials=4))
    b = runner.run(RunConfig("bad-then-good", "toy-reach", seed=11, max_trials=4))
    strip = lambda h: [{k: v for k, v in r.items() if k not in ("wall_seconds", "eval_seconds")} for r in h]
    assert strip(a.history) == strip(b.history)


class TestToyTaskConformance(TaskConformance):
    task_cls = toy.ToyReach


class TestBadThenGoodConformance(LearnerConformance):
    learner_cls = toy.BadThenGood
    task_name = "cartpole"


def test_conformance_detects_a_broken_reward():
    from harness.testing import check_task_env

    class WrongReward(toy.ToyReach):
        def make_env(self, render_mode=None):
            env = super().make_env()
            step = env.step

            def bad_step(action):
                obs, reward, term, trunc, info = step(action)
                return obs, reward + 0.5, term, trunc, info

            env.step = bad_step
            return env

    with pytest.raises(AssertionError, match="reward"):
        check_task_env(WrongReward())


def test_conformance_detects_a_learner_that_ignores_the_budget():
    from harness.errors import BudgetExhaustedError
    from harness.testing import check_learner

    class Swallower(toy.Greedy):
        def learn(self, interaction):
            try:
                while True:
                    interaction.rollout(toy.Proportional(0.0))
            except BudgetExhaustedError:
                pass
            while True:
                yield toy.Proportional(0.0)

    with pytest.raises(AssertionError):
        check_learner(Swallower, toy.ToyReach())


def test_progress_line_says_where_the_trials_wall_time_went():
    from harness.progress import format_record
    from plugins.pilco.learner import Pilco

    record = {"trial": 3, "max_trials": 10, "interaction_seconds": 12.0, "eval_success_rate": 0.3, "eval_cost": 31.2,
              "J_after": 25.1, "wall_seconds": 42.4}
    logs = Pilco.logs  # what PILCO declares it logs: J shown, GP and policy search timed
    assert format_record(record, logs=logs) == "trial 3/10 | 12.0 s interaction | success 30% | eval cost 31.20 | J 25.10 | wall 42 s"
    assert format_record(record) == "trial 3/10 | 12.0 s interaction | success 30% | eval cost 31.20 | wall 42 s"  # declared nothing
    record.update(model_train_seconds=3.2, policy_opt_seconds=30.4, eval_seconds=1.6)
    assert format_record(record, logs=logs).endswith("| wall 42 s (GP 3 s, policy 30 s, eval 2 s)")
    assert format_record(record).endswith("| wall 42 s (eval 2 s)")
    # after the first hand-over the line gives the trial's own wall time (since the last hand-over)
    assert format_record(record, previous_wall=5.0, logs=logs).endswith("| wall 42 s (trial 37 s: GP 3 s, policy 30 s, eval 2 s)")
    del record["model_train_seconds"], record["policy_opt_seconds"], record["eval_seconds"]
    assert format_record(record, previous_wall=5.0, logs=logs).endswith("| wall 42 s (trial 37 s)")
    # a metric declared with a format spec: PILCO's planning horizon in steps
    assert "| J 25.10 | H 40 | wall 42 s" in format_record({**record, "planning_horizon": 40.0}, logs=logs)
    # a run limited by interaction time shows how much of its budget it has used
    budgeted = {**record, "max_trials": None, "budget_seconds": 2000.0}
    assert format_record(budgeted).startswith("trial 3 | 12.0/2000 s interaction | success 30%")


def test_saved_episodes_load_back_equal(tmp_path):
    rng = np.random.default_rng(0)
    episodes = [
        Episode(observations=rng.normal(size=(steps + 1, 3)), states=rng.normal(size=(steps + 1, 3)),
                actions=rng.normal(size=(steps, 1)), costs=rng.random(steps), terminated=terminated)
        for steps, terminated in [(5, False), (3, True), (7, False)]
    ]
    loaded = runner.load_episodes(runner.save_episodes(episodes, tmp_path / "episodes.npz"))
    assert len(loaded) == 3
    for a, b in zip(episodes, loaded):
        for key in ("observations", "states", "actions", "costs"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        assert a.terminated == b.terminated


def test_loading_a_missing_episodes_file_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.npz"):
        runner.load_episodes(tmp_path / "nothing.npz")
