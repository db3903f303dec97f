"""Reading a PILCO run back from an MLflow store (what the benchmarks that re-examine a run use)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from harness.errors import CheckpointError, TrackingError
from harness.runner import RunConfig, run
from plugins.pilco.objective import PolicyObjective
from plugins.pilco.policy import linear_policy_from_gain
from plugins.pilco.saved_run import SavedPilcoRun
from tasks.unicycle_lqr import riding_lqr

TINY = {"num_centres": "4", "policy_max_evaluations": "8", "gp_max_evals": "20", "plots": "false", "sample_particles": "0"}


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path_factory.mktemp("saved-run-store"))
    pilco = run(RunConfig("pilco", "cartpole", seed=0, learner_options=TINY, task_options={"horizon": 12}, max_trials=2,
                          eval_episodes=2), tracker=MlflowTracker(uri))
    other = run(RunConfig("random", "cartpole", seed=0, task_options={"horizon": 12}, max_trials=1, eval_episodes=2),
                tracker=MlflowTracker(uri))
    return uri, pilco, other


def test_a_saved_run_gives_back_its_task_settings_models_policies_and_episodes(stored):
    uri, pilco, _ = stored
    with SavedPilcoRun(pilco.run_id, uri, task="cartpole") as saved:
        assert saved.task.spec.horizon == 12  # the recorded task option, not the task's default
        assert saved.planning_horizon == 12 and saved.mean_only is False
        # the options left to the preset are logged with the values used beside them
        params = saved.params
        assert (params["learner.controller"], params["used.learner.controller"]) == ("None", "rbf")
        assert (params["learner.planning_horizon"], params["used.learner.planning_horizon"]) == ("None", "12")
        assert params["used.learner.sparse_threshold"] == "300" and "used.learner.num_centres" not in params  # set: logged as is
        assert saved.model_trials() == [1, 2] and saved.policy_trials() == [1, 2]
        episodes = saved.episodes()
        # the random rollout and trial 1's; the policy of trial 2 was only evaluated (the run ended there)
        assert len(episodes) == 2 and all(ep.steps == 12 for ep in episodes)
        model, policy = saved.model(2), saved.policy(2)
        assert saved.saved_model(2)["layout"] == policy.layout
        # trial 2's GP was trained on the episodes before it (the random rollout and trial 1): 2 x 12 transitions
        assert saved.saved_model(2)["gp"]["inputs"].shape[0] == 2 * 12
        assert saved.metric("J_after").keys() == {1, 2}
        objective = PolicyObjective(policy.controller, model.posterior(), policy.layout, saved.task.spec.cost,
                                    saved.task.spec.init_mean, saved.task.spec.init_cov, saved.planning_horizon)
        with torch.no_grad():
            J = float(objective.step_costs()[0].sum())
        # the closed-form J of the handed-over policy under the trial's model is what the run logged
        assert J == pytest.approx(saved.metric("J_after")[2], rel=1e-6)
        settings_file = saved.file("trial001/pilco_settings.json")
    # a local store's files are read where they are (nothing downloaded, nothing left to remove)
    assert settings_file.is_relative_to(Path(uri[len("sqlite:///"):]).parent / "mlruns") and settings_file.exists()


def _stored_run(tmp_path: Path, task: str, options: dict[str, str], trials: int):
    """A tiny PILCO run (task horizon 12, seed 0) into a fresh store under ``tmp_path``: ``(uri, result)``."""
    from harness.tracking import MlflowTracker, default_tracking_uri

    (tmp_path / "store").mkdir()
    uri = default_tracking_uri(tmp_path / "store")
    return uri, run(RunConfig("pilco", task, seed=0, learner_options=options, task_options={"horizon": 12}, max_trials=trials,
                              eval_episodes=2), tracker=MlflowTracker(uri))


def test_a_grown_horizon_is_read_per_trial_and_the_prediction_check_uses_it(tmp_path):
    """With a horizon schedule the search of a later trial planned over more steps than the first:
    ``planning_horizon_at`` gives each trial's (its logged metric), and the prediction check sums J over it."""
    from benchmarks.pilco_prediction_check import main

    options = {**TINY, "planning_horizon": "3", "grow_horizon_below": "10", "grow_horizon_on": "realised"}
    uri, result = _stored_run(tmp_path, "cartpole", options, trials=2)
    with SavedPilcoRun(result.run_id, uri) as saved:
        logged = {trial: int(h) for trial, h in saved.metric("planning_horizon").items()}
        assert saved.planning_horizon == 3 and logged[2] > 3  # grown: a cost per step of at most 1 is below 10
        assert [saved.planning_horizon_at(t) for t in (1, 2)] == [logged[1], logged[2]]
    main([result.run_id, "--trial", "2", "--particles", "20", "--episodes", "2", "--tracking-uri", uri, "--out", str(tmp_path)])
    text = (tmp_path / f"prediction_check_cartpole_{result.run_id[:8]}_t2.md").read_text()
    assert f"planning horizon {logged[2]};" in text and f"| J = sum over {logged[2]} steps |" in text


def test_a_trials_objective_is_rebuilt_as_the_run_planned_it_and_the_gp_budget_check_uses_it(tmp_path):
    """Planning noise, a cost width of its own and two random rollouts: ``objective(trial, policy)`` gives
    the J the run's search logged, ``task_cost`` the task's width instead, and the GP budget check takes
    the own GP of the trial that was trained on its training episodes."""
    from benchmarks.gp_budget_check import main

    options = {**TINY, "plan_with_noise": "true", "cost_width": "0.5", "initial_rollouts": "2"}
    # the unicycle: its linear policy sees raw state entries, which planning noise needs
    uri, result = _stored_run(tmp_path, "unicycle", options, trials=3)
    with SavedPilcoRun(result.run_id, uri) as saved:
        assert saved.initial_rollouts == 2 and saved.option_used("plan_with_noise") == "True"
        assert saved.option_used("controller") == "linear" and saved.option_used("no_such_option") is None
        # trial K's GP was trained on the first 2 + K - 1 episodes
        # (a fall's last transition is dropped)
        assert saved.saved_model(2)["gp"]["inputs"].shape[0] == sum(ep.steps - ep.terminated for ep in saved.episodes()[:3])
        policy = saved.policy(2)
        planned, on_task = saved.objective(2, policy), saved.objective(2, policy, task_cost=True)
        settings, first_folder = saved.settings, saved.file("trial001/pilco_settings.json").parent
        assert planned.policy_noise is not None
        with torch.no_grad():
            J, J_task = float(planned.step_costs()[0].sum()), float(on_task.step_costs()[0].sum())
    assert J == pytest.approx(saved.metric("J_after")[2], rel=1e-6)  # what the run's search computed
    assert abs(J_task - J) > 1e-3 * J  # the task's width 1.0 is another cost
    main([result.run_id, "--train-episodes", "3", "--policy-trial", "2", "--configs", "5:all", "5:all:10", "--particles", "50", "--episodes", "2",
          "--tracking-uri", uri, "--out", str(tmp_path)])
    text = (tmp_path / f"gp_budget_check_unicycle_{result.run_id[:8]}_seeds0.md").read_text()
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ") and "seed" not in line}
    assert set(rows) == {"run's own GP at trial 2 (100:300, warm-started)", "5:all", "5:all:10"}
    own = [float(c) for c in rows["run's own GP at trial 2 (100:300, warm-started)"].split("|")[6:10]]
    assert own[0] == pytest.approx(J_task, abs=0.006)  # its closed-form J is the task-width J above (2 decimals)
    assert all(np.isfinite(own))  # the sampled J and its gap are reported
    # --lqr-speeds: the riding LQR scored under every model too, its J through the own GP as the run would plan it
    main([result.run_id, "--train-episodes", "3", "--policy-trial", "2", "--configs", "5:all", "--lqr-speeds", "0.3",
          "--episodes", "2", "--tracking-uri", uri, "--out", str(tmp_path)])
    text = (tmp_path / f"gp_budget_check_unicycle_{result.run_id[:8]}_seeds0_lqr.md").read_text()
    assert "Riding LQR 0.3 m/s" in text and "LQR 0.3: J |" in text
    with SavedPilcoRun(result.run_id, uri) as saved:
        lqr = linear_policy_from_gain(saved.task.spec, *riding_lqr(saved.task, 0.3))
        with torch.no_grad():
            J_lqr = float(saved.objective(2, lqr, saved.model(2).posterior(), task_cost=True).step_costs()[0].sum())
    rows = {line.split("|")[1].strip(): line.split("|") for line in text.splitlines() if line.startswith("| ") and "seed" not in line}
    assert set(rows) == {"run's own GP at trial 2 (100:300, warm-started)", "5:all"}
    assert float(rows["run's own GP at trial 2 (100:300, warm-started)"][8]) == pytest.approx(J_lqr, abs=0.006)
    assert np.isfinite(float(rows["5:all"][8]))
    # a store that kept only the later trials' GPs (trial 2: its hyperparameters alone): the settings are rebuilt from
    # the earliest GP left and the params
    shutil.rmtree(first_folder)
    (first_folder.parent / "trial002" / "model_trial002.pt").unlink()
    with SavedPilcoRun(result.run_id, uri) as bare:
        assert bare.model_trials() == [3] and bare.settings == settings


def test_the_gp_budget_check_refits_with_the_runs_own_draw_and_gets_the_runs_gp_back(tmp_path):
    """A sparse GP trains its hyperparameters on a random subset: refitting from the previous trial's GP with
    the run's own draw (``gp_fit_seed``: the learner's derived seed plus the trial) gives the run's GP back
    exactly; another seed's draw gives another GP. ``--warm-only`` leaves out the fits from scratch."""
    from benchmarks.gp_budget_check import main
    from harness.seeding import derive_seeds

    options = {**TINY, "sparse_threshold": "10", "num_pseudo": "6", "gp_hyper_subset": "8", "initial_rollouts": "2"}
    uri, result = _stored_run(tmp_path, "cartpole", options, trials=4)
    with SavedPilcoRun(result.run_id, uri) as saved:
        assert saved.gp_fit_seed(3) == derive_seeds(0)["learner"] + 3
        assert saved.saved_model(3)["gp"]["inputs"].shape[0] > 10  # sparse, on a subset of 8
    main([result.run_id, "--train-episodes", "4", "--policy-trial", "3", "--configs", "100:8", "--seeds", "1", "--warm-start",
          "--warm-only", "--episodes", "2", "--tracking-uri", uri, "--out", str(tmp_path)])
    text = (tmp_path / f"gp_budget_check_cartpole_{result.run_id[:8]}_seeds1_warm.md").read_text()
    rows = {line.split("|")[1].strip(): line.split("|")[4:8] for line in text.splitlines() if line.startswith("| ") and "seed" not in line}
    assert set(rows) == {"run's own GP at trial 3 (100:8, warm-started)", "100:8 from the run's trial-2 GP, its pseudo-inputs",
                         "100:8 from the run's trial-2 GP, fresh pseudo-inputs", "100:8 from the run's trial-2 GP, its pseudo-inputs, the run's draw"}
    own = rows["run's own GP at trial 3 (100:8, warm-started)"]
    assert rows["100:8 from the run's trial-2 GP, its pseudo-inputs, the run's draw"] == own  # NLPD, SMSE, J, J - real
    assert rows["100:8 from the run's trial-2 GP, its pseudo-inputs"][0] != own[0]  # seed 1's subset: another GP


def test_the_pseudo_subset_check_refits_on_all_points_and_on_a_subset(tmp_path):
    """benchmarks/pseudo_subset_check.py on a run that drew fresh pseudo-inputs every trial: one row per subset size
    and seed (the FITC NLL is the fit's report, on all training points: tests/pilco/test_gp.py), a subset's fit
    another model; a run that kept its pseudo-inputs is refused with the option to look for."""
    from benchmarks.pseudo_subset_check import main

    options = {**TINY, "sparse_threshold": "10", "num_pseudo": "6", "gp_hyper_subset": "8", "initial_rollouts": "2",
               "gp_refresh_pseudo": "true"}
    uri, result = _stored_run(tmp_path, "cartpole", options, trials=4)
    main([result.run_id, "--train-episodes", "4", "--test-episodes", "1", "--subsets", "0", "12", "--seeds", "0",
          "--episodes", "2", "--tracking-uri", uri, "--out", str(tmp_path)])
    text = (tmp_path / f"pseudo_subset_check_cartpole_{result.run_id[:8]}_k4.md").read_text()
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in text.splitlines()
            if line.startswith("| ") and "seed" not in line}
    assert set(rows) == {"all 48", "12 points"}  # 4 episodes of 12 steps
    assert rows["all 48"][2] != rows["12 points"][2] and all(np.isfinite(float(c)) for c in rows["12 points"][1:])
    assert "its **real** cost over 2 episodes" in text  # the later policy (trial 4) is scored
    (tmp_path / "kept").mkdir()
    kept, kept_run = _stored_run(tmp_path / "kept", "cartpole", {**options, "gp_refresh_pseudo": "false"}, trials=3)
    with pytest.raises(SystemExit, match="gp_refresh_pseudo=True"):
        main([kept_run.run_id, "--train-episodes", "3", "--test-episodes", "1", "--tracking-uri", kept, "--out", str(tmp_path)])


def test_a_missing_artifact_or_a_non_pilco_run_is_named(stored):
    uri, pilco, other = stored
    with pytest.raises(TrackingError, match="no run 'no-such-run' in sqlite:///"):
        SavedPilcoRun("no-such-run", uri)
    with pytest.raises(CheckpointError, match=r"'random' run; this needs a PILCO \(or mc-pilco\) run"):
        SavedPilcoRun(other.run_id, uri)
    with pytest.raises(CheckpointError, match="needs a run on 'unicycle'"):
        SavedPilcoRun(pilco.run_id, uri, task="unicycle")
    with SavedPilcoRun(pilco.run_id, uri) as saved, pytest.raises(CheckpointError, match="no artifact 'trial009/model_trial009.pt'"):
        saved.model(9)
    assert np.isfinite(saved.metric("J_before")[1])


def test_swingup_failure_modes_classes_every_test_episode(stored, tmp_path):
    from benchmarks.swingup_failure_modes import main

    uri, pilco, _ = stored
    out = tmp_path / "modes.md"
    main(["--runs", pilco.run_id, "--trials", "1", "2", "--episodes", "7", "--tracking-uri", uri, "--out", str(out)])
    assert out.read_text().startswith("# How swing-up policies fail (cartpole: pilco)")
    rows = [line for line in out.read_text().splitlines() if line.startswith(f"| `{pilco.run_id[:8]}`")]
    assert len(rows) == 2
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        successes = int(cells[4].split("/")[0])
        assert successes + int(cells[5]) + int(cells[6]) + int(cells[7]) == 7


def test_swingup_failure_modes_pure_parts():
    from benchmarks.swingup_failure_modes import outcome

    radius = 0.1
    assert outcome(np.array([1.0, 0.5, 0.3]), radius, solved=False) == "never reached"
    assert outcome(np.array([1.0, 0.05, 0.3]), radius, solved=False) == "reached, fell away"
    assert outcome(np.array([1.0, 0.3, 0.05]), radius, solved=False) == "reached, cut off"
    assert outcome(np.array([1.0, 0.05, 0.05]), radius, solved=True) == "success"


def _tip_cost(task, episode, width: float, steps: int | None = None) -> float:
    """1 - exp(-d^2 / (2 width^2)) summed over the tip distances d of states 1..steps: the cart-pole's
    cost written from its geometry, independently of SaturatingCost's linear map."""
    d = task.tip_distance(episode.states)[1:][:steps]
    return float(np.sum(1.0 - np.exp(-0.5 * d * d / width**2)))


def test_planning_cost_check_sets_each_prediction_beside_the_episode_its_policy_produced(stored, tmp_path):
    from benchmarks.planning_cost_check import check_run, main

    uri, pilco, _ = stored
    with SavedPilcoRun(pilco.run_id, uri) as saved:
        found = check_run(saved)
        episodes, task = saved.episodes(), saved.task
        J_after = saved.metric("J_after")
    assert found["width"] == found["task_width"] == 0.25 and found["random"] == 1
    # trial 2's policy was only evaluated: only trial 1 has an episode of its own (the run's second)
    [row] = found["rows"]
    assert row["trial"] == 1 and row["horizon"] == 12 and row["predicted"] == J_after[1]
    assert row["realised"] == pytest.approx(_tip_cost(task, episodes[1], 0.25, 12), rel=1e-12)
    assert row["task"] == pytest.approx(_tip_cost(task, episodes[1], 0.25), rel=1e-12)
    out = tmp_path / "check.md"
    main(["--runs", pilco.run_id, "--tracking-uri", uri, "--out", str(out)])
    assert f"| 1 | 12 | 0.25 | {J_after[1]:.2f} | {row['realised']:.2f} |" in out.read_text()


def test_an_mc_pilco_run_opens_for_its_policies_episodes_and_planning_width(tmp_path):
    from benchmarks.planning_cost_check import check_run
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path)
    options = {"num_centres": "4", "particles": "8", "max_steps": "4", "window": "2", "gp_max_evals": "10", "cost_width": "1.0",
               "cost_narrowing": "0.5"}
    result = run(RunConfig("mc-pilco", "cartpole", seed=0, learner_options=options, task_options={"horizon": 10}, max_trials=3,
                           eval_episodes=1), tracker=MlflowTracker(uri))
    with SavedPilcoRun(result.run_id, uri) as saved:
        assert saved.policy_trials() == [1, 2, 3] and saved.policy(3).layout is not None
        found = check_run(saved)  # no pilco_settings.json: the width is the run's per trial (narrowing), the horizon its metric
        episodes, task = saved.episodes(), saved.task
    assert found["width"] == 1.0 and found["task_width"] == 0.25
    first, second = found["rows"]
    assert (first["width"], second["width"]) == (1.0, 0.5)
    assert first["realised"] == pytest.approx(_tip_cost(task, episodes[1], 1.0, 10), rel=1e-12)
    assert second["realised"] == pytest.approx(_tip_cost(task, episodes[2], 0.5, 10), rel=1e-12)


def test_planning_cost_check_realises_an_mc_pilco_run_with_the_paper_cost_by_its_formula(tmp_path):
    """An ``mc-pilco`` run with ``cost=paper`` has no width: the realised planning cost is MC-PILCO's cart-pole
    cost written out here from the recorded angles and positions."""
    import math

    from benchmarks.planning_cost_check import check_run, main
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path)
    options = {"num_centres": "4", "particles": "8", "max_steps": "4", "window": "2", "gp_max_evals": "10", "cost": "paper"}
    result = run(RunConfig("mc-pilco", "cartpole", seed=0, learner_options=options, task_options={"horizon": 10}, max_trials=2,
                           eval_episodes=1), tracker=MlflowTracker(uri))
    with SavedPilcoRun(result.run_id, uri) as saved:
        found = check_run(saved)
        states = np.asarray(saved.episodes()[1].states)[1:11]
    assert found["width"] is None
    [row] = found["rows"]
    by_hand = sum(1 - math.exp(-((abs(th) - math.pi) / 3) ** 2 - x**2) for x, th in zip(states[:, 0], states[:, 3]))
    assert row["width"] is None and row["realised"] == pytest.approx(by_hand, rel=1e-12)
    out = tmp_path / "check.md"
    main(["--runs", result.run_id, "--tracking-uri", uri, "--out", str(out)])
    assert "Planned with MC-PILCO's cost (no width)" in out.read_text() and "| 1 | 10 | MC-PILCO |" in out.read_text()


@pytest.mark.filterwarnings("ignore:mc-pilco. the RBF policy's centres are far:UserWarning")  # its tiny mc-pilco run
def test_paper_cost_of_policies_scores_a_stored_policy_with_both_costs_by_their_formulas(tmp_path):
    """The stored policy's test episodes, re-run here with the same seed, scored by hand: the cart-pole's tip
    cost from its geometry, MC-PILCO's from the recorded angles and positions; the horizon override holds."""
    import math

    from benchmarks.paper_cost_of_policies import main, score_policy
    from harness.discovery import load_task
    from harness.evaluation import Evaluator
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path)
    options = {"num_centres": "4", "particles": "8", "max_steps": "4", "window": "2", "gp_max_evals": "10"}
    result = run(RunConfig("mc-pilco", "cartpole", seed=1, learner_options=options, task_options={"horizon": 10}, max_trials=2,
                           eval_episodes=1), tracker=MlflowTracker(uri))
    with SavedPilcoRun(result.run_id, uri) as saved:
        found = score_policy(saved, None, 15, 3, 5)
        task, policy = saved.task, saved.policy(2)
    assert found["trial"] == 2 and found["horizon"] == 15
    longer = load_task("cartpole")(**{**task.options, "horizon": 15})
    episodes = Evaluator(longer, n_episodes=3, seed=5)(policy).episodes
    for k, ep in enumerate(episodes):
        s = np.asarray(ep.states)[1:]
        assert len(s) == 15
        paper = sum(1 - math.exp(-((abs(th) - math.pi) / 3) ** 2 - x**2) for x, th in zip(s[:, 0], s[:, 3]))
        assert found["paper"][k] == pytest.approx(paper, rel=1e-12)
        assert found["task"][k] == pytest.approx(_tip_cost(longer, ep, 0.25), rel=1e-12)
    out = tmp_path / "scores.md"
    main(["--runs", result.run_id, "--episodes", "3", "--seed", "5", "--horizon", "15", "--tracking-uri", uri, "--out", str(out)])
    assert f"| {found['paper'].mean():.2f} ({found['paper'].min():.2f}-" in out.read_text()
    with SavedPilcoRun(result.run_id, uri) as saved, pytest.raises(CheckpointError, match="has no policy of trial 7"):
        score_policy(saved, 7, None, 1, 0)


def test_the_ensemble_search_check_averages_j_and_dj_and_scores_every_policy_under_every_gp(tmp_path):
    """``MeanObjective`` is the mean of its members' J and dJ (each computed alone); the check refits
    the GP per draw, searches and writes one row per policy with J under every GP."""
    from benchmarks.ensemble_search_check import MeanObjective, main

    options = {**TINY, "sparse_threshold": "10", "num_pseudo": "6", "gp_hyper_subset": "8", "initial_rollouts": "2"}
    uri, result = _stored_run(tmp_path, "cartpole", options, trials=3)
    with SavedPilcoRun(result.run_id, uri) as saved:
        policy = saved.policy(2)
        objectives = [saved.objective(trial, policy) for trial in (2, 3)]  # one controller, two GPs
        theta = objectives[0].get_flat() + 0.01
        alone = [objective.value_and_grad(theta) for objective in objectives]
        J, dJ = MeanObjective(objectives).value_and_grad(theta)
    assert J == pytest.approx((alone[0][0] + alone[1][0]) / 2, rel=1e-12)
    np.testing.assert_allclose(dJ, (alone[0][1] + alone[1][1]) / 2, rtol=1e-12)
    assert abs(alone[0][0] - alone[1][0]) > 1e-6 * abs(J)  # two different GPs: the mean is not one of them
    main([result.run_id, "--trial", "3", "--draws", "1", "2", "--episodes", "2", "--tracking-uri", uri, "--out", str(tmp_path)])
    text = (tmp_path / f"ensemble_search_check_cartpole_{result.run_id[:8]}_t3.md").read_text()
    assert "| policy | J + dJ evaluations | J under run's own GP | J under draw 1 GP | J under draw 2 GP | real cost | real success |" in text
    rows = [line for line in text.splitlines() if line.startswith("| ") and "J + dJ evaluations" not in line]
    assert [r.split("|")[1].strip() for r in rows] == ["the run's trial-3 policy (searched under its own GP)",
                                                        "searched under draw 1 alone", "searched on the mean J of draws 1, 2"]
    assert all(np.isfinite(float(c)) for r in rows for c in r.split("|")[3:7])


def test_the_unicycle_drift_check_counts_falls_as_the_episodes_and_the_task_do(tmp_path):
    """The real fallen fraction at a step is the share of test episodes that ended in a fall by then; the
    model's is the share of sampled states the task calls fallen; both per step, every state entry reported."""
    from benchmarks.unicycle_drift_check import main
    from harness.evaluation import Evaluator

    uri, result = _stored_run(tmp_path, "unicycle", {**TINY, "initial_rollouts": "2"}, trials=2)
    main([result.run_id, "--trial", "2", "--particles", "50", "--episodes", "6", "--steps", "3", "12", "--tracking-uri", uri,
          "--out", str(tmp_path)])
    text = (tmp_path / f"drift_check_unicycle_{result.run_id[:8]}_t2.md").read_text()
    with SavedPilcoRun(result.run_id, uri) as saved:
        episodes = Evaluator(saved.task, n_episodes=6, seed=200_000)(saved.policy(2)).episodes
        names = saved.task.spec.state_names
    rows = {int(line.split("|")[1]): line.split("|")[2:-1] for line in text.splitlines()
            if line.startswith("| ") and line.split("|")[1].strip().isdigit()}
    assert set(rows) == {3, 12}
    torques = [line.split("|")[1].strip() for line in text.splitlines() if line.startswith("| ") and "-" in line.split("|")[1]]
    assert torques == ["0-3", "3-12"] * 2  # the real torques, then the GP's one-step errors, by fate, between consecutive steps
    persistence = [line.split("|")[1].strip() for line in text.splitlines() if line.startswith("| ") and "[" in line.split("|")[1]]
    assert persistence == list(names)  # the error correlations, one row per state entry
    for t, cells in rows.items():
        fell = sum(ep.terminated and len(ep.states) - 1 <= t for ep in episodes)
        assert cells[0].strip() == f"{100 * fell / 6:.1f} %"
        assert 0 <= float(cells[1].strip(" %")) <= 100 and len(cells) == 4 + 2 * len(names)
        # a ride that fell has been past the 0.3 rad tilt before: at least as many, in the real rides as in the model's
        assert float(cells[2].strip(" %")) >= float(cells[0].strip(" %")) and float(cells[3].strip(" %")) >= float(cells[1].strip(" %"))


def test_the_drift_check_refits_on_the_observations_to_the_runs_gp_and_on_true_states_to_another(tmp_path):
    """``--train-on observations`` trains trial K's GP again as the run did (``refit_model``): the same report as the
    saved GP's; ``--train-on true-states`` trains on the noise-free states of the same episodes: another GP."""
    from benchmarks.unicycle_drift_check import main

    options = {**TINY, "sparse_threshold": "10", "num_pseudo": "6", "gp_hyper_subset": "8", "initial_rollouts": "2"}
    uri, result = _stored_run(tmp_path, "unicycle", options, trials=3)
    common = [result.run_id, "--trial", "3", "--particles", "30", "--episodes", "3", "--steps", "4", "12", "--tracking-uri", uri,
              "--out", str(tmp_path)]

    def body(suffix: str, *extra: str) -> list[str]:
        main(common + list(extra))
        text = (tmp_path / f"drift_check_unicycle_{result.run_id[:8]}_t3{suffix}.md").read_text()
        return [line for line in text.splitlines() if line.startswith("| ") or line.startswith("Expected cost")]

    saved = body("")
    assert body("_observations", "--train-on", "observations") == saved
    assert body("_true-states", "--train-on", "true-states") != saved
    assert body("_smoothed", "--train-on", "smoothed", "--smooth-window", "5") != saved
    mixed = [body(f"_{side}", "--train-on", side) for side in ("true-inputs", "true-targets")]
    assert saved not in mixed and mixed[0] != mixed[1]  # one side true, the other observed: two more GPs
    lqr = body("_lqr0.3", "--lqr-speed", "0.3")
    assert lqr != saved and len(lqr) == len(saved)
    smoothed = body("_gp-smoothed-r1-q1", "--train-on", "gp-smoothed", "--smooth-rounds", "1", "--process-std", "1")
    assert smoothed != saved and len(smoothed) == len(saved)
    assert smoothed != body("_gp-smoothed-r2-q1", "--train-on", "gp-smoothed", "--smooth-rounds", "2", "--process-std", "1")
    text = (tmp_path / f"drift_check_unicycle_{result.run_id[:8]}_t3_gp-smoothed-r1-q1.md").read_text()
    assert "Smoothing round 1: rms error of the estimates over that of the observations" in text


def test_the_drift_checks_smoothing_keeps_a_quadratic_and_shortens_nothing():
    """The Savitzky-Golay filter (quadratic) leaves a quadratic trajectory as it is, takes noise down, and leaves an
    episode shorter than its window unchanged."""
    from benchmarks.unicycle_drift_check import smoothed

    t = np.arange(20.0)[:, None]
    quadratic = np.hstack([0.5 * t**2 - 3 * t + 1, -t**2])
    np.testing.assert_allclose(smoothed(quadratic, 5), quadratic, atol=1e-9)
    noise = np.random.default_rng(0).normal(size=(400, 1))
    assert smoothed(noise, 5).std() < 0.8 * noise.std()
    np.testing.assert_array_equal(smoothed(quadratic[:3], 5), quadratic[:3])
