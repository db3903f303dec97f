"""benchmarks/plateau_search_check.py: the replayed search is the run's own (same model, settings and budget)."""

from __future__ import annotations

import pytest

from benchmarks.plateau_search_check import check, table
from harness.evaluation import Evaluator
from harness.runner import RunConfig, run
from plugins.pilco.saved_run import SavedPilcoRun

TINY = {"num_centres": "4", "policy_max_evaluations": "8", "gp_max_evals": "20", "plots": "false", "sample_particles": "0",
        "restart_tol": "0"}  # the cart-pole preset's restarts off: the replay is of one search per trial


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path_factory.mktemp("plateau-store"))
    result = run(RunConfig("pilco", "cartpole", seed=3, learner_options=TINY, task_options={"horizon": 12}, max_trials=3,
                           eval_episodes=2), tracker=MlflowTracker(uri))
    return uri, result.run_id


def replay(stored, episodes: int, **options):
    """check() on trial 3 of the stored run, and the run's logged J + dJ evaluations of that trial."""
    uri, run_id = stored
    with SavedPilcoRun(run_id, uri) as saved:
        evaluator = Evaluator(saved.task, n_episodes=episodes, seed=777)
        try:
            return check(saved, 3, evaluator=evaluator, log=lambda _: None, **options), saved.metric("policy_evaluations")[3]
        finally:
            evaluator.close()


def test_the_replayed_search_is_the_runs_own(stored):
    (rows, horizon, logged), evaluations = replay(stored, 3, fresh=2, budgets=2)
    assert horizon == 12
    assert [r.start.split(" (")[0] for r in rows] == [
        "the run's trial-3 policy", "the run's search again", "continued", "fresh 1", "fresh 2"]
    own, again, continued, *fresh = rows
    # the run's policy under its own trial's model: the J the run logged
    assert own.J_after == pytest.approx(logged, rel=1e-9) and own.evaluations is None
    # the same start, model, settings and budget: the run's search, to rounding
    assert again.J_after == pytest.approx(logged, rel=1e-6)
    assert again.evaluations == evaluations
    # continuing from the run's result starts where it ended and cannot end higher
    assert continued.J_before == pytest.approx(logged, rel=1e-9) and continued.J_after <= continued.J_before
    for r in fresh:  # two budgets in a row, each continuing from the last
        assert len(r.J_budgets) == 2 and r.J_budgets[1] <= r.J_budgets[0] <= r.J_before
        assert r.J_after == pytest.approx(r.J_budgets[1], rel=1e-12) and 0 <= r.successes <= 3
    assert again.J_budgets == () and continued.J_budgets == ()
    assert fresh[0].J_before != fresh[1].J_before  # different initial controllers
    lines = table(rows, 3)
    assert len(lines) == 2 + len(rows) and "| the run's trial-3 policy (no search) | – |" in lines[2]
    assert f"{fresh[0].J_budgets[0]:.2f} -> {fresh[0].J_budgets[1]:.2f}" in lines[5]


def test_an_unknown_option_is_a_one_line_error(stored):
    from harness.errors import OptionError

    with pytest.raises(OptionError, match="unknown option 'planing_horizon'.*Did you mean 'planning_horizon'"):
        replay(stored, 1, fresh=0, changes={"planing_horizon": "6"})


def test_a_trial_without_a_model_is_a_one_line_error(stored):
    from harness.errors import CheckpointError

    uri, run_id = stored
    with SavedPilcoRun(run_id, uri) as saved, pytest.raises(CheckpointError, match="no model and policy of trial 9"):
        check(saved, 9, fresh=0, evaluator=None)


def test_a_shorter_planning_horizon_replaces_the_runs_own(stored):
    (rows, horizon, logged), _ = replay(stored, 2, fresh=0, changes={"planning_horizon": "6"})
    assert horizon == 6 and len(rows) == 3
    # the same policy's expected cost summed over the first 6 of the run's 12 steps: less than the run's J
    assert 0 < rows[0].J_after < logged
    assert rows[2].J_before == pytest.approx(rows[0].J_after, rel=1e-9) and rows[2].J_after <= rows[2].J_before


def test_perturbed_starts_move_every_parameter_tensor_by_its_own_spread_and_search_from_there(stored):
    """perturbed_copy moves each parameter tensor by scale x its spread x N(0, 1) (checked against the noise drawn
    again here) and leaves the original alone; check() adds one search per perturbed start, from there."""
    import torch

    from benchmarks.plateau_search_check import perturbed_copy

    uri, run_id = stored
    with SavedPilcoRun(run_id, uri) as saved:
        controller = saved.policy(3).controller
    before = [q.detach().clone() for q in controller.parameters()]
    moved = perturbed_copy(controller, 0.3, seed=5)
    gen = torch.Generator().manual_seed(5)
    for q0, q, m in zip(before, controller.parameters(), moved.parameters()):
        assert torch.equal(q0, q.detach())  # the original is untouched
        spread = q0.abs().max() if q0.numel() == 1 else q0.std()
        expected = q0 + 0.3 * spread * torch.randn(q0.shape, generator=gen, dtype=q0.dtype)
        assert torch.allclose(m.detach(), expected, rtol=0, atol=1e-15)
    assert any(not torch.equal(q0, m.detach()) for q0, m in zip(before, moved.parameters()))
    (rows, _, _), _ = replay(stored, 2, fresh=0, perturbed=2, perturb_scale=0.3)
    perturbed = [r for r in rows if r.start.startswith("perturbed")]
    assert len(perturbed) == 2 and perturbed[0].J_before != perturbed[1].J_before
    assert all(r.J_after <= r.J_before for r in perturbed)  # L-BFGS-B never hands back worse than its start
