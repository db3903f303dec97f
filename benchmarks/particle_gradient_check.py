"""Is MC-PILCO's particle estimate of J smooth in the policy's parameters, and does Adam lower it?

Usage::

    .venv/bin/python benchmarks/particle_gradient_check.py [--task cartpole] [--basis 100] [--cost-width 1.0] \\
        [--horizons 10 20 40] [--steps 300] [--out results/benchmarks/particle_gradient_check.md]

``mc-pilco`` searches with Adam on ``J_hat(theta)``, a sum over ``H`` steps of particle costs that is a
deterministic function of ``theta`` once the random numbers are drawn. If ``J_hat`` is smooth, its gradient
predicts how it changes over a step of the size Adam takes (learning rate 0.01); if it is rough (a chaotic
closed loop, or a policy whose small parameter changes make large control changes), the gradient is a
local slope that says nothing at that scale and the search wanders. This benchmark measures which, for
each initial controller of the learner (option ``centres``: ``initial``, the reference's, drawn from the
initial state distribution; ``spread``, MC-PILCO's, spread over the state space):

* the largest |weight| of the RBF policy (``beta = (K + 0.01^2 I)^-1 t``: large where the centres nearly
  coincide and the policy's Gram matrix is close to singular);
* per planning horizon ``H``: the directional derivative of ``J_hat`` along one random unit direction of
  ``theta`` by autograd, and by central differences with steps 1e-3, 1e-5 and 1e-7 (same random numbers,
  no dropout). Smooth: all agree. Rough: only the smallest step agrees with autograd;
* Adam as the learner runs it (:func:`plugins.mc_pilco.optimise.optimise_particles` with the learner's
  learning rate, dropout and its schedule, at most ``--steps`` steps, windows of the learner's 100 steps or a
  quarter of ``--steps`` if that is fewer, so that a short search still sees the schedule) at the learner's
  planning horizon: ``J_hat`` before and after on the same fixed particles (no dropout), and the window means
  along the way.

The model: a GP on ``--n`` transitions of uniformly random rollouts of the real task, hyperparameters set
from the data's scales (``benchmarks/task_objectives.py``), planned through FITC on ``--basis`` points
(the learner's ``planning_basis``), the planning cost with ``--cost-width``. One torch thread.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from benchmarks.mc_pilco_step import particle_objectives  # noqa: E402
from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402

STEPS = (1e-3, 1e-5, 1e-7)


def directional_derivatives(objective, direction: list[torch.Tensor], seed: int) -> tuple[float, list[float]]:
    """``(autograd, [central difference per step in STEPS])`` of ``J_hat`` along ``direction`` (unit norm
    over all parameters) at fixed random numbers (no dropout)."""
    params = objective.parameters()
    draws = objective.draw(torch.Generator().manual_seed(seed), 0.0)
    J = objective.rollout_drawn(draws, 0.0)[1].sum()
    grads = torch.autograd.grad(J, params)
    exact = float(sum((g * d).sum() for g, d in zip(grads, direction)))
    differences = []
    with torch.no_grad():
        for eps in STEPS:
            for p, d in zip(params, direction):
                p.add_(eps * d)
            plus = float(objective.rollout_drawn(draws, 0.0)[1].sum())
            for p, d in zip(params, direction):
                p.sub_(2 * eps * d)
            minus = float(objective.rollout_drawn(draws, 0.0)[1].sum())
            for p, d in zip(params, direction):
                p.add_(eps * d)
            differences.append((plus - minus) / (2 * eps))
    return exact, differences


def main(argv: list[str] | None = None) -> None:
    from plugins.mc_pilco.learner import McPilco
    from plugins.mc_pilco.optimise import optimise_particles

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="cartpole")
    parser.add_argument("--n", type=int, default=400, help="random-rollout transitions the GP is built on")
    parser.add_argument("--basis", type=int, default=100, help="FITC basis points the particles go through (planning_basis)")
    parser.add_argument("--cost-width", type=float, default=1.0, help="planning cost width (mc-pilco's cost_width)")
    parser.add_argument("--particles", type=int, default=400)
    parser.add_argument("--horizons", type=int, nargs="+", default=[10, 20, 40])
    parser.add_argument("--steps", type=int, default=300, help="Adam steps at most (the learner's max_steps)")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "particle_gradient_check.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load = load_average()
    defaults = McPilco.option_set().defaults()
    lines = [f"# MC-PILCO: is the particle estimate of J smooth in the policy's parameters, and does Adam lower it? ({args.task})", "",
             f"Command: `{command_line(__file__, argv)}`  ", f"{machine_line(load)}  ",
             f"GP on {args.n} random-rollout transitions, particles through FITC on {args.basis} of them; planning cost width "
             f"{args.cost_width}; {args.particles} particles; one direction of theta (unit norm, seed 0), random numbers seed 5, "
             "no dropout in the derivatives.", "",
             "| initial centres | max abs policy weight | H | J_hat | dJ along the direction, autograd | central difference, step "
             + " / ".join(f"{eps:g}" for eps in STEPS) + " |", "|---|---|---|---|---|---|"]
    searches = []
    for centres in ("initial", "spread"):
        options = {"centres": centres, "cost_width": str(args.cost_width)}
        objective = next(iter(particle_objectives(args.task, {}, args.n, (args.basis,), args.particles,
                                                  learner_options=options, full=False)[0].values()))
        base = objective.controller.base
        with torch.no_grad():
            weight = float(base.posterior().beta.abs().max()) if hasattr(base, "posterior") else float("nan")
        params = objective.parameters()
        gen = torch.Generator().manual_seed(0)
        direction = [torch.randn(p.shape, generator=gen, dtype=p.dtype) for p in params]
        norm = math.sqrt(sum(float((d * d).sum()) for d in direction))
        direction = [d / norm for d in direction]
        full_horizon = objective.horizon
        for horizon in args.horizons:
            objective.horizon = horizon
            exact, differences = directional_derivatives(objective, direction, seed=5)
            with torch.no_grad():
                J = float(objective.value(torch.Generator().manual_seed(5)))
            lines.append(f"| {centres} | {weight:.3g} | {horizon} | {J:.3f} | {exact:.4g} | "
                         + " / ".join(f"{d:.4g}" for d in differences) + " |")
            print(lines[-1], flush=True)
        objective.horizon = full_horizon  # the learner's planning horizon
        start = time.process_time()
        result = optimise_particles(objective, max_steps=args.steps, lr=defaults["lr"], dropout=defaults["dropout"],
                                    dropout_step=defaults["dropout_step"], lr_decay=defaults["lr_decay"],
                                    window=min(defaults["window"], max(1, args.steps // 4)),
                                    min_improvement=defaults["min_improvement"], seed=7)
        searches.append((centres, objective.horizon, result, time.process_time() - start))
        print(centres, result.J_before, result.J_after, flush=True)
    lines += ["", f"Adam as the learner runs it (learning rate {defaults['lr']}, dropout {defaults['dropout']} reduced by "
              f"{defaults['dropout_step']} when a window's mean stalls), at most {args.steps} steps, from each initial controller:", "",
              "| initial centres | H | J_hat before | J_hat after | steps | dropout reductions | window means (with dropout) | CPU s |",
              "|---|---|---|---|---|---|---|---|"]
    for centres, horizon, result, seconds in searches:
        lines.append(f"| {centres} | {horizon} | {result.J_before:.3f} | {result.J_after:.3f} | {result.steps} | {result.reductions} | "
                     + ", ".join(f"{t:.2f}" for t in result.trace) + f" | {seconds:.0f} |")
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
