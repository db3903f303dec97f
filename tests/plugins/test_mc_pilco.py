"""MC-PILCO (plugins.mc_pilco): the particle estimate, its gradient, the optimiser, the learner.

The estimate is checked against moment matching over one step (where moment matching is exact in
mean and covariance of the GP prediction, so both agree to Monte Carlo error), its gradient against
central differences at fixed random numbers (the estimate is then a deterministic function of the
parameters), and the learner against the plugin contract, seeding and resume.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from harness.runner import RunConfig, run
from harness.testing import LearnerConformance
from harness.tracking import MemoryTracker
from plugins.mc_pilco.learner import McPilco
from plugins.mc_pilco.optimise import optimise_particles
from plugins.mc_pilco.particles import ParticleObjective, policy_actions
from plugins.pilco.objective import PolicyObjective
from tests.devices import CUDA, default_device, run_on_cuda
from tests.harness.toy import RecordingProgress
from tests.harness.trackers import InterruptAt
from tests.pilco.test_fused_step import _objective

torch.set_num_threads(1)

# TINY's 4 spread centres are far from the start states for some seeds: the run's warning is expected there
pytestmark = pytest.mark.filterwarnings("ignore:mc-pilco. the RBF policy's centres are far:UserWarning")

TINY = {"num_centres": "4", "particles": "16", "max_steps": "12", "window": "4", "gp_max_evals": "20"}


def _particles(obj: PolicyObjective, particles: int, horizon: int | None = None) -> ParticleObjective:
    return ParticleObjective(obj.controller, obj.posterior, obj.layout, obj.cost, obj.init_mean, obj.init_cov,
                             horizon or obj.horizon, particles)


def test_one_step_particles_have_the_moments_of_moment_matching() -> None:
    """A linear, unsquashed policy on a state without angles: state and control are exactly jointly
    Gaussian, so one moment-matching step gives the exact mean and covariance of the model's
    prediction; 200k particles agree to Monte Carlo error (and the step's cost estimate is their mean cost)."""
    obj = _objective("no-angles-linear")
    obj.horizon = 1
    with torch.no_grad():
        means, covs = obj.state_distributions()
        states, costs = _particles(obj, 200_000, 1).rollout(torch.Generator().manual_seed(0))
    x1 = states[1]
    sd = covs[1].diagonal().sqrt()
    np.testing.assert_allclose(((x1.mean(0) - means[1]) / sd).numpy(), 0.0, atol=0.01)
    np.testing.assert_allclose((torch.cov(x1.T) / (sd[:, None] * sd[None, :])).numpy(),
                               (covs[1] / (sd[:, None] * sd[None, :])).numpy(), atol=0.015)
    assert float(costs[0]) == pytest.approx(float(obj.cost.sample(x1).mean()), rel=1e-12)


@pytest.mark.parametrize("dropout", [0.0, 0.25])
def test_gradient_matches_central_differences_at_fixed_random_numbers(dropout) -> None:
    obj = _objective("rbf-two-controls")
    particles = _particles(obj, 64, 6)
    params = [p for p in obj.controller.parameters()]
    theta = obj.get_flat()

    def J(vector):
        obj.set_flat(vector)
        return particles.value(torch.Generator().manual_seed(3), dropout)

    (grad,) = torch.autograd.grad(J(theta), params[1])  # the RBF targets
    rng = np.random.default_rng(1)
    offset = sum(p.numel() for p in params[:1])
    for index in rng.choice(params[1].numel(), size=4, replace=False):
        step = np.zeros_like(theta)
        step[offset + index] = 1e-6
        with torch.no_grad():
            fd = (float(J(theta + step)) - float(J(theta - step))) / 2e-6
        assert fd == pytest.approx(float(grad.reshape(-1)[index]), rel=1e-5, abs=1e-8)


def _reference_rollout(obj: ParticleObjective, generator: torch.Generator, dropout: float):
    """The rollout as first written (random numbers drawn where they are used, the RBF network's
    posterior formed at every step): what :meth:`ParticleObjective.draw` + ``rollout_drawn`` replace."""
    from plugins.pilco.gp import predict_latent

    x = obj.init_mean + torch.randn(obj.particles, obj.init_mean.shape[0], generator=generator, dtype=torch.float64) @ obj._root.T
    pol, mod = obj.layout.policy_index, obj.layout.model_index
    states, costs = [x], []
    for _ in range(obj.horizon):
        a = obj.layout.augment(x)
        u = policy_actions(obj.controller, a[:, pol], dropout, generator)  # draws its mask here, posterior per step
        mean, var = predict_latent(obj.posterior, torch.cat([a[:, mod], u], dim=1))
        x = x + mean + var.clamp_min(1e-12).sqrt() * torch.randn(x.shape, generator=generator, dtype=torch.float64)
        states.append(x)
        costs.append(obj.cost.sample(x).mean())
    return torch.stack(states), torch.stack(costs)


@pytest.mark.parametrize("case,dropout", [("rbf-two-controls", 0.25), ("rbf-two-controls", 0.0), ("linear-sin", 0.0)])
def test_drawing_first_gives_the_numbers_drawn_where_used(case, dropout) -> None:
    """All random numbers drawn before the rollout (one copy to a GPU, capturable) are the ones the rollout
    drew step by step: the same states bit for bit; the gradient agrees to rounding (the RBF posterior is
    now formed once per rollout, so autograd sums its contributions in another order)."""
    obj = _particles(_objective(case), 40, 7)
    params = obj.parameters()
    new_states, new_costs = obj.rollout(torch.Generator().manual_seed(5), dropout)
    old_states, old_costs = _reference_rollout(obj, torch.Generator().manual_seed(5), dropout)
    assert torch.equal(new_states, old_states) and torch.equal(new_costs, old_costs)
    g_new = torch.cat([g.reshape(-1) for g in torch.autograd.grad(new_costs.sum(), params)])
    g_old = torch.cat([g.reshape(-1) for g in torch.autograd.grad(old_costs.sum(), params)])
    assert float((g_new - g_old).norm()) <= 1e-12 * float(g_old.norm())
    J, usable, grads = obj.value_and_grad(torch.Generator().manual_seed(5), dropout)
    assert usable and J == float(old_costs.sum().detach()) and torch.equal(torch.cat([g.reshape(-1) for g in grads]), g_new)


def test_a_step_with_a_non_finite_estimate_is_not_usable() -> None:
    obj = _particles(_objective("linear-sin"), 8, 3)
    with torch.no_grad():
        obj.posterior.beta[0, 0] = float("nan")
    J, usable, grads = obj.value_and_grad(torch.Generator().manual_seed(0))
    assert np.isnan(J) and not usable and grads == [None] * len(obj.parameters())


def test_dropout_masks_only_rbf_weights_and_scales_the_rest() -> None:
    obj = _objective("rbf-two-controls")
    inputs = torch.randn(2000, 5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    with torch.no_grad():
        plain = policy_actions(obj.controller, inputs)
        dropped = policy_actions(obj.controller, inputs, 0.5, torch.Generator().manual_seed(1))
        base = obj.controller.base
    assert torch.allclose(plain, obj.controller(inputs))
    assert not torch.allclose(dropped, plain)
    # in expectation the pre-squash output is unchanged (inverted dropout): compare the mean over masks
    with torch.no_grad():
        z = base(inputs[:1])
        post = base.posterior()
        from plugins.pilco.kernels import se_ard

        k = se_ard(inputs[:1].expand(20000, 5), post.inputs, post.log_ell, post.log_alpha)
        keep = torch.rand(k.shape, generator=torch.Generator().manual_seed(2), dtype=k.dtype) >= 0.5
        mean = torch.einsum("anm,am->na", k * keep / 0.5, post.beta).mean(0)
    assert torch.allclose(mean, z[0], atol=0.05 * z.abs().max().item() + 1e-3)
    linear = _objective("linear-sin").controller
    with torch.no_grad():
        assert torch.equal(policy_actions(linear, inputs[:, :5], 0.5, torch.Generator()), linear(inputs[:, :5]))


def test_optimiser_lowers_the_estimate_and_reduces_dropout_when_it_stalls() -> None:
    obj = _objective("rbf-two-controls")
    particles = _particles(obj, 64, 8)
    result = optimise_particles(particles, max_steps=200, lr=0.05, dropout=0.25, dropout_step=0.125, lr_decay=0.5,
                                window=10, min_improvement=0.01, seed=0)
    assert result.J_after < result.J_before
    assert result.reductions >= 1 and result.final_dropout == pytest.approx(0.25 - 0.125 * result.reductions)
    assert result.final_lr == pytest.approx(0.05 * 0.5**result.reductions)
    assert len(result.trace) == (result.steps - result.skipped) // 10


def test_lr_reductions_lower_the_rate_at_dropout_zero_before_a_stall_ends_the_search() -> None:
    """Without dropout the paper's rule ends the search at its first stall; with lr_reductions=k the
    first k stalls halve the learning rate instead (the steps before the first stall are the same
    ones), and the (k+1)-th ends it."""
    kwargs = dict(max_steps=400, lr=0.2, dropout=0.0, dropout_step=0.125, lr_decay=0.5, window=10, min_improvement=0.01,
                  seed=0)
    runs = {}
    for k in (0, 2):
        obj = _objective("rbf-two-controls")
        runs[k] = optimise_particles(_particles(obj, 64, 8), lr_reductions=k, **kwargs)
    plain, cut = runs[0], runs[2]
    assert plain.steps < kwargs["max_steps"] and plain.lr_reductions == 0 and plain.final_lr == 0.2
    assert cut.lr_reductions == 2 and cut.reductions == 0 and cut.final_lr == pytest.approx(0.2 * 0.5**2)
    assert cut.steps > plain.steps and cut.trace[:len(plain.trace)] == plain.trace
    stalls = [i for i in range(1, len(cut.trace)) if cut.trace[i - 1] - cut.trace[i] < 0.01 * abs(cut.trace[i - 1])]
    assert len(stalls) == 3 and stalls[-1] == len(cut.trace) - 1  # two cuts, then the third stall ends it
    with pytest.raises(ValueError, match="lr_reductions must be >= 0"):
        optimise_particles(_particles(_objective("rbf-two-controls"), 64, 8), lr_reductions=-1, **kwargs)


def test_revert_goes_back_to_the_best_parameters_with_smaller_steps() -> None:
    """keep=best with revert: at lr 1 the plain search runs uphill and hands back its start; with revert a window
    the fixed particles rate no better than the best so far sends the parameters back there and halves the rate, up to lr_reductions times, after
    which such a window ends the search. It ends below its start, where the plain one did not; every window end
    that the checks rated above the best so far was followed by a step from the best's parameters."""
    kwargs = dict(max_steps=400, lr=1.0, dropout=0.0, dropout_step=0.125, lr_decay=0.5, window=10, min_improvement=0.01,
                  seed=0, keep="best")
    plain = optimise_particles(_particles(_objective("rbf-two-controls"), 64, 8), **kwargs)
    assert plain.kept_step == 0 and plain.reverts == 0
    obj = _objective("rbf-two-controls")
    particles = _particles(obj, 64, 8)
    events = []  # ("check", its value, the parameters it rated) and ("step", the parameters the Adam step starts from)
    real, real_step = particles.value, particles.value_and_grad
    params = lambda: [q.detach().clone() for q in obj.controller.parameters()]  # noqa: E731

    def value(gen):
        out = real(gen)
        events.append(("check", float(out), params()))
        return out

    def value_and_grad(gen, p):
        events.append(("step", None, params()))
        return real_step(gen, p)

    particles.value, particles.value_and_grad = value, value_and_grad
    result = optimise_particles(particles, lr_reductions=3, revert=True, **kwargs)
    assert 1 <= result.reverts <= 3 and result.lr_reductions >= result.reverts
    assert result.final_lr == pytest.approx(0.5**result.lr_reductions)
    assert result.J_after < result.J_before and result.kept_step > 0
    with torch.no_grad():
        assert float(real(torch.Generator().manual_seed(1))) == result.J_after  # the handed-over parameters
    best, backtracks = (events[0][1], events[0][2]), 0
    for i, (kind, v, theta) in enumerate(events[1:-1], start=1):  # the last check rates the end, after the loop
        if kind != "check":
            continue
        if v < best[0]:
            best = (v, theta)
        elif i + 1 < len(events) and events[i + 1][0] == "step":  # rated above the best: the next step starts from it
            assert all(torch.equal(a, b) for a, b in zip(events[i + 1][2], best[1]))
            backtracks += 1
    assert backtracks == result.reverts
    with pytest.raises(ValueError, match="only keep='best' tracks"):
        optimise_particles(particles, **{**kwargs, "keep": "last"}, revert=True)
    from harness.discovery import load_task
    from harness.errors import OptionError

    McPilco(load_task("cartpole")().spec, {"revert": True, "keep": "best"}, 0)
    with pytest.raises(OptionError, match="only keep=best tracks: add --set learner.keep=best"):
        McPilco(load_task("cartpole")().spec, {"revert": True}, 0)


class _ScriptedSearch:
    """A particle objective whose estimates and fixed-particle checks follow a script (zero gradients)."""

    def __init__(self, estimates: list[float], checks: list[float]) -> None:
        self.x = torch.zeros(1, requires_grad=True)
        self.estimates, self.checks = list(estimates), list(checks)

    def parameters(self) -> list[torch.Tensor]:
        return [self.x]

    def value_and_grad(self, gen, dropout):
        return self.estimates.pop(0), True, [torch.zeros(1)]

    def value(self, gen):
        return torch.tensor(self.checks.pop(0) if self.checks else 0.0)


def test_lr_growth_is_not_counted_when_the_window_that_set_a_best_also_ends_the_search() -> None:
    """Window means 10, 11, 10.5, 10.6; checks (start 10) 9, 12, 8, 7. Window 2 backtracks (rate 1 -> 0.5, the one
    reduction allowed), window 3's new best grows it to 0.75, window 4 sets a new best but its mean rose with no
    reduction left: the search ends at rate 0.75, one growth (not a growth to 1 that no step used)."""
    scripted = _ScriptedSearch([10.0, 11.0, 10.5, 10.6], [10.0, 9.0, 12.0, 8.0, 7.0, 7.0])
    result = optimise_particles(scripted, max_steps=10, lr=1.0, dropout=0.0, dropout_step=0.1, lr_decay=0.5, window=1,
                                min_improvement=0.0, seed=0, keep="best", revert=True, lr_reductions=1, lr_growth=1.5)
    assert (result.steps, result.reverts, result.growths) == (4, 1, 1)
    assert result.rates == [1.0, 0.5, 0.75] and result.final_lr == 0.75
    assert result.J_after == 7.0


def test_lr_growth_raises_the_rate_after_each_new_best_up_to_lr_and_is_off_by_default() -> None:
    """revert with lr_growth=2 (a trust region): the rate after each window is the one before it halved by a
    backtrack, doubled (capped at lr) after a window end the fixed particles rated below the best so far, and never
    above lr; with lr_growth=1 the search is the one without the option, step for step. On this problem the rate
    grows again after the first backtrack."""
    kwargs = dict(max_steps=400, lr=1.0, dropout=0.0, dropout_step=0.125, lr_decay=0.5, window=10, min_improvement=0.0,
                  seed=0, keep="best", revert=True, lr_reductions=6)
    same = optimise_particles(_particles(_objective("rbf-two-controls"), 64, 8), lr_growth=1.0, **kwargs)
    plain = optimise_particles(_particles(_objective("rbf-two-controls"), 64, 8), **kwargs)
    assert (same.trace, same.rates, same.J_after, same.kept_step) == (plain.trace, plain.rates, plain.J_after, plain.kept_step)
    assert plain.growths == 0

    obj = _objective("rbf-two-controls")
    particles = _particles(obj, 64, 8)
    checks = []  # the fixed particles' value at each window end, in order (the first: the start)
    real = particles.value

    def value(gen):
        out = real(gen)
        checks.append(float(out))
        return out

    particles.value = value
    grown = optimise_particles(particles, lr_growth=2.0, **kwargs)
    assert grown.growths >= 1 and grown.reverts >= 1
    best, rate = checks[0], kwargs["lr"]
    for i, (check, after) in enumerate(zip(checks[1:], grown.rates)):
        if check < best:
            best, rate = check, min(kwargs["lr"], rate * 2.0)
            if i >= 1 and grown.trace[i] > grown.trace[i - 1]:  # a window mean that rose is a stall: halved as well
                rate *= 0.5
        else:
            rate *= 0.5  # a backtrack
        assert after == pytest.approx(rate) and after <= kwargs["lr"]
    assert grown.final_lr == pytest.approx(rate)
    with pytest.raises(ValueError, match="only revert=True"):
        optimise_particles(_particles(_objective("rbf-two-controls"), 64, 8), **{**kwargs, "revert": False}, lr_growth=2.0)
    with pytest.raises(ValueError, match="lr_growth must be >= 1"):
        optimise_particles(_particles(_objective("rbf-two-controls"), 64, 8), **kwargs, lr_growth=0.5)
    from harness.discovery import load_task
    from harness.errors import OptionError

    with pytest.raises(OptionError, match="needs revert=true"):
        McPilco(load_task("cartpole")().spec, {"lr_growth": 2.0}, 0)


@pytest.mark.parametrize("lr, kept", [(0.2, "a window's end"), (0.5, "the start")])
def test_keep_best_hands_over_the_parameters_the_fixed_particles_rate_lowest(lr, kept) -> None:
    """keep="best" takes the same Adam steps as keep="last" (its checks draw from their own generator)
    and hands over, of the start, each window's end and the end, the parameters with the lowest
    estimate on the fixed particles of J_before/J_after: each candidate is re-estimated here with
    the same random numbers. At these learning rates the last step's parameters rate worse than an
    earlier window's (lr 0.2) or than the start (lr 0.5): a search that ended above where it began."""
    kwargs = dict(max_steps=200, lr=lr, dropout=0.25, dropout_step=0.125, lr_decay=0.5, window=10, min_improvement=0.01,
                  seed=0)
    last_obj = _objective("rbf-two-controls")
    last = optimise_particles(_particles(last_obj, 64, 8), **kwargs)
    assert last.J_after == last.J_last and last.kept_step == last.steps
    obj = _objective("rbf-two-controls")
    start = [q.detach().clone() for q in obj.controller.parameters()]
    particles = _particles(obj, 64, 8)
    best = optimise_particles(particles, keep="best", **kwargs)
    assert best.steps == last.steps and best.J_before == last.J_before and best.J_last == last.J_last
    assert best.J_after < best.J_last and best.J_after <= best.J_before
    assert (0 < best.kept_step < best.steps) if kept == "a window's end" else best.kept_step == 0
    with torch.no_grad():  # the handed-over parameters are the kept ones: the same estimate again
        assert float(particles.value(torch.Generator().manual_seed(1))) == best.J_after
    if kept == "the start":
        for q, q0 in zip(obj.controller.parameters(), start):
            assert torch.equal(q, q0)
    with pytest.raises(ValueError, match="keep must be 'last' or 'best'"):
        optimise_particles(particles, keep="first", **kwargs)


class TestMcPilcoConformance(LearnerConformance):
    learner_cls = McPilco
    task_name = "cartpole"
    task_options = {"horizon": 10}
    learner_options = TINY


def test_same_seed_same_run_and_resume_equals_uninterrupted() -> None:
    config = RunConfig("mc-pilco", "cartpole", seed=2, learner_options=TINY, task_options={"horizon": 10}, max_trials=3,
                       eval_episodes=2)
    strip = lambda h: [{k: v for k, v in r.items() if "seconds" not in k or k == "interaction_seconds"} for r in h]  # noqa: E731
    tracker, shown = MemoryTracker(), RecordingProgress()
    reference = run(config, tracker=tracker, progress=shown)
    assert strip(run(config).history) == strip(reference.history)
    # what `harness bench` shows during a trial: GP training, then every Adam step with the window mean
    first = shown.events[:shown.events.index("hand-over 1")]
    assert first[0] == "GP training on 10 transitions"
    steps = [e for e in first if e.startswith("policy search: Adam step ")]
    assert len(steps) == int(dict(tracker.metrics["policy_steps"])[1])
    assert steps[0].startswith("policy search: Adam step 1/12, dropout")
    assert "J_hat" in steps[3] and "(mean of the last 4)" in steps[3] and "J_hat" not in steps[2]
    assert {"J_before", "J_after", "J_last", "kept_step", "policy_steps", "final_dropout"} <= set(tracker.metrics)
    interrupted = InterruptAt(2)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=interrupted)
    resumed = run(config, tracker=interrupted, resume_run_id=interrupted.run_id)
    assert strip(resumed.history) == strip(reference.history)


def test_gp_data_smoothed_smooths_for_mc_pilco_too(fit_inputs) -> None:
    """The PILCO core's gp_data option (plugins.pilco.gp_data) in mc-pilco: per trial a fit on the observations,
    then smooth_rounds fits on episodes smoothed through the GP (moved by about the noise, 0.01), the smoothing's
    metrics logged per trial, the same run again from the same seed; the default fits once per trial."""
    fits = fit_inputs
    strip = lambda h: [{k: v for k, v in r.items() if "seconds" not in k or k == "interaction_seconds"} for r in h]  # noqa: E731
    histories, trackers = {}, {}
    for label, extra in (("default", {}), ("smoothed", {"gp_data": "smoothed"}), ("again", {"gp_data": "smoothed"})):
        fits.clear()
        trackers[label] = MemoryTracker()
        config = RunConfig("mc-pilco", "cartpole", seed=1, learner_options={**TINY, **extra}, task_options={"horizon": 10},
                           max_trials=2, eval_episodes=1)
        histories[label] = strip(run(config, tracker=trackers[label]).history)
        trackers[label].fits = list(fits)
    assert len(trackers["default"].fits) == 2 and "smoothing_obs_rms" not in trackers["default"].metrics
    smoothed = trackers["smoothed"].fits
    assert len(smoothed) == 2 * 3 and np.array_equal(smoothed[0], trackers["default"].fits[0])
    for x in smoothed[1:3]:
        assert x.shape == smoothed[0].shape and 0 < np.abs(x - smoothed[0]).max() < 0.2
    metrics = trackers["smoothed"].metrics
    for key in ("smoothing_obs_rms", "smoothing_residual_rms", "smoothing_seconds"):
        assert set(dict(metrics[key])) == {1, 2}
    assert all(0 < v < 5 for v in dict(metrics["smoothing_obs_rms"]).values())
    assert histories["again"] == histories["smoothed"] != histories["default"]


def test_horizon_schedule_grows_the_particles_horizon_and_a_resume_continues_at_the_grown_one() -> None:
    """PILCO's horizon schedule in mc-pilco: cart-pole's cost per step lies in (0, 1], so the realised rule at a
    threshold of 10 doubles the planning horizon after every rollout of a learned policy (3 -> 6 -> 10, the task's),
    logs the rollout's cost per step from trial 2, and a run interrupted after trial 2 resumes at the grown horizon."""
    options = {**TINY, "planning_horizon": "3", "grow_horizon_below": "10", "grow_horizon_on": "realised"}
    config = RunConfig("mc-pilco", "cartpole", seed=3, learner_options=options, task_options={"horizon": 10}, max_trials=3,
                       eval_episodes=1)
    strip = lambda h: [{k: v for k, v in r.items() if "seconds" not in k or k == "interaction_seconds"} for r in h]  # noqa: E731
    tracker = MemoryTracker()
    reference = run(config, tracker=tracker)
    assert [h for _, h in sorted(tracker.metrics["planning_horizon"])] == [3.0, 6.0, 10.0]
    assert [step for step, _ in sorted(tracker.metrics["rollout_cost_per_step"])] == [2, 3]
    fixed = MemoryTracker()  # the default: no schedule, the planning horizon stays
    run(dataclasses.replace(config, learner_options={**TINY, "planning_horizon": "3"}), tracker=fixed)
    assert [h for _, h in sorted(fixed.metrics["planning_horizon"])] == [3.0, 3.0, 3.0]
    interrupted = InterruptAt(2)
    with pytest.raises(KeyboardInterrupt):
        run(config, tracker=interrupted)
    resumed = run(config, tracker=interrupted, resume_run_id=interrupted.run_id)
    assert strip(resumed.history) == strip(reference.history)


def test_planning_basis_limits_the_points_the_particles_go_through() -> None:
    """Cart-pole with 10-step episodes: 2 trials give 20 transitions; with planning_basis=8 the particles
    go through a posterior on 8 basis points (logged), with the default through all the data's."""
    config = RunConfig("mc-pilco", "cartpole", seed=1, learner_options=TINY, task_options={"horizon": 10}, max_trials=2,
                       eval_episodes=1)
    full, reduced = MemoryTracker(), MemoryTracker()
    run(config, tracker=full)
    run(dataclasses.replace(config, learner_options={**TINY, "planning_basis": "8"}), tracker=reduced)
    assert [v for _, v in full.metrics["planning_basis"]] == [10.0, 20.0]
    assert [v for _, v in reduced.metrics["planning_basis"]] == [8.0, 8.0]
    assert full.metrics["J_after"] != reduced.metrics["J_after"]


@pytest.mark.parametrize("dropout", [0.0, 0.25])
def test_particles_create_no_tensor_on_the_default_device(dropout) -> None:
    """With torch's default device set to ``meta`` (holds no data), a tensor created without an explicit
    device lands there and the first operation that mixes it with the real ones fails: a pass means
    nothing in the particle rollout (random numbers included) would be left off a GPU the model lives on."""
    obj = _particles(_objective("rbf-two-controls"), 30)
    J0 = obj.value(torch.Generator().manual_seed(4), dropout)
    with default_device("meta"):
        J1 = obj.value(torch.Generator().manual_seed(4), dropout)
    assert J1.device.type == "cpu" and float(J1.detach()) == float(J0.detach())


def test_mc_pilco_refuses_cuda_without_a_gpu_in_one_line() -> None:
    from harness.errors import OptionError
    from harness.discovery import load_task

    spec = load_task("cartpole")().spec
    assert McPilco(spec, {"device": "cpu"}).device.type == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(OptionError, match=r"device=cuda: torch sees no CUDA GPU here"):
            McPilco(spec, {"device": "cuda"})


@CUDA
@pytest.mark.parametrize("dropout", [0.0, 0.25])
def test_particles_on_cuda_equal_the_cpu(dropout) -> None:
    """Same random numbers (drawn on the CPU) on both devices: J_hat and its gradient agree to rounding."""
    import copy

    cpu = _particles(_objective("rbf-two-controls"), 50)
    gpu = dataclasses.replace(cpu, controller=copy.deepcopy(cpu.controller).cuda(), posterior=cpu.posterior.to("cuda"),
                              cost=type(cpu.cost)(cpu.cost.cost, cpu.cost.width, "cuda"), init_mean=cpu.init_mean.cuda(),
                              init_cov=cpu.init_cov.cuda())
    values = []
    for obj in (cpu, gpu):
        J = obj.value(torch.Generator().manual_seed(7), dropout)
        grads = torch.autograd.grad(J, [p for p in obj.controller.parameters() if p.requires_grad])
        values.append((float(J), torch.cat([g.reshape(-1) for g in grads]).cpu()))
    (J_c, g_c), (J_g, g_g) = values
    assert abs(J_g - J_c) <= 1e-10 * abs(J_c) and float((g_g - g_c).norm()) <= 1e-7 * float(g_c.norm())


@CUDA
def test_mc_pilco_runs_on_cuda() -> None:
    result = run_on_cuda("mc-pilco", {"num_centres": "5", "max_steps": "20", "particles": "20", "gp_max_evals": "30"})
    assert result.trials == 2


def _on_cuda(obj: ParticleObjective, cuda_graph: bool = True) -> ParticleObjective:
    import copy

    return dataclasses.replace(obj, controller=copy.deepcopy(obj.controller).cuda(), posterior=obj.posterior.to("cuda"),
                               cost=type(obj.cost)(obj.cost.cost, obj.cost.width, "cuda"), init_mean=obj.init_mean.cuda(),
                               init_cov=obj.init_cov.cuda(), cuda_graph=cuda_graph)


@CUDA
@pytest.mark.parametrize("case", ["rbf-two-controls", "linear-sin"])
def test_adam_steps_replayed_as_a_cuda_graph_equal_the_launched_ones(case) -> None:
    """A search whose steps replay CUDA graphs (one per dropout value) takes the same steps as one that
    launches every operation: same estimates, same parameters at the end. Against the CPU only the start
    agrees to rounding: over 60 Adam steps with dropout, rounding differences of 1e-16 grew to 3 % of theta
    (measured on an H100), as any change of summation order would."""
    cpu = _particles(_objective(case), 48, 6)
    results = []
    for obj in (_on_cuda(cpu, True), _on_cuda(cpu, False), cpu):
        r = optimise_particles(obj, max_steps=60, lr=0.02, dropout=0.25, dropout_step=0.125, lr_decay=0.5,
                               window=10, min_improvement=0.01, seed=4)
        theta = torch.cat([p.detach().reshape(-1) for p in obj.controller.parameters()]).cpu()
        results.append((r, theta, obj))
    (graph, t_graph, g_obj), (launched, t_launched, _), (on_cpu, _, _) = results
    assert g_obj.graph_error is None and len(g_obj._graphs) == (1 + graph.reductions if case.startswith("rbf") else 1)
    assert graph.steps == launched.steps and graph.trace == pytest.approx(launched.trace, rel=1e-12)
    assert float((t_graph - t_launched).norm()) <= 1e-12 * float(t_launched.norm())
    assert graph.J_before == pytest.approx(on_cpu.J_before, rel=1e-10)


def test_spread_centres_cover_the_state_space_and_keep_the_policy_gram_well_conditioned() -> None:
    """Cart-pole: the spread centres' sin/cos entries lie on the unit circle at angles over the whole
    circle, the other entries fill [-pi, pi]; the reference's centres (drawn from the initial state
    distribution) nearly coincide, so their policy Gram matrix is far worse conditioned and the
    weights beta = (K + 0.01^2 I)^-1 t are orders of magnitude larger for targets of the same size."""
    import math

    from harness.discovery import load_task
    from plugins.pilco.policy import initial_controller, spread_centres

    spec = load_task("cartpole")().spec
    learner = McPilco(spec, {}, 0)
    layout = learner.layout
    centres = spread_centres(layout, 2000, math.pi, torch.Generator().manual_seed(0))
    assert centres.shape == (2000, len(layout.policy_inputs))
    plain = [k for k, i in enumerate(layout.policy_inputs) if i < layout.state_dim]
    sin, cos = centres[:, len(plain)], centres[:, len(plain) + 1]
    np.testing.assert_allclose((sin**2 + cos**2).numpy(), 1.0, rtol=1e-12)
    angles = torch.atan2(sin, cos)
    assert angles.min() < -0.99 * math.pi and angles.max() > 0.99 * math.pi
    assert centres[:, plain].abs().max() <= math.pi and centres[:, plain].abs().max() > 0.99 * math.pi
    assert torch.equal(spread_centres(layout, 50, math.pi, torch.Generator().manual_seed(3)),
                       spread_centres(layout, 50, math.pi, torch.Generator().manual_seed(3)))
    betas = {}
    for name, spread in (("spread", math.pi), ("initial", None)):
        controller = initial_controller(spec, learner.preset, layout, "trapezoid", torch.Generator().manual_seed(0), spread=spread)
        betas[name] = float(controller.base.posterior().beta.detach().abs().max())
    assert betas["spread"] < 5.0 and betas["initial"] > 100.0 * betas["spread"]
    with pytest.raises(ValueError, match="spread must be positive"):
        spread_centres(layout, 5, 0.0, torch.Generator())


def test_mc_pilco_starts_from_spread_centres_unless_asked_for_the_reference() -> None:
    """The learner's initial controller: spread centres by default; with ``centres=initial`` exactly
    PILCO's own initial controller for the same generator."""
    from harness.discovery import load_task
    from plugins.pilco.learner import Pilco

    spec = load_task("cartpole")().spec
    spread = McPilco(spec, {}, 4).new_controller(torch.Generator().manual_seed(4))
    initial = McPilco(spec, {"centres": "initial"}, 4).new_controller(torch.Generator().manual_seed(4))
    reference = Pilco(spec, {}, 4).new_controller(torch.Generator().manual_seed(4))
    for name, value in reference.state_dict().items():
        assert torch.equal(initial.state_dict()[name], value), name
    assert initial.base.centres[:, :3].abs().max() < 0.6  # x, dx, dtheta around the initial state (std 0.1)
    assert spread.base.centres[:, :3].abs().max() > 2.0
    assert spread.base.centres.shape == initial.base.centres.shape


def test_the_planning_width_narrows_per_trial_to_the_tasks_and_is_logged() -> None:
    """cost_width=1.0 with cost_narrowing=0.5 on cart-pole (task width 0.25): 1.0, 0.5, 0.25, 0.25, ...; the
    first trial plans exactly as a run at the constant 1.0 width, the second no longer does."""
    from harness.discovery import load_task

    spec = load_task("cartpole")().spec
    learner = McPilco(spec, {"cost_width": 1.0, "cost_narrowing": 0.5})
    assert [learner.planning_width(t) for t in (1, 2, 3, 4)] == [1.0, 0.5, 0.25, 0.25]
    assert [McPilco(spec, {"cost_width": 1.0}).planning_width(t) for t in (1, 5)] == [1.0, 1.0]
    assert McPilco(spec, {"cost_width": 0.1, "cost_narrowing": 0.5}).planning_width(3) == 0.1  # set below the task's: kept
    assert McPilco(spec, {"cost_narrowing": 0.5}).planning_width(2) == 0.25  # the task's width: nothing to narrow
    config = RunConfig("mc-pilco", "cartpole", seed=3, learner_options={**TINY, "cost_width": "1.0"}, task_options={"horizon": 10},
                       max_trials=3, eval_episodes=1)
    constant, narrowing = MemoryTracker(), MemoryTracker()
    run(config, tracker=constant)
    run(dataclasses.replace(config, learner_options={**config.learner_options, "cost_narrowing": "0.5"}), tracker=narrowing)
    assert [v for _, v in narrowing.metrics["cost_width"]] == [1.0, 0.5, 0.25]
    assert [v for _, v in constant.metrics["cost_width"]] == [1.0, 1.0, 1.0]
    assert narrowing.metrics["J_after"][0] == constant.metrics["J_after"][0]
    assert narrowing.metrics["J_before"][1] != constant.metrics["J_before"][1]


def test_target_scale_draws_the_initial_rbf_targets_uniformly_and_needs_spread_centres() -> None:
    from harness.discovery import load_task
    from harness.errors import OptionError

    spec = load_task("cartpole")().spec
    default = McPilco(spec, {}, 2).new_controller(torch.Generator().manual_seed(2)).base
    wide = McPilco(spec, {"target_scale": 0.5}, 2).new_controller(torch.Generator().manual_seed(2)).base
    assert torch.equal(default.centres, wide.centres)  # the same centres: the targets are drawn after them
    t = wide.targets.detach()
    assert t.shape == (50, 1) and float(t.abs().max()) <= 0.5 and float(t.abs().max()) > 0.4
    assert abs(float(t.mean())) < 0.1 and float(default.targets.detach().abs().max()) < 0.5  # 0.1 randn by default
    with pytest.raises(OptionError, match="target_scale sets the initial targets of an RBF policy with spread centres"):
        McPilco(spec, {"target_scale": 0.5, "centres": "initial"}, 2)


def test_the_paper_cart_pole_cost_has_the_values_of_its_formula_and_charges_a_spun_pole() -> None:
    """MC-PILCO's cart-pole cost on the harness's state (x, xdot, thetadot, theta), against the formula
    written out by hand: 0 upright either way round, 1 - exp(-(pi/3)^2) hanging, 1 - exp(-(2 pi/3)^2) a full
    turn past upright, the position term with 1 m; torch and NumPy agree; its gradient matches central
    differences."""
    import math

    from plugins.mc_pilco.costs import CARTPOLE, PAPER_COSTS

    assert PAPER_COSTS["cartpole"] is CARTPOLE
    states = np.array([[0.0, 0.3, -1.0, math.pi], [0.0, 0.0, 0.0, -math.pi], [0.0, 0.0, 0.0, 0.0],
                       [0.0, 0.0, 0.0, 3 * math.pi], [1.0, 0.0, 0.0, math.pi], [-0.5, 2.0, 1.0, 2.0]])
    by_hand = [0.0, 0.0, 1 - math.exp(-(math.pi / 3) ** 2), 1 - math.exp(-(2 * math.pi / 3) ** 2), 1 - math.exp(-1.0),
               1 - math.exp(-((2.0 - math.pi) / 3) ** 2 - 0.25)]
    np.testing.assert_allclose(CARTPOLE(states), by_hand, rtol=1e-14, atol=1e-15)
    x = torch.tensor(states, dtype=torch.float64, requires_grad=True)
    values = CARTPOLE.sample(x)
    np.testing.assert_allclose(values.detach().numpy(), by_hand, rtol=1e-14, atol=1e-15)
    (grad,) = torch.autograd.grad(values[5], x)
    h, numeric = 1e-6, np.zeros(4)
    for i in range(4):
        step = np.zeros(4)
        step[i] = h
        numeric[i] = (CARTPOLE(states[5] + step) - CARTPOLE(states[5] - step)) / (2 * h)
    np.testing.assert_allclose(grad[5].numpy(), numeric, rtol=1e-7, atol=1e-10)
    assert grad[5, 1] == 0.0 and grad[5, 2] == 0.0  # the velocities are not costed


def test_cost_paper_plans_with_the_mc_pilco_cost_and_refuses_where_it_has_none() -> None:
    """``cost=paper``: the search's objective is MC-PILCO's cart-pole cost, no ``cost_width`` is logged (there is
    no width), J_hat differs from the task cost's; a task the paper gives no cost for, or a width set beside
    it, is a one-line OptionError naming the fix."""
    from harness.discovery import load_task
    from harness.errors import OptionError
    from plugins.mc_pilco.costs import CARTPOLE

    spec = load_task("cartpole")().spec
    assert McPilco(spec, {"cost": "paper"}).planning_cost(1) is CARTPOLE
    with pytest.raises(OptionError, match="defines no planning cost for this task.*use cost=task"):
        McPilco(load_task("unicycle")().spec, {"cost": "paper"})
    with pytest.raises(OptionError, match="cost=paper has its own length-scales: drop them"):
        McPilco(spec, {"cost": "paper", "cost_width": 1.0})
    config = RunConfig("mc-pilco", "cartpole", seed=3, learner_options=TINY, task_options={"horizon": 10},
                       max_trials=2, eval_episodes=1)
    task_cost, paper = MemoryTracker(), MemoryTracker()
    run(config, tracker=task_cost)
    run(dataclasses.replace(config, learner_options={**TINY, "cost": "paper"}), tracker=paper)
    assert "cost_width" not in paper.metrics and len(task_cost.metrics["cost_width"]) == 2
    assert paper.metrics["J_before"][0] != task_cost.metrics["J_before"][0]
    assert 0.0 < paper.metrics["J_before"][0][1] < 10.0  # 10 steps, each cost in [0, 1)


class _StopAtFirstRollout:
    """An interaction that stops a learner at its first rollout (what happened before it is what is tested)."""

    class Reached(Exception):
        pass

    def rollout(self, policy, max_steps=None):
        raise self.Reached


def test_far_rbf_centres_are_measured_and_warned_about() -> None:
    """start_kernel is the largest SE kernel value (of 1) between the RBF centres and the mean start state's policy
    input, as written out in NumPy; a fresh run whose centres are all far from it (the unicycle's spread centres in 10
    dimensions) warns with the fix, one whose centres reach it (cart-pole; centres=initial) does not."""
    from tasks.cartpole import CartPole
    from tasks.unicycle import Unicycle

    spec = Unicycle().spec
    learner = McPilco(spec, {"controller": "rbf"}, seed=0)
    controller = learner.new_controller(torch.Generator().manual_seed(0))
    centres = controller.base.centres.detach().numpy()
    ell = np.exp(controller.base.log_ell.detach().numpy())  # (F, p)
    a = learner.layout.augment(torch.as_tensor(spec.init_mean, dtype=torch.float64)[None])
    x = a[0, learner.layout.policy_index].numpy()
    by_hand = max(float(np.exp(-0.5 * (((x - c) / e) ** 2).sum())) for e in ell for c in centres)
    assert learner.start_kernel(controller) == pytest.approx(by_hand, rel=1e-12) and by_hand < 0.01
    with pytest.warns(UserWarning, match=r"centres are far from the start states .* --set learner.centres=initial"):
        with pytest.raises(_StopAtFirstRollout.Reached):
            next(learner.learn(_StopAtFirstRollout()))
    for near in (McPilco(spec, {"controller": "rbf", "centres": "initial"}, seed=0), McPilco(CartPole().spec, {}, seed=0)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(_StopAtFirstRollout.Reached):
                next(near.learn(_StopAtFirstRollout()))
    assert McPilco(spec, {"controller": "linear"}, seed=0).start_kernel(
        McPilco(spec, {"controller": "linear"}, seed=0).new_controller(torch.Generator().manual_seed(0))) is None


class _Quadratic:
    """A deterministic J(theta) = sum a (theta - t)^2 over two parameter tensors, with the
    :class:`ParticleObjective` methods :func:`optimise_particles` uses; ``map`` turns the optimised
    parameters into theta (``theta = map * phi``, 1 for the parameters themselves)."""

    def __init__(self, start: list[torch.Tensor], map_: list[torch.Tensor]) -> None:
        g = torch.Generator().manual_seed(3)
        self.params = [q.clone().requires_grad_(True) for q in start]
        self.map = map_
        self.a = [torch.rand(q.shape, generator=g, dtype=torch.float64) * 10 ** torch.linspace(-2, 2, q.numel()).view(q.shape)
                  for q in start]
        self.t = [torch.randn(q.shape, generator=g, dtype=torch.float64) for q in start]

    def parameters(self) -> list[torch.Tensor]:
        return self.params

    def value(self, generator: torch.Generator, dropout: float = 0.0) -> torch.Tensor:
        return sum((a * (m * q - t) ** 2).sum() for q, m, a, t in zip(self.params, self.map, self.a, self.t))

    def value_and_grad(self, generator: torch.Generator, dropout: float = 0.0):
        J = self.value(generator)
        return float(J.detach()), True, list(torch.autograd.grad(J, self.params))


def test_step_scales_run_adam_on_the_parameters_over_their_scales() -> None:
    """Adam with step_scales c on theta is Adam without them on phi = theta / c (J(c phi)): the same
    path, computed here as that second, unscaled search."""
    g = torch.Generator().manual_seed(0)
    theta0 = [torch.randn(2, 3, generator=g, dtype=torch.float64), torch.randn(2, generator=g, dtype=torch.float64)]
    scales = [torch.tensor([[0.1, 1.0, 8.0], [0.5, 2.0, 0.02]], dtype=torch.float64), torch.tensor([1.0, 3.0], dtype=torch.float64)]
    kwargs = dict(max_steps=60, lr=0.05, dropout=0.0, dropout_step=0.125, lr_decay=0.5, window=1000, min_improvement=0.0, seed=0)
    scaled = _Quadratic(theta0, [torch.ones_like(q) for q in theta0])
    a = optimise_particles(scaled, step_scales=scales, **kwargs)
    phi = _Quadratic([q / c for q, c in zip(theta0, scales)], scales)
    b = optimise_particles(phi, **kwargs)
    for q, p, c in zip(scaled.params, phi.params, scales):
        torch.testing.assert_close(q.detach(), c * p.detach(), rtol=1e-12, atol=1e-12)
    assert a.J_after == pytest.approx(b.J_after, rel=1e-10) and a.J_after < a.J_before
    unscaled = _Quadratic(theta0, [torch.ones_like(q) for q in theta0])
    optimise_particles(unscaled, **kwargs)  # a different path without them
    assert not torch.allclose(unscaled.params[0], scaled.params[0])
    with pytest.raises(ValueError, match="step_scales must have the parameters' shapes"):
        optimise_particles(_Quadratic(theta0, scales), step_scales=scales[:1], **kwargs)


def test_step_scale_inputs_uses_the_spread_of_the_policy_inputs_in_the_data() -> None:
    """Cart-pole's policy sees [x, xdot, thetadot, sin theta, cos theta] of each observation (computed
    here with numpy): a linear policy's weight column j gets 1/std_j, its bias 1; RBF centres std_j."""
    from harness.task import Episode

    rng = np.random.default_rng(1)
    episodes = [Episode(observations=rng.normal(size=(6, 4)) * [0.5, 2.0, 9.0, 3.0], states=np.zeros((6, 4)),
                        actions=np.zeros((5, 1)), costs=np.zeros(5), terminated=False, clipped_actions=0, extra={})
                for _ in range(3)]
    obs = np.concatenate([ep.observations for ep in episodes])
    std = np.stack([obs[:, 0], obs[:, 1], obs[:, 2], np.sin(obs[:, 3]), np.cos(obs[:, 3])], axis=1).std(axis=0, ddof=1)
    from harness.runner import new_learner, prepare

    linear = new_learner(prepare(RunConfig("mc-pilco", "cartpole", seed=0, learner_options={"controller": "linear",
                                                                                             "step_scale": "inputs"})))
    controller = linear.new_controller(torch.Generator().manual_seed(0))
    weight, bias = linear.step_scales(controller, episodes)
    np.testing.assert_allclose(weight.numpy(), np.tile(1.0 / std, (controller.base.weight.shape[0], 1)), rtol=1e-12)
    assert torch.equal(bias, torch.ones_like(controller.base.bias))
    rbf = new_learner(prepare(RunConfig("mc-pilco", "cartpole", seed=0, learner_options={"step_scale": "inputs", **TINY})))
    controller = rbf.new_controller(torch.Generator().manual_seed(0))
    scales = dict(zip([n for n, p in controller.named_parameters() if p.requires_grad], rbf.step_scales(controller, episodes)))
    np.testing.assert_allclose(scales["base.centres"].numpy(), np.tile(std, (4, 1)), rtol=1e-12)
    assert all(torch.equal(s, torch.ones_like(s)) for n, s in scales.items() if n != "base.centres")
    assert new_learner(prepare(RunConfig("mc-pilco", "cartpole", seed=0))).step_scales(controller, episodes) is None


def test_step_scale_inputs_runs_and_changes_the_search() -> None:
    base = RunConfig("mc-pilco", "cartpole", seed=3, learner_options=TINY | {"controller": "linear"}, task_options={"horizon": 10},
                     max_trials=2, eval_episodes=1)
    plain = run(base).history
    scaled = run(dataclasses.replace(base, learner_options=base.learner_options | {"step_scale": "inputs"})).history
    assert plain[0]["J_before"] == scaled[0]["J_before"] and plain[0]["J_after"] != scaled[0]["J_after"]
