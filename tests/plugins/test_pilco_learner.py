"""Smoke test of the PILCO learner end to end (the full learning runs are benchmarks, not CI)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from harness.discovery import load_learner
from harness.errors import NumericalError, OptionError
from harness.runner import RunConfig, run
from harness.testing import LearnerConformance
from harness.tracking import MemoryTracker
from plugins.pilco.learner import PRESETS, Pilco, PilcoMean
from plugins.pilco.policy import layout_for, transitions
from tasks.cartpole import CartPole
from tests.harness.toy import RecordingProgress

# restart_tol 0: the cart-pole preset's restarts off, so that each test counts the searches of its own mechanism
TINY = {"num_centres": "5", "policy_max_evaluations": "15", "gp_max_evals": "40", "plots": "true", "restart_tol": "0"}


def test_pilco_smoke_on_short_cartpole():
    tracker, shown = MemoryTracker(), RecordingProgress()
    result = run(
        RunConfig("pilco", "cartpole", seed=0, learner_options=TINY, task_options={"horizon": 15}, max_trials=2, eval_episodes=2),
        tracker=tracker, progress=shown,
    )
    # what `harness bench` shows during a trial: GP training, then the search's count and best J so far
    first = shown.events[:shown.events.index("hand-over 1")]
    assert first[0] == "GP training on 15 transitions"
    searched = [e for e in first if e.startswith("policy search: ")]
    counts = [int(e.split(": ")[1].split("/")[0]) for e in searched]
    assert counts == list(range(len(counts))) and searched[-1].startswith(f"policy search: {counts[-1]}/15 J + dJ")
    assert counts[-1] == int(dict(tracker.metrics["policy_evaluations"])[1]) - 1  # the initial J is number 0
    assert searched[-1].endswith(f"J {dict(tracker.metrics['J_after'])[1]:.2f}")
    assert "GP training on 30 transitions" in shown.events
    assert result.trials == 2 and result.interaction_seconds == pytest.approx(2 * 15 * 0.1)
    for step in (1, 2):
        before = dict(tracker.metrics["J_before"])[step]
        after = dict(tracker.metrics["J_after"])[step]
        assert after <= before  # policy search never ends worse than it started
    assert dict(tracker.metrics["J_after"])[1] < dict(tracker.metrics["J_before"])[1]
    for key in ("n_data", "model_train_seconds", "policy_opt_seconds", "line_searches", "predicted_cost", "gp_noise_std_0"):
        assert key in tracker.metrics, key
    assert dict(tracker.metrics["n_data"]) == {1: 15.0, 2: 30.0}
    assert dict(tracker.metrics["policy_parameters"])[1] == 5 * 5 + 5 + 5  # n_c p + n_c F + F p
    # the same policy and model by Monte Carlo: near the closed form at this short horizon, within [0, H]
    for step in (1, 2):
        sampled, closed = dict(tracker.metrics["J_sampled"])[step], dict(tracker.metrics["J_after"])[step]
        assert 0.0 <= sampled <= 15.0 and abs(sampled - closed) < 0.1 * closed
    names = {p.name for p, _ in tracker.artifacts}
    assert {"model_trial001.pt", "gp_hyperparameters_trial001.json", "prediction_trial001.png", "pilco_settings.json"} <= names
    assert tracker.status == "FINISHED"
    folder = next(folder for p, folder in tracker.artifacts if p.name == "pilco_settings.json")
    settings = json.loads((tracker.root / (folder or "") / "pilco_settings.json").read_text())
    assert settings["preset"]["num_centres"] == 5 and settings["preset"]["policy_max_evaluations"] == 15
    assert settings["preset"]["policy_max_iterations"] == 150 and settings["planning_horizon"] == 15


def test_policy_search_budget_comes_from_the_task_preset():
    """The unicycle's reference budget is 150 J evaluations in all; options override presets."""
    from tasks.unicycle import Unicycle

    unicycle = Pilco(Unicycle().spec, {}, seed=0)
    assert (unicycle.preset.policy_max_iterations, unicycle.preset.policy_max_evaluations) == (150, 150)
    cartpole = Pilco(CartPole().spec, {"policy_max_iterations": "40"}, seed=0)
    assert (cartpole.preset.policy_max_iterations, cartpole.preset.policy_max_evaluations) == (40, 300)


def test_gp_training_budgets_reach_the_dynamics_model(monkeypatch):
    """gp_fitc_evals, gp_hyper_subset, gp_pseudo_subset and gp_refresh_pseudo configure the GPModel the learner trains
    (FITC from 20 points here)."""
    import plugins.pilco.gp as gp_module
    from plugins.pilco.gp import GPModel

    fits = []

    class Recording(GPModel):
        def fit(self, *args, **kwargs):
            report = super().fit(*args, **kwargs)
            fits.append((self.max_evals_fitc, self.hyper_subset, self.pseudo_subset, report.n_hyper_points, report.sparse,
                         self.refresh_pseudo))
            return report

    monkeypatch.setattr(gp_module, "GPModel", Recording)  # the learner imports it at first use
    options = {**TINY, "sparse_threshold": "20", "num_pseudo": "10", "gp_fitc_evals": "7", "gp_hyper_subset": "12",
               "gp_pseudo_subset": "25", "gp_refresh_pseudo": "true"}
    run(RunConfig("pilco", "cartpole", seed=0, learner_options=options, task_options={"horizon": 15}, max_trials=2, eval_episodes=1),
        tracker=MemoryTracker())
    # trial 1: 15 points, a full GP on all of them; trial 2: 30 > 20, FITC, hyperparameters on 12 random points
    assert fits == [(7, 12, 25, 15, False, True), (7, 12, 25, 12, True, True)]
    default = Pilco(CartPole().spec, {}, seed=0)
    assert (default.options["gp_fitc_evals"], default.options["gp_hyper_subset"], default.options["gp_pseudo_subset"],
            default.options["gp_refresh_pseudo"]) == (100, None, None, False)


def test_gp_data_smoothed_trains_the_gp_again_on_the_smoothed_episodes(fit_inputs):
    """gp_data=smoothed: after the fit on the observations, smooth_rounds more fits, each on transitions of
    episodes smoothed through the GP (not the observations: they move by about the noise), logged per trial;
    the GP planned with is the last one. The default trains on the observations only."""
    fits = fit_inputs
    trackers = {}
    for label, extra in (("default", {}), ("smoothed", {"gp_data": "smoothed", "smooth_rounds": "2"})):
        fits.clear()
        trackers[label] = MemoryTracker()
        run(RunConfig("pilco", "cartpole", seed=0, learner_options={**TINY, "plots": "false", "sample_particles": "0", **extra},
                      task_options={"horizon": 15}, max_trials=2, eval_episodes=1), tracker=trackers[label])
        trackers[label].fits = list(fits)
    assert len(trackers["default"].fits) == 2 and "smoothing_obs_rms" not in trackers["default"].metrics
    smoothed = trackers["smoothed"].fits
    assert len(smoothed) == 2 * 3  # per trial: observations, then two rounds
    first, rounds = smoothed[0], smoothed[1:3]
    assert np.array_equal(first, trackers["default"].fits[0])  # the same observations as the default's first fit
    for x in rounds:
        assert x.shape == first.shape and 0 < np.abs(x - first).max() < 0.2  # states moved, by about the noise (0.01)
    metrics = trackers["smoothed"].metrics
    assert set(dict(metrics["smoothing_obs_rms"])) == {1, 2} and all(0 < v < 5 for v in dict(metrics["smoothing_obs_rms"]).values())
    gp_seconds, smoothing_seconds = dict(metrics["model_train_seconds"]), dict(metrics["smoothing_seconds"])
    assert set(smoothing_seconds) == {1, 2} and all(0 < smoothing_seconds[k] < gp_seconds[k] for k in smoothing_seconds)
    assert dict(metrics["J_after"]) != dict(trackers["default"].metrics["J_after"])


def test_gp_data_must_be_a_known_choice():
    with pytest.raises(OptionError, match="gp_data"):
        Pilco(CartPole().spec, {"gp_data": "filtered"}, seed=0)


@pytest.mark.parametrize("learner", ["pilco", "mc-pilco"])
def test_gp_data_smoothed_needs_measurement_noise_and_says_so_at_construction(learner):
    """Both learners refuse smoothing on a noise-free task when they are built, with the fix in the message;
    with noise (the default) the same option is accepted."""
    from plugins.mc_pilco.learner import McPilco

    cls = {"pilco": Pilco, "mc-pilco": McPilco}[learner]
    with pytest.raises(OptionError, match=r"gp_data=smoothed on cartpole: .*task\.measurement_noise > 0"):
        cls(CartPole(measurement_noise=0.0).spec, {"gp_data": "smoothed"}, seed=0)
    cls(CartPole().spec, {"gp_data": "smoothed"}, seed=0)
    cls(CartPole(measurement_noise=0.0).spec, {}, seed=0)  # observations: no noise needed


def test_planning_basis_bounds_the_basis_the_policy_search_plans_with():
    """planning_basis=10: J is computed on a 10-point FITC posterior of the trained GP (15 and 30 points here),
    logged per trial; by default the whole model (a full GP: all its points)."""
    trackers = {}
    for label, extra in (("default", {}), ("reduced", {"planning_basis": "10"})):
        trackers[label] = MemoryTracker()
        run(RunConfig("pilco", "cartpole", seed=0, learner_options={**TINY, "plots": "false", "sample_particles": "0", **extra},
                      task_options={"horizon": 15}, max_trials=2, eval_episodes=1), tracker=trackers[label])
    assert dict(trackers["default"].metrics["planning_basis"]) == {1: 15.0, 2: 30.0}
    assert dict(trackers["reduced"].metrics["planning_basis"]) == {1: 10.0, 2: 10.0}
    assert dict(trackers["reduced"].metrics["J_after"]) != dict(trackers["default"].metrics["J_after"])


def test_planning_horizon_and_cost_width_come_from_the_task_preset():
    """dm_control cart-pole plans over 40 steps with a 0.42 m width; other tasks use the task's; options override."""
    from tasks.dmc_cartpole import DMCCartpole

    dmc = Pilco(DMCCartpole().spec, {}, seed=0)
    assert (dmc.horizon, dmc.cost_width) == (40, 0.42) and dmc.spec.horizon == 100
    cartpole = Pilco(CartPole().spec, {}, seed=0)
    assert (cartpole.horizon, cartpole.cost_width) == (CartPole().spec.horizon, None)
    overridden = Pilco(DMCCartpole().spec, {"planning_horizon": "100", "cost_width": "0.25"}, seed=0)
    assert (overridden.horizon, overridden.cost_width) == (100, 0.25)


def test_fresh_start_tolerance_comes_from_the_task_preset_and_zero_turns_it_off():
    from tasks.dmc_cartpole import DMCCartpole

    assert Pilco(DMCCartpole().spec, {}, seed=0).fresh_start_tol == 0.05
    assert Pilco(DMCCartpole().spec, {}, seed=0).options_used()["fresh_start_tol"] == 0.05
    assert Pilco(DMCCartpole().spec, {"fresh_start_tol": "0"}, seed=0).fresh_start_tol is None
    assert Pilco(CartPole().spec, {}, seed=0).fresh_start_tol is None
    assert Pilco(CartPole().spec, {"fresh_start_tol": "0.1"}, seed=0).fresh_start_tol == 0.1


def test_restart_tolerance_comes_from_the_task_preset_and_zero_turns_it_off(monkeypatch):
    from dataclasses import replace

    from plugins.pilco import presets
    from tasks.dmc_cartpole import DMCCartpole

    assert Pilco(CartPole().spec, {}, seed=0).restart_tol == 0.05  # the cart-pole preset's (findings_cartpole.md)
    assert Pilco(DMCCartpole().spec, {}, seed=0).restart_tol is None
    assert Pilco(DMCCartpole().spec, {"restart_tol": "0.05"}, seed=0).restart_tol == 0.05
    monkeypatch.setitem(presets.PRESETS, "cartpole", replace(presets.PRESETS["cartpole"], restart_tol=0.07))
    assert Pilco(CartPole().spec, {}, seed=0).restart_tol == 0.07
    assert Pilco(CartPole().spec, {}, seed=0).options_used()["restart_tol"] == 0.07
    assert Pilco(CartPole().spec, {"restart_tol": "0"}, seed=0).restart_tol is None
    assert Pilco(CartPole().spec, {"restart_tol": "0.1"}, seed=0).restart_tol == 0.1


def test_plan_with_noise_uses_the_tasks_measurement_noise_and_refuses_trig_policies():
    """The unicycle's policy sees raw states: planning adds the task's observation noise to its
    input. Cart-pole's sees sin/cos of the angle: a clear option error naming the fix."""
    from tasks.unicycle import Unicycle

    spec = Unicycle().spec
    learner = Pilco(spec, {"plan_with_noise": "true"}, seed=0)
    np.testing.assert_array_equal(learner.policy_noise_std, spec.measurement_noise_std)
    assert Pilco(spec, {"plan_with_noise": "false"}, seed=0).policy_noise_std is None
    with pytest.raises(OptionError, match="plan_with_noise on cartpole: .*sin/cos of angles.*drop --set plan_with_noise=true"):
        Pilco(CartPole().spec, {"plan_with_noise": "true"}, seed=0)


def test_the_unicycles_preset_plans_with_noise_over_a_growing_horizon_and_each_part_can_be_switched_off():
    """The unicycle's defaults are the settings its tuning seeds were run with (planning noise, 20 steps doubled
    after a trial whose real cost per planned step was below 0.2): a default run uses (and logs as
    used.learner.*) what a run with those options given uses. Each is an option that can be given
    (``plan_with_noise=false``, ``grow_horizon_below=0``, ``grow_horizon_on=prediction``); other tasks keep the
    reference's settings, and mc-pilco ignores the PILCO learner's schedule."""
    from plugins.mc_pilco.learner import McPilco
    from tasks.unicycle import Unicycle

    spec = Unicycle().spec
    default = Pilco(spec, {}, seed=0)
    assert default.horizon == 20 and default.schedule.grow_below == 0.2 and default.schedule.rule == "realised"
    np.testing.assert_array_equal(default.policy_noise_std, spec.measurement_noise_std)
    given = Pilco(spec, {"plan_with_noise": "true", "planning_horizon": "20", "grow_horizon_below": "0.2",
                         "grow_horizon_on": "realised"}, seed=0)
    keys = ("plan_with_noise", "planning_horizon", "grow_horizon_below", "grow_horizon_on")
    assert {k: default.options_used()[k] for k in keys} == {k: given.options_used()[k] for k in keys} == {
        "plan_with_noise": True, "planning_horizon": 20, "grow_horizon_below": 0.2, "grow_horizon_on": "realised"}
    off = Pilco(spec, {"plan_with_noise": "false", "grow_horizon_below": "0", "planning_horizon": "67"}, seed=0)
    assert off.policy_noise_std is None and off.schedule.grow_below is None and off.horizon == 67
    assert {k: off.options_used()[k] for k in keys} == {"plan_with_noise": False, "planning_horizon": 67,
                                                         "grow_horizon_below": None, "grow_horizon_on": "realised"}
    assert Pilco(spec, {"grow_horizon_on": "prediction"}, seed=0).schedule.rule == "prediction"
    cartpole = Pilco(CartPole().spec, {}, seed=0)
    assert cartpole.policy_noise_std is None and cartpole.schedule.grow_below is None
    assert cartpole.options_used()["plan_with_noise"] is False and cartpole.schedule.rule == "prediction"
    assert McPilco(spec, {}, seed=0).horizon == spec.horizon


def test_horizon_schedule_doubles_up_to_the_task_horizon_when_the_policy_does_well():
    from types import SimpleNamespace

    from plugins.pilco.horizon import next_planning_horizon

    good, poor = SimpleNamespace(J_after=1.0), SimpleNamespace(J_after=10.0)  # 0.05 and 0.5 per step over 20
    assert next_planning_horizon(20, 67, good, 0.1) == 40
    assert next_planning_horizon(40, 67, good, 0.1) == 67 and next_planning_horizon(67, 67, good, 0.1) == 67
    assert next_planning_horizon(20, 67, poor, 0.1) == 20
    assert next_planning_horizon(20, 67, good, None) == 20 and next_planning_horizon(20, 67, None, 0.1) == 20
    assert next_planning_horizon(20, 67, SimpleNamespace(J_after=float("nan")), 0.1) == 20  # a failed search's J


def test_survival_rule_doubles_the_horizon_only_after_an_episode_that_stayed_up_for_all_planned_steps():
    from harness.task import Episode
    from plugins.pilco.horizon import survived_horizon

    def episode(steps: int, terminated: bool) -> Episode:
        return Episode(np.zeros((steps + 1, 2)), np.zeros((steps + 1, 2)), np.zeros((steps, 1)), np.zeros(steps), terminated)

    assert survived_horizon(20, 67, episode(12, True)) == 20  # fell within the planned steps
    assert survived_horizon(20, 67, episode(19, True)) == 20
    assert survived_horizon(20, 67, episode(20, True)) == 40  # fell after them
    assert survived_horizon(20, 67, episode(67, False)) == 40
    assert survived_horizon(40, 67, episode(45, True)) == 67 and survived_horizon(67, 67, episode(67, False)) == 67


def test_survival_rule_grows_the_horizon_in_a_run_and_is_logged():
    """Cart-pole at 10 steps is never aborted: under the survival rule every trial doubles the planning
    horizon, 3 -> 6 -> 10, from the trial after the first learned policy was applied."""
    options = {"num_centres": "4", "policy_max_evaluations": "4", "gp_max_evals": "20", "plots": "false",
               "sample_particles": "0", "planning_horizon": "3", "grow_horizon_below": "1", "grow_horizon_on": "survival"}
    tracker = MemoryTracker()
    run(RunConfig("pilco", "cartpole", seed=0, learner_options=options, task_options={"horizon": 10}, max_trials=3,
                  eval_episodes=1), tracker=tracker)
    assert [h for _, h in sorted(tracker.metrics["planning_horizon"])] == [3.0, 6.0, 10.0]
    assert tracker.params["learner.grow_horizon_on"] == "survival"
    with pytest.raises(OptionError, match="grow_horizon_on"):
        Pilco(CartPole().spec, {"grow_horizon_on": "always"}, seed=0)


def test_realised_rule_doubles_the_horizon_only_after_an_episode_cheap_over_the_planned_steps():
    from harness.task import Episode
    from plugins.pilco.horizon import realised_cost_per_step, realised_horizon

    def episode(costs: list[float], terminated: bool) -> Episode:
        steps = len(costs)
        return Episode(np.zeros((steps + 1, 2)), np.zeros((steps + 1, 2)), np.zeros((steps, 1)), np.array(costs), terminated)

    cheap_then_fall = episode([0.1] * 20 + [1.0] * 5, True)  # fell after the 20 planned steps: only those count
    assert realised_cost_per_step(20, cheap_then_fall) == pytest.approx(0.1)
    assert realised_horizon(20, 67, cheap_then_fall, 0.2) == 40 and realised_horizon(20, 67, cheap_then_fall, 0.1) == 20
    # fell at step 10 (last cost 0.9): 9 x 0.1 + 0.9, and 0.9 held for the 10 steps not taken -> 10.8 / 20
    early_fall = episode([0.1] * 9 + [0.9], True)
    assert realised_cost_per_step(20, early_fall) == pytest.approx(10.8 / 20)
    assert realised_horizon(20, 67, early_fall, 0.5) == 20 and realised_horizon(20, 67, early_fall, 0.6) == 40
    # stayed up all along but far from the goal: the survival rule would grow, this one does not
    upright_far = episode([0.3] * 67, False)
    assert realised_horizon(20, 67, upright_far, 0.2) == 20
    assert realised_horizon(40, 67, episode([0.0] * 67, False), 0.2) == 67 and realised_horizon(67, 67, episode([0.0] * 67, False), 0.2) == 67


def test_horizon_schedule_applies_each_rule_at_its_point_only():
    """A real-episode rule acts after the rollout and ignores the search; the prediction rule the other way round."""
    from types import SimpleNamespace

    from harness.task import Episode
    from plugins.pilco.horizon import HorizonSchedule

    cheap = Episode(np.zeros((21, 2)), np.zeros((21, 2)), np.zeros((20, 1)), np.full(20, 0.01), False)
    good_search = SimpleNamespace(J_after=0.1)
    for rule, after_rollout, after_search in [("prediction", 20, 40), ("survival", 40, 40), ("realised", 40, 40)]:
        schedule = HorizonSchedule(20, 67, 0.05, rule)
        assert schedule.after_rollout(cheap) == pytest.approx(0.01) and schedule.horizon == after_rollout, rule
        schedule.after_search(good_search)
        assert schedule.horizon == after_search, rule
    fixed = HorizonSchedule(20, 67, None, "realised")  # no threshold: the horizon stays
    fixed.after_rollout(cheap), fixed.after_search(good_search)
    assert fixed.horizon == 20
    with pytest.raises(ValueError, match="not one of prediction, survival, realised"):
        HorizonSchedule(20, 67, 0.05, "always")


@pytest.mark.parametrize("below,expected", [("10", [3.0, 6.0, 10.0]), ("1e-12", [3.0, 3.0, 3.0])])
def test_realised_rule_in_a_run_follows_the_logged_rollout_cost(below, expected):
    """Cart-pole's cost per step lies in (0, 1]: a threshold of 10 doubles the planning horizon after every
    rollout of a learned policy (3 -> 6 -> 10), 1e-12 never; the cost it judged by is logged per trial."""
    options = {"num_centres": "4", "policy_max_evaluations": "4", "gp_max_evals": "20", "plots": "false",
               "sample_particles": "0", "planning_horizon": "3", "grow_horizon_below": below, "grow_horizon_on": "realised"}
    tracker = MemoryTracker()
    run(RunConfig("pilco", "cartpole", seed=0, learner_options=options, task_options={"horizon": 10}, max_trials=3,
                  eval_episodes=1), tracker=tracker)
    assert [h for _, h in sorted(tracker.metrics["planning_horizon"])] == expected
    rollout = sorted(tracker.metrics["rollout_cost_per_step"])  # from trial 2: trial 1 follows the random rollouts only
    assert [step for step, _ in rollout] == [2, 3] and all(0.0 < c <= 1.0 for _, c in rollout)


def test_entry_points_and_ablation_flag():
    assert load_learner("pilco") is Pilco and load_learner("pilco-mean") is PilcoMean
    assert not Pilco.mean_only and PilcoMean.mean_only
    assert PilcoMean.options == Pilco.options  # everything else equal


def test_transitions_drop_the_step_that_left_the_region():
    from harness.task import Episode

    spec = __import__("tasks.cartpole", fromlist=["CartPole"]).CartPole().spec
    layout = layout_for(spec, PRESETS["cartpole"])
    obs = np.arange(5 * 4, dtype=float).reshape(5, 4) / 10
    ep = Episode(obs, obs, np.ones((4, 1)), np.zeros(4), terminated=True)
    x, y = transitions([ep], layout)
    assert x.shape == (3, 6) and y.shape == (3, 4)
    assert np.allclose(y, 0.4)  # x_{t+1} - x_t
    assert np.allclose(x[0, :3], obs[0, :3]) and np.allclose(x[0, 3:5], [np.sin(0.3), np.cos(0.3)]) and x[0, 5] == 1.0


class TestPilcoConformance(LearnerConformance):
    learner_cls = Pilco
    task_name = "cartpole"
    task_options = {"horizon": 10}
    learner_options = {"num_centres": 3, "policy_max_evaluations": 3, "gp_max_evals": 10, "plots": False}


def test_same_seed_gives_identical_metrics():
    config = RunConfig("pilco", "cartpole", seed=3, learner_options=TINY, task_options={"horizon": 10}, max_trials=2, eval_episodes=2)
    a, b = run(config), run(config)
    strip = lambda h: [{k: v for k, v in r.items() if "seconds" not in k or k == "interaction_seconds"} for r in h]
    assert strip(a.history) == strip(b.history)
    c = run(RunConfig("pilco", "cartpole", seed=4, learner_options=TINY, task_options={"horizon": 10}, max_trials=2, eval_episodes=2))
    assert strip(c.history) != strip(a.history)


@pytest.mark.parametrize("error", [torch.linalg.LinAlgError, NumericalError])
def test_a_degenerate_prediction_does_not_end_the_run(monkeypatch, error):
    """The kept policy's predicted cost can fail (propagated covariance no longer definite): the
    trial is still handed over, without the plot, and ``prediction_failed`` says so."""
    from plugins.pilco.objective import PolicyObjective

    def broken(self):
        raise error("linalg.cholesky: the input is not positive-definite")

    monkeypatch.setattr(PolicyObjective, "predicted_costs", broken)
    tracker = MemoryTracker()
    result = run(
        RunConfig("pilco", "cartpole", seed=0, learner_options=TINY, task_options={"horizon": 10}, max_trials=2, eval_episodes=1),
        tracker=tracker,
    )
    assert result.trials == 2 and tracker.status == "FINISHED"
    assert dict(tracker.metrics["prediction_failed"]) == {1: 1.0, 2: 1.0}
    assert "predicted_cost" not in tracker.metrics
    assert not any(p.name.startswith("prediction_trial") for p, _ in tracker.artifacts)


def test_fresh_start_compares_the_prediction_with_a_fall_held_as_evaluations_count_it():
    """An episode that fell at step 8 of 20 predicted steps: its 8 costs, then its last one for the 12 steps not
    taken (the prediction charges the fallen states too); an episode longer than the prediction counts its first 20."""
    from types import SimpleNamespace

    from harness.task import Episode
    from plugins.pilco.learner import _realised_sum

    def episode(costs: list[float], terminated: bool) -> Episode:
        n = len(costs)
        return Episode(np.zeros((n + 1, 2)), np.zeros((n + 1, 2)), np.zeros((n, 1)), np.array(costs), terminated)

    predicted = (np.full(20, 0.65), np.zeros(20))
    fell = SimpleNamespace(episodes=[episode([0.5] * 7 + [0.9], True)])
    assert _realised_sum(fell, predicted) == pytest.approx(7 * 0.5 + 0.9 + 12 * 0.9)
    rode = SimpleNamespace(episodes=[episode([0.1] * 67, False)])
    assert _realised_sum(rode, predicted) == pytest.approx(2.0)
    assert _realised_sum(fell, None) is None and _realised_sum(SimpleNamespace(episodes=[]), predicted) is None


def test_stalled_rule_needs_a_still_J_and_a_confirmed_prediction():
    from plugins.pilco.learner import stalled

    assert stalled(28.4, 28.5, predicted=28.37, realised=28.26, tol=0.05)  # the stuck cart-pole seed 11 at trial 9
    assert not stalled(20.0, 28.5, predicted=28.37, realised=28.26, tol=0.05)  # J still moving
    assert not stalled(28.4, 28.5, predicted=12.0, realised=28.26, tol=0.05)  # the model was wrong: new data will move it
    assert not stalled(28.4, 28.5, predicted=28.37, realised=28.26, tol=None)  # off by default
    assert not stalled(28.4, None, predicted=28.37, realised=28.26, tol=0.05)  # no previous search
    assert not stalled(28.4, 28.5, predicted=None, realised=None, tol=0.05)
    assert not stalled(float("nan"), 28.5, predicted=28.37, realised=28.26, tol=0.05)


@pytest.fixture
def searches(monkeypatch) -> list:
    """Every policy search's result, in order, recorded as the learner runs them."""
    import plugins.pilco.policy_search as search_module

    recorded = []
    original = search_module.optimise_policy

    def recording(*args, **kwargs):
        result = original(*args, **kwargs)
        recorded.append(result)
        return result

    monkeypatch.setattr(search_module, "optimise_policy", recording)  # the learner imports it at each search
    return recorded


def test_fresh_start_keeps_the_lower_J_of_the_two_searches(searches):
    """With a tolerance that always holds, every trial after the first also searches from fresh
    parameters; the reported J is the lower of the two searches' (recorded independently here), the
    metrics say which was kept, and both searches' time is counted."""
    tracker = MemoryTracker()
    options = dict(TINY, fresh_start_tol="1e9", plots="false")
    result = run(RunConfig("pilco", "cartpole", seed=1, learner_options=options, task_options={"horizon": 10}, max_trials=3,
                           eval_episodes=1), tracker=tracker)
    assert result.trials == 3
    fresh, kept = dict(tracker.metrics["fresh_start"]), dict(tracker.metrics["fresh_start_kept"])
    assert fresh == {1: 0.0, 2: 1.0, 3: 1.0} and len(searches) == 5
    J_after, J_fresh = dict(tracker.metrics["J_after"]), dict(tracker.metrics["J_fresh_start"])
    assert J_after[1] == searches[0].J_after and 1 not in J_fresh  # no fresh start, no value (NaN is not logged)
    for trial, (first, second) in zip((2, 3), (searches[1:3], searches[3:5])):
        assert J_fresh[trial] == second.J_after
        assert J_after[trial] == min(first.J_after, second.J_after)
        assert kept[trial] == float(second.J_after < first.J_after)
        assert dict(tracker.metrics["policy_evaluations"])[trial] == first.evaluations + second.evaluations


def test_early_starts_keep_the_lowest_J_of_all_starts_in_the_first_trials_only(searches):
    """early_starts=3 for the first 2 trials: those trials search three times (the controller handed over,
    then two fresh ones), the third trial once; a trial's reported J is the lowest of its searches'
    (recorded independently), early_start_kept names the search that gave it, J_early_starts_worst the
    highest, and all searches' evaluations are counted."""
    tracker = MemoryTracker()
    options = dict(TINY, early_starts="3", early_start_trials="2", plots="false")
    result = run(RunConfig("pilco", "cartpole", seed=4, learner_options=options, task_options={"horizon": 10}, max_trials=3,
                           eval_episodes=1), tracker=tracker)
    assert result.trials == 3 and len(searches) == 3 + 3 + 1
    J_after, kept = dict(tracker.metrics["J_after"]), dict(tracker.metrics["early_start_kept"])
    worst, evaluations = dict(tracker.metrics["J_early_starts_worst"]), dict(tracker.metrics["policy_evaluations"])
    assert set(kept) == {1, 2} and set(worst) == {1, 2}
    for trial, group in ((1, searches[0:3]), (2, searches[3:6])):
        Js = [s.J_after for s in group]
        assert J_after[trial] == min(Js) and kept[trial] == float(Js.index(min(Js)))
        assert worst[trial] == max(Js)
        assert evaluations[trial] == sum(s.evaluations for s in group)
    assert J_after[3] == searches[6].J_after and evaluations[3] == searches[6].evaluations
    assert len({s.J_after for s in searches[0:3]}) == 3  # the fresh starts are other controllers


def test_restarts_search_near_the_handed_policy_when_stalled_and_keep_the_lowest_J(searches):
    """With a restart tolerance that always holds, every trial after the first also searches from two perturbed
    copies of the policy its search handed over; the trial's J is the lowest of its three searches' (recorded
    independently), restart_kept names the one, J_restart_best is the restarts' lowest, and all evaluations count.
    The restarts start near the handed policy, not from scratch: their starting J is the handed policy's within
    the perturbation's reach, not a fresh controller's."""
    tracker = MemoryTracker()
    options = dict(TINY, restart_tol="1e9", restarts="2", plots="false")
    result = run(RunConfig("pilco", "cartpole", seed=2, learner_options=options, task_options={"horizon": 10}, max_trials=3,
                           eval_episodes=1), tracker=tracker)
    assert result.trials == 3 and len(searches) == 1 + 3 + 3
    restarted, kept = dict(tracker.metrics["restarted"]), dict(tracker.metrics["restart_kept"])
    J_after, best = dict(tracker.metrics["J_after"]), dict(tracker.metrics["J_restart_best"])
    evaluations = dict(tracker.metrics["policy_evaluations"])
    assert restarted == {1: 0.0, 2: 1.0, 3: 1.0} and set(kept) == {2, 3}
    for trial, group in ((2, searches[1:4]), (3, searches[4:7])):
        Js = [s.J_after for s in group]
        assert J_after[trial] == min(Js) and kept[trial] == float(Js.index(min(Js)))
        assert best[trial] == min(Js[1:])
        assert evaluations[trial] == sum(s.evaluations for s in group)
        assert all(s.J_before != group[0].J_after for s in group[1:])  # perturbed, not the handed policy itself


def test_perturbed_state_moves_each_parameter_tensor_by_its_own_spread():
    """perturbed_state: each parameter tensor plus scale x its spread (std, or magnitude for one entry) x N(0, 1) from
    the generator, in the controller's parameter order; scale 0 gives the parameters back; the controller is left
    as it was."""
    from plugins.pilco.policy import perturbed_state

    learner = Pilco(CartPole().spec, {"num_centres": "5"}, seed=0)
    controller = learner.new_controller(torch.Generator().manual_seed(0))
    before = {k: v.clone() for k, v in controller.state_dict().items()}
    moved = perturbed_state(controller, 0.1, torch.Generator().manual_seed(3))
    gen = torch.Generator().manual_seed(3)
    names = [name for name, _ in controller.named_parameters()]
    assert names and set(names) <= set(moved)
    for name, q in controller.named_parameters():
        spread = q.detach().abs().max() if q.numel() == 1 else q.detach().std()
        expected = q.detach() + 0.1 * spread * torch.randn(q.shape, generator=gen, dtype=q.dtype)
        assert torch.allclose(moved[name], expected, rtol=0, atol=1e-15) and not torch.equal(moved[name], q.detach())
    for k, v in controller.state_dict().items():
        assert torch.equal(v, before[k])
    same = perturbed_state(controller, 0.0, torch.Generator().manual_seed(3))
    assert all(torch.equal(same[k], before[k]) for k in before)


def test_early_starts_must_be_at_least_one():
    with pytest.raises(OptionError, match="early_starts"):
        Pilco(CartPole().spec, {"early_starts": "0"}, seed=0)


def test_a_run_makes_the_same_decisions_with_either_kernel():
    """The compiled Q contractions (numba, fused) and the torch reference, same seed: the same first two
    policies (J to 1e-7, then 5e-4; their evaluation costs to 1e-3), after which the runs part slowly.
    The kernels round differently (J ~1e-12 apart; numba takes its exp from NumPy, torch from its own,
    each within 1 ulp, fused from its own polynomial, within 2 ulp of NumPy's, and sums the exponent
    in another order than BLAS), so the L-BFGS searches take slightly different steps and the first
    policies differ in their last digits (J 3.5e-9 apart for numba, 7e-9 for fused); the GP of trial 2
    is trained on data that differ accordingly, and each search amplifies it. Measured when the fused
    kernel came: J apart 5.7e-5 (numba) and 1.9e-4 (fused) at trial 2, 7e-4 and 6.8e-3 at trial 3."""
    pytest.importorskip("numba")
    runs = {}
    for kernel in ("torch", "numba", "fused"):
        tracker = MemoryTracker()
        config = RunConfig("pilco", "cartpole", seed=2, learner_options=dict(TINY, kernel=kernel, plots="false"),
                           task_options={"horizon": 12}, max_trials=3, eval_episodes=2)
        runs[kernel] = (run(config, tracker=tracker), tracker)
    a, ta = runs["torch"]
    for kernel in ("numba", "fused"):  # the fused kernel's exp is its own (within 2 ulp of NumPy's)
        b, tb = runs[kernel]
        assert a.trials == b.trials == 3
        J_a, J_b = dict(ta.metrics["J_after"]), dict(tb.metrics["J_after"])
        cost_a, cost_b = dict(ta.metrics["eval_cost"]), dict(tb.metrics["eval_cost"])
        assert J_a.keys() == J_b.keys() == cost_a.keys() == cost_b.keys() == {1, 2, 3}
        for step, rel in ((1, 1e-7), (2, 5e-4), (3, 5e-2)):
            assert J_b[step] == pytest.approx(J_a[step], rel=rel), (kernel, step)
        for step in (1, 2):
            assert cost_b[step] == pytest.approx(cost_a[step], rel=1e-3), (kernel, step)
        assert dict(ta.metrics["n_data"]) == dict(tb.metrics["n_data"])
