"""MC-PILCO (plugins.mc_pilco): the particle estimate, its gradient, the optimiser, the learner.

The estimate is checked against moment matching over one step (where moment matching is exact in
mean and covariance of the GP prediction, so both agree to Monte Carlo error), its gradient against
central differences at fixed random numbers (the estimate is then a deterministic function of the
parameters), and the learner against the plugin contract, seeding and resume.
"""

from __future__ import annotations

import dataclasses

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
from tests.harness.trackers import InterruptAt
from tests.pilco.test_fused_step import _objective

torch.set_num_threads(1)

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


class TestMcPilcoConformance(LearnerConformance):
    learner_cls = McPilco
    task_name = "cartpole"
    task_options = {"horizon": 10}
    learner_options = TINY


def test_same_seed_same_run_and_resume_equals_uninterrupted() -> None:
    config = RunConfig("mc-pilco", "cartpole", seed=2, learner_options=TINY, task_options={"horizon": 10}, max_trials=3,
                       eval_episodes=2)
    strip = lambda h: [{k: v for k, v in r.items() if "seconds" not in k or k == "interaction_seconds"} for r in h]  # noqa: E731
    tracker = MemoryTracker()
    reference = run(config, tracker=tracker)
    assert strip(run(config).history) == strip(reference.history)
    assert {"J_before", "J_after", "policy_steps", "final_dropout"} <= set(tracker.metrics)
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
