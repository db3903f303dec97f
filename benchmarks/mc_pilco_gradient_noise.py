"""How noisy is mc-pilco's gradient at a stored trial, and do Adam's steps along it lower J? Per planning horizon.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mc_pilco_gradient_noise.py --run RUN_ID --trial K
        [--horizons 10 20 40] [--batches 16] [--common 4000] [--adam-steps 50] [--lr LR]
        [--adam-variants "" "step_scale=inputs" "lr=0.001"]
        [--tracking-uri URI] [--out FILE]

Every Adam step of ``mc-pilco``'s search draws fresh particles (the run's ``N``: initial states and model
noise) and follows the pathwise gradient of that draw's ``J_hat`` (:class:`~plugins.mc_pilco.particles.ParticleObjective`).
That gradient is unbiased, but over long horizons through a chaotic closed loop its variance can grow
fast (Parmas et al., PIPPS, ICML 2018), and Adam's first update moves every parameter by about ``lr`` in
the direction of its gradient's sign whatever the gradient's size, so a gradient that is mostly noise
steps as far as one that is mostly signal. This benchmark measures which, in the state a stored run was
in after trial ``K``: the data of its trial-``K`` checkpoint (every episode recorded before that hand-over),
the GP refit on it warm-started from that checkpoint's hyperparameters (the run's seed), and the
controller handed over at ``K`` (where trial ``K+1``'s search starts). Per horizon ``H``:

* ``--batches`` independent draws of ``N`` particles (no dropout: ``J_hat`` and gradient ``g_b`` each);
  the standard deviation of ``J_hat`` between draws; the *signal fraction* ``|mean_b g_b| / rms_b |g_b|``
  (1 when every draw gives the same gradient, about ``1/sqrt(B)`` when the draws' gradients are
  independent noise); the mean cosine between two draws' gradients; and each draw's cosine with the
  gradient ``g_c`` of a common estimate on ``--common`` particles (fixed random numbers), the reference;
* the reference checked against an independent computation: its directional derivative along
  ``g_c / |g_c|`` by autograd and by central differences (step 1e-5) on the same fixed particles;
* Adam's first update, ``-lr * g / (|g| + eps)`` per parameter (``torch.optim.Adam``'s first step: the
  bias corrections cancel), from each draw's gradient and from the reference's: the change of the common
  estimate ``J_c`` it causes (mean over draws, how many lower it), beside the first-order prediction
  ``-lr * sum |g_c|`` for the reference's step, and the change along the steepest descent ``-g_c`` over the
  same distance (a sign step that raises ``J_c`` where this lowers it is badly scaled, not noisy);
* ``--adam-steps`` steps of Adam as the search takes them (fresh ``N`` particles each, the run's learning
  rate unless ``--lr``), once per ``--adam-variants`` entry (the learner's option ``step_scale``, a
  learning rate): ``J_c`` at 5 points along the way.

One torch thread; the common estimate is the costly part (``--common / N`` times an Adam step).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from harness.errors import CheckpointError, OptionError, exit_on_error  # noqa: E402
from harness.task import Episode  # noqa: E402

DIFFERENCE_STEP = 1e-5


@dataclasses.dataclass(frozen=True)
class GradientStatistics:
    """What ``B`` draws' gradients ``(B, P)`` say, against a reference gradient ``(P,)``.

    Attributes:
        signal_fraction: ``|mean_b g_b| / sqrt(mean_b |g_b|^2)``: 1 for identical draws, ``1/sqrt(B)`` in
            expectation for independent zero-mean noise.
        pairwise_cosine: the mean cosine between two different draws' gradients.
        reference_cosine: each draw's cosine with the reference, ``(B,)``.
        sign_agreement: the fraction of (draw, parameter) entries whose sign is the reference's.
    """

    signal_fraction: float
    pairwise_cosine: float
    reference_cosine: np.ndarray
    sign_agreement: float


def gradient_statistics(grads: np.ndarray, reference: np.ndarray) -> GradientStatistics:
    """:class:`GradientStatistics` of ``grads`` ``(B, P)`` (``B >= 2``) against ``reference`` ``(P,)``."""
    grads, reference = np.asarray(grads, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if grads.ndim != 2 or grads.shape[0] < 2 or reference.shape != grads.shape[1:]:
        raise ValueError(f"grads must be (B >= 2, P) and reference (P,), got {grads.shape} and {reference.shape}")
    norms = np.linalg.norm(grads, axis=1)
    signal = float(np.linalg.norm(grads.mean(axis=0)) / math.sqrt(float(np.mean(norms ** 2))))
    unit = grads / norms[:, None]
    gram = unit @ unit.T
    b = grads.shape[0]
    pairwise = float((gram.sum() - np.trace(gram)) / (b * (b - 1)))
    reference_cosine = unit @ reference / np.linalg.norm(reference)
    agreement = float(np.mean(np.sign(grads) == np.sign(reference)[None, :]))
    return GradientStatistics(signal, pairwise, reference_cosine, agreement)


def flat(tensors) -> torch.Tensor:
    return torch.cat([t.reshape(-1) for t in tensors])


def set_flat(params: list[torch.Tensor], values: torch.Tensor) -> None:
    with torch.no_grad():
        offset = 0
        for p in params:
            p.copy_(values[offset:offset + p.numel()].view_as(p))
            offset += p.numel()


def adam_first_step(params: list[torch.Tensor], grad: torch.Tensor, lr: float) -> torch.Tensor:
    """The parameters ``(P,)`` after one ``torch.optim.Adam`` step with gradient ``grad`` ``(P,)`` from
    ``params`` (left unchanged)."""
    start = flat(params).detach().clone()
    copies = [p.detach().clone().requires_grad_(True) for p in params]
    optimiser = torch.optim.Adam(copies, lr=lr)
    offset = 0
    for q in copies:
        q.grad = grad[offset:offset + q.numel()].view_as(q).clone()
        offset += q.numel()
    optimiser.step()
    after = flat(copies).detach()
    set_flat(params, start)
    return after


def stored_state(run_id: str, trial: int, tracking_uri: str | None):
    """``(run configuration, episodes, hyperparameters, controller state)`` of a stored ``mc-pilco`` run
    at its trial-``trial`` checkpoint."""
    from harness.checkpoint import checkpoint_name, load_checkpoint
    from harness.runner import config_from_identity
    from harness.store import Store, layout

    reader = Store(tracking_uri).run(run_id)
    try:
        if reader.params.get("learner") != "mc-pilco":
            raise CheckpointError(f"run {run_id} is a {reader.params.get('learner')!r} run; this needs an mc-pilco run")
        saved = load_checkpoint(reader.file(f"{layout.CHECKPOINTS}/{checkpoint_name(trial)}"))
    finally:
        reader.close()
    return (config_from_identity(saved.identity), saved.interaction["episodes"], saved.learner["hyperparameters"],
            saved.learner["controller"])


def build(config, episodes, hyperparameters, controller_state, trial: int):
    """The run's learner (on the CPU), the GP refit on ``episodes`` warm-started from ``hyperparameters``
    and the stored controller: ``(learner, posterior, controller)``."""
    from harness.runner import new_learner, prepare
    from harness.task import Episode
    from plugins.pilco.gp import GPHyperparameters
    from plugins.pilco.gp_data import train_dynamics

    options = {**config.learner_options, "device": "cpu"}
    prep = prepare(dataclasses.replace(config, learner_options=options))
    learner = new_learner(prep)
    model = learner.new_model()
    train_dynamics(model, [Episode(**ep) for ep in episodes], learner.layout, learner.options, prep.task.spec.measurement_noise_std,
                   GPHyperparameters.from_dict(hyperparameters), seed=learner.seed + trial)
    posterior = model.posterior(max_basis=learner.options["planning_basis"]).detach()
    controller = learner.new_controller(torch.Generator().manual_seed(learner.seed))
    controller.load_state_dict(controller_state)
    return learner, posterior, controller


def objective_for(learner, posterior, controller, trial: int, horizon: int, particles: int):
    """Trial ``trial + 1``'s particle objective over ``horizon`` steps with ``particles`` particles (on the CPU)."""
    from plugins.mc_pilco.particles import ParticleObjective

    spec = learner.spec
    init_mean = torch.as_tensor(np.asarray(spec.init_mean, dtype=np.float64))
    init_cov = torch.as_tensor(np.asarray(spec.init_cov, dtype=np.float64))
    return ParticleObjective(controller, posterior, learner.layout, learner.planning_cost(trial + 1), init_mean, init_cov,
                             horizon, particles, cuda_graph=False)


@dataclasses.dataclass(frozen=True)
class AdamVariant:
    """One Adam path: its label, option ``step_scale`` (``none``, ``inputs``) and learning rate (None: the run's)."""

    label: str
    step_scale: str = "none"
    lr: float | None = None


def parse_adam_variant(text: str) -> AdamVariant:
    """``""`` (the run's search), ``"step_scale=inputs"``, ``"lr=0.001"`` or both, comma-separated."""
    pairs = [p.strip() for p in text.split(",") if p.strip()]
    bad = [p for p in pairs if "=" not in p or p.split("=", 1)[0] not in ("step_scale", "lr")]
    if bad:
        raise OptionError(f"Adam variant {text!r}: {bad[0]!r} is not step_scale=... or lr=...; write e.g. "
                          "\"step_scale=inputs,lr=0.003\"")
    values = dict(p.split("=", 1) for p in pairs)
    if values.get("step_scale", "none") not in ("none", "inputs"):
        raise OptionError(f"Adam variant {text!r}: step_scale is none or inputs")
    try:
        lr = float(values["lr"]) if "lr" in values else None
    except ValueError:
        raise OptionError(f"Adam variant {text!r}: lr is a number, e.g. lr=0.001") from None
    return AdamVariant(text or "the run's", values.get("step_scale", "none"), lr)


def measure_horizon(learner, posterior, controller, trial: int, horizon: int, *, batches: int, common: int, adam_steps: int,
                    lr: float, seed: int, variants: tuple[AdamVariant, ...] = (AdamVariant("the run's"),),
                    episodes=None) -> dict:
    """Every figure of one horizon's row (see the module docstring), the controller left as it was;
    ``variants``: the Adam paths (a ``step_scale=inputs`` one needs ``episodes``, the data recorded)."""
    from plugins.mc_pilco.optimise import adam_step

    particles = int(learner.options["particles"])
    draws = objective_for(learner, posterior, controller, trial, horizon, particles)
    fixed = objective_for(learner, posterior, controller, trial, horizon, common)
    params = draws.parameters()
    start = flat(params).detach().clone()
    common_seed = 10_000 * seed + 7

    def J_common(values: torch.Tensor | None = None) -> float:
        if values is not None:
            set_flat(params, values)
        with torch.no_grad():
            value = float(fixed.value(torch.Generator().manual_seed(common_seed)))
        set_flat(params, start)
        return value

    J_c = fixed.value(torch.Generator().manual_seed(common_seed))
    g_c = flat(torch.autograd.grad(J_c, params))
    J_c = float(J_c.detach())
    direction = g_c / g_c.norm()
    plus, minus = J_common(start + DIFFERENCE_STEP * direction), J_common(start - DIFFERENCE_STEP * direction)
    difference = (plus - minus) / (2 * DIFFERENCE_STEP)

    gen = torch.Generator().manual_seed(10_000 * seed + 11)
    values, grads = [], []
    for _ in range(batches):
        J, usable, g = draws.value_and_grad(gen, 0.0)
        if not usable:
            raise FloatingPointError(f"horizon {horizon}: a draw's J_hat or gradient is not finite")
        values.append(J)
        grads.append(flat(g))
    G = torch.stack(grads)
    stats = gradient_statistics(G.numpy(), g_c.numpy())
    step_changes = [J_common(adam_first_step(params, g, lr)) - J_c for g in G]
    first_step = adam_first_step(params, g_c, lr)
    reference_change = J_common(first_step) - J_c
    length = float((first_step - start).norm())  # steepest descent over the same distance
    descent_change = J_common(start - length * direction) - J_c

    trajectories = {}
    checks = sorted({max(1, round(adam_steps * f)) for f in (0.1, 0.25, 0.5, 0.75, 1.0)}) if adam_steps > 0 else []
    for variant in variants if adam_steps > 0 else ():
        scales = learner.step_scales(controller, episodes, variant.step_scale) if variant.step_scale != "none" else None
        optimiser = torch.optim.Adam(params, lr=lr if variant.lr is None else variant.lr)
        gen = torch.Generator().manual_seed(10_000 * seed + 13)  # the same draws for every variant
        trajectory = trajectories[variant.label] = []
        for step in range(1, adam_steps + 1):
            _, usable, g = draws.value_and_grad(gen, 0.0)
            if usable:
                adam_step(optimiser, params, g, scales)
            if step in checks:
                with torch.no_grad():
                    trajectory.append((step, float(fixed.value(torch.Generator().manual_seed(common_seed)))))
        set_flat(params, start)
    return {
        "horizon": horizon, "particles": particles, "J_mean": float(np.mean(values)), "J_std": float(np.std(values, ddof=1)),
        "J_common": J_c, "grad_norm": float(g_c.norm()), "autograd": float(g_c @ direction), "difference": difference,
        "stats": stats, "step_changes": np.asarray(step_changes), "reference_change": reference_change,
        "predicted_change": -lr * float(g_c.abs().sum()), "descent_change": descent_change, "descent_predicted": -length * float(g_c.norm()),
        "step_length": length, "trajectories": trajectories,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--trial", type=int, required=True, help="the checkpoint: the state after trial K's hand-over")
    parser.add_argument("--horizons", type=int, nargs="+", default=[10, 20, 40])
    parser.add_argument("--batches", type=int, default=16, help="independent draws of the run's particles (>= 2)")
    parser.add_argument("--common", type=int, default=4000, help="particles of the common (reference) estimate")
    parser.add_argument("--adam-steps", type=int, default=50)
    parser.add_argument("--lr", type=float, default=None, help="Adam's learning rate (default: the run's)")
    parser.add_argument("--adam-variants", nargs="+", default=[""],
                        help='Adam paths: "" (the run\'s), "step_scale=inputs", "lr=0.001", or both comma-separated')
    parser.add_argument("--seed", type=int, default=0, help="seed of every draw here")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.batches < 2:
        parser.error(f"--batches {args.batches}: the spread between draws needs at least 2")
    variants = tuple(parse_adam_variant(text) for text in args.adam_variants)
    torch.set_num_threads(1)
    load, t0 = load_average(), time.perf_counter()
    config, episodes, hyperparameters, controller_state = stored_state(args.run, args.trial, args.tracking_uri)
    learner, posterior, controller = build(config, episodes, hyperparameters, controller_state, args.trial)
    lr = float(args.lr if args.lr is not None else learner.options["lr"])
    rows = []
    for horizon in args.horizons:
        row = measure_horizon(learner, posterior, controller, args.trial, horizon, batches=args.batches, common=args.common,
                              adam_steps=args.adam_steps, lr=lr, seed=args.seed, variants=variants,
                              episodes=[Episode(**ep) for ep in episodes])
        rows.append(row)
        s = row["stats"]
        print(f"H {horizon:3d}: J {row['J_mean']:.2f} +- {row['J_std']:.2f}, signal {s.signal_fraction:.2f}, "
              f"cos(draw, ref) {np.mean(s.reference_cosine):.2f}, first step dJ_c {np.mean(row['step_changes']):+.3f} "
              f"(ref {row['reference_change']:+.3f}), Adam {row['trajectories']} ({time.perf_counter() - t0:.0f} s)", flush=True)

    n_params = int(sum(p.numel() for p in controller.parameters() if p.requires_grad))
    particles = rows[0]["particles"] if rows else learner.options["particles"]
    lines = [
        f"# mc-pilco's gradient between particle draws: run `{args.run[:8]}`, after trial {args.trial}", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        machine_line(load) + "  ",
        f"State: {learner.spec.name}, the GP refit on the {len(episodes)} episodes of the trial-{args.trial} checkpoint "
        f"(warm-started from its hyperparameters), planning basis {posterior.inputs.shape[0]}; the controller handed over at "
        f"trial {args.trial} ({n_params} parameters; trial {args.trial + 1}'s search starts there). Draws: {args.batches} of "
        f"the run's {particles} particles each, no dropout; reference: one fixed draw of {args.common} particles (J_c, g_c). "
        f"Adam learning rate {lr:g}. One thread.", "",
        "| H | J_hat over draws: mean (std) | J_c | dJ_c along g_c/|g_c|: autograd / differences | signal fraction (independent noise: "
        f"{1 / math.sqrt(args.batches):.2f}) | cosine between draws | cosine draw - g_c: mean (min-max) | signs as g_c |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s = r["stats"]
        lines.append(f"| {r['horizon']} | {r['J_mean']:.3f} ({r['J_std']:.3f}) | {r['J_common']:.3f} | {r['autograd']:.6g} / "
                     f"{r['difference']:.6g} | {s.signal_fraction:.2f} | {s.pairwise_cosine:.2f} | {np.mean(s.reference_cosine):.2f} "
                     f"({np.min(s.reference_cosine):.2f}-{np.max(s.reference_cosine):.2f}) | {100 * s.sign_agreement:.0f} % |")
    lines += ["", "Adam's first update (every parameter moved by about the learning rate, in its gradient's sign), scored on the "
              "common particles; then the search's own steps:", "",
              "| H | from a draw's gradient: dJ_c mean (min-max), draws lowering J_c | from g_c: dJ_c (first-order "
              "prediction) | steepest descent along -g_c as far (step length): dJ_c (first-order) |", "|---|---|---|---|"]
    for r in rows:
        c = r["step_changes"]
        lines.append(f"| {r['horizon']} | {c.mean():+.4f} ({c.min():+.4f} to {c.max():+.4f}), {int((c < 0).sum())}/{len(c)} | "
                     f"{r['reference_change']:+.4f} ({r['predicted_change']:+.4f}) | ({r['step_length']:.3g}) "
                     f"{r['descent_change']:+.4f} ({r['descent_predicted']:+.4f}) |")
    if args.adam_steps > 0:
        lines += ["", f"{args.adam_steps} Adam steps on fresh draws of the run's particles (the same draws for every path), "
                  "J_c on the common particles along the way (step_scale=inputs: Adam in the units of the policy inputs' "
                  "spread over the data, option `step_scale` of the learner):", "",
                  "| H | Adam path | J_c at step 0 -> (step: J_c) |", "|---|---|---|"]
        for r in rows:
            for label, path in r["trajectories"].items():
                text = ", ".join(f"{step}: {value:.3f}" for step, value in path)
                lines.append(f"| {r['horizon']} | {label} | {r['J_common']:.3f} -> {text} |")
    lines += ["", f"Wall time {time.perf_counter() - t0:.0f} s."]
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
