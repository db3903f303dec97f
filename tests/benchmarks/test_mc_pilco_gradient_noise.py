"""benchmarks/mc_pilco_gradient_noise.py: its gradient statistics, Adam's first step, and a stored run's table."""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest
import torch

from benchmarks.mc_pilco_gradient_noise import adam_first_step, flat, gradient_statistics

TINY = {"num_centres": "4", "particles": "12", "max_steps": "10", "window": "3", "gp_max_evals": "15"}


def test_statistics_match_a_direct_computation_and_their_limits() -> None:
    rng = np.random.default_rng(3)
    grads, reference = rng.normal(size=(5, 7)), rng.normal(size=7)
    stats = gradient_statistics(grads, reference)

    def cosine(a, b):
        return sum(x * y for x, y in zip(a, b)) / math.sqrt(sum(x * x for x in a) * sum(y * y for y in b))

    mean = [sum(g[j] for g in grads) / 5 for j in range(7)]
    assert stats.signal_fraction == pytest.approx(math.sqrt(sum(m * m for m in mean)) / math.sqrt(
        sum(sum(x * x for x in g) for g in grads) / 5), rel=1e-12)
    assert stats.pairwise_cosine == pytest.approx(np.mean([cosine(a, b) for a, b in itertools.permutations(grads, 2)]), rel=1e-12)
    assert stats.reference_cosine == pytest.approx([cosine(g, reference) for g in grads], rel=1e-12)
    assert stats.sign_agreement == pytest.approx(sum((x > 0) == (r > 0) for g in grads for x, r in zip(g, reference)) / 35)
    same = gradient_statistics(np.tile(reference, (4, 1)), reference)
    assert same.signal_fraction == pytest.approx(1.0) and same.pairwise_cosine == pytest.approx(1.0)
    assert same.sign_agreement == 1.0 and same.reference_cosine == pytest.approx(np.ones(4))
    opposite = gradient_statistics(np.stack([reference, -reference]), reference)
    assert opposite.signal_fraction == pytest.approx(0.0, abs=1e-15) and opposite.pairwise_cosine == pytest.approx(-1.0)
    noise = gradient_statistics(rng.normal(size=(400, 60)), reference[:1].repeat(60))
    assert noise.signal_fraction == pytest.approx(1 / math.sqrt(400), rel=0.25)  # independent noise: about 1/sqrt(B)
    assert abs(noise.pairwise_cosine) < 0.01
    with pytest.raises(ValueError, match="B >= 2"):
        gradient_statistics(grads[:1], reference)


def test_adams_first_step_moves_each_parameter_by_the_learning_rate_in_its_gradients_sign() -> None:
    params = [torch.tensor([[0.5, -1.0], [2.0, 0.0]], dtype=torch.float64), torch.tensor([3.0, -0.25], dtype=torch.float64)]
    before = flat(params).clone()
    grad = torch.tensor([1e-6, -4.0, 250.0, -0.5, 2e-3, 7.0], dtype=torch.float64)
    after = adam_first_step(params, grad, lr=0.01)
    # torch's Adam, first step: m_hat = g, v_hat = g^2, update lr * g / (|g| + eps), eps = 1e-8
    assert after == pytest.approx(before - 0.01 * grad / (grad.abs() + 1e-8), rel=0, abs=1e-15)
    assert torch.equal(flat(params), before)  # the parameters themselves are left as they were


def test_a_stored_runs_table_has_a_row_per_horizon_and_its_gradient_is_the_finite_differences(tmp_path) -> None:
    from benchmarks.mc_pilco_gradient_noise import AdamVariant, build, main, measure_horizon, stored_state
    from harness.task import Episode
    from harness.runner import RunConfig, run
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path)
    result = run(RunConfig("mc-pilco", "cartpole", seed=6, learner_options=TINY | {"cost": "paper"}, task_options={"horizon": 10},
                           max_trials=2, eval_episodes=1), tracker=MlflowTracker(uri))
    out = tmp_path / "noise.md"
    main(["--run", result.run_id, "--trial", "1", "--horizons", "2", "4", "--batches", "3", "--common", "30", "--adam-steps", "2",
          "--adam-variants", "", "step_scale=inputs", "--tracking-uri", uri, "--out", str(out)])
    text = out.read_text()
    rows = [line.split("|")[1:-1] for line in text.splitlines() if re.match(r"\| [24] \| [0-9.]+ \(", line)]
    assert [int(r[0]) for r in rows] == [2, 4]
    for row in rows:  # autograd's directional derivative of the common estimate is its central difference
        autograd, difference = (float(v) for v in row[3].split("/"))
        assert difference == pytest.approx(autograd, rel=1e-4, abs=1e-9)
    steps = [line for line in text.splitlines() if re.match(r"\| [24] \| [+-][0-9.]+ \(", line)]
    assert len(steps) == 2  # Adam's first update, per horizon
    paths = {(line.split("|")[1].strip(), line.split("|")[2].strip()): line.split("|")[3] for line in text.splitlines()
             if re.match(r"\| [24] \| (the run's|step_scale=inputs) \|", line)}
    assert set(paths) == {(h, v) for h in ("2", "4") for v in ("the run's", "step_scale=inputs")}
    for h in ("2", "4"):  # both paths checked at their last step, from the same start
        assert all(", 2: " in path for path in paths.values())
        assert paths[(h, "the run's")].split("->")[0] == paths[(h, "step_scale=inputs")].split("->")[0]
    # the measurement leaves the controller where it started
    config, episodes, hyperparameters, controller_state = stored_state(result.run_id, 1, uri)
    learner, posterior, controller = build(config, episodes, hyperparameters, controller_state, 1)
    start = flat(controller.parameters()).detach().clone()
    variants = (AdamVariant("plain"), AdamVariant("scaled", "inputs"))
    row = measure_horizon(learner, posterior, controller, 1, 3, batches=2, common=20, adam_steps=2, lr=0.01, seed=1,
                          variants=variants, episodes=[Episode(**ep) for ep in episodes])
    assert torch.equal(flat(controller.parameters()).detach(), start)
    plain, scaled = row["trajectories"]["plain"], row["trajectories"]["scaled"]
    assert [s for s, _ in plain] == [s for s, _ in scaled] == [1, 2] and plain != scaled  # the same draws, other steps
    assert len(row["step_changes"]) == 2 and row["J_std"] >= 0.0


def test_adam_variants_are_parsed_and_bad_ones_refused_in_one_line() -> None:
    from benchmarks.mc_pilco_gradient_noise import AdamVariant, parse_adam_variant
    from harness.errors import OptionError

    assert parse_adam_variant("") == AdamVariant("the run's")
    assert parse_adam_variant("step_scale=inputs,lr=0.003") == AdamVariant("step_scale=inputs,lr=0.003", "inputs", 0.003)
    for bad, message in (("lr", "is not step_scale"), ("momentum=0.9", "is not step_scale"), ("step_scale=big", "none or inputs"),
                         ("lr=fast", "lr is a number")):
        with pytest.raises(OptionError, match=message):
            parse_adam_variant(bad)
