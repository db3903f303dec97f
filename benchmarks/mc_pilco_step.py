"""What one MC-PILCO Adam step costs, and what planning on fewer basis points changes in its estimate.

Usage::

    .venv/bin/python benchmarks/mc_pilco_step.py [--tasks cartpole unicycle] [--repeats 5] [--device cuda] [--compare-prediction]

For each task: a dynamics GP on ``n`` transitions of uniformly random rollouts of the real task, with
hyperparameters set from the data's scales (as ``benchmarks/task_objectives.py`` does: they do not
change the cost of a step), the task's preset controller fresh from seed 0, and ``mc-pilco``'s
particle objective at its defaults (400 particles, the preset's planning horizon, dropout 0.25). Each
row is one posterior: the full GP on all ``n`` points, or the FITC posterior on ``planning_basis``
of them that the learner's option builds (``GPModel.posterior(max_basis)``). Columns:

* ms per Adam step (the estimate J_hat and its gradient: forward and backward), median of
  ``--repeats`` after a warm-up, and what the learner's default search of at most 1500 steps costs at
  that rate: CPU time on one torch thread with ``--device cpu`` (the default); with ``--device cuda``
  the wall time on the GPU (``mc-pilco``'s ``device=cuda``: the GP, controller, cost and particles
  there, the random numbers drawn on the host as the learner draws them), each step ending with a
  synchronisation, so the wall is the real latency; on a GPU the row's first column launches every
  operation (``cuda_graph=False``) and a second column replays the step as a CUDA graph (the learner's
  default), which the search's minutes are computed from;
* J_hat with dropout 0 on one fixed set of random numbers, and its difference from the full GP's on
  the same numbers, beside the Monte-Carlo standard error of J_hat itself (the spread over 20 sets of
  random numbers / sqrt(20)): a reduced basis whose change is well inside that error changes the
  search's signal less than its own noise does. The controller is fresh (the learner's first
  search starts there); on cart-pole, where it leaves the pendulum hanging, every step costs ~1 and
  J_hat says little about the model; on the unicycle (``init=code``, starting upright) it falls at
  varying times and J_hat is informative.

With ``--compare-prediction`` (CPU): a second table times each row's Adam step with the GP prediction as
the learner makes it (``predict_latent``'s fused pass with its closed-form gradient) and as the torch
composition differentiated by autograd (``fused=False``, the path before it), alternately in one process,
from the learner's own initial controller (spread centres), and gives how far J_hat and its gradient are apart.

Writes ``results/benchmarks/mc_pilco_step.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from benchmarks.task_objectives import random_rollout_data  # noqa: E402

#: task -> (task options, transitions n, planning_basis values to compare)
SIZES: dict[str, tuple[dict[str, str], int, tuple[int, ...]]] = {
    "cartpole": ({}, 400, (300, 200, 100, 50)),
    "unicycle": ({"init": "code"}, 300, (200, 100, 50)),
}


def particle_objectives(task_name: str, options: dict[str, str], n: int, bases: tuple[int, ...], particles: int,
                        device: torch.device = torch.device("cpu"), learner_options: dict[str, str] | None = None,
                        full: bool = True):
    """``{label: ParticleObjective}``: the full GP on ``n`` random-rollout transitions (unless not ``full``),
    then FITC on each basis size, each with its posterior, controller, cost and initial distribution on
    ``device``. The controller is ``mc-pilco``'s initial one for seed 0 with ``learner_options`` (default: the
    reference's centres, ``centres=initial``, as this benchmark's committed rows were measured with)."""
    from harness.discovery import load_task
    from plugins.mc_pilco.learner import McPilco
    from plugins.mc_pilco.particles import ParticleObjective
    from plugins.pilco.cost import CostMoments
    from plugins.pilco.gp import full_posterior
    from plugins.pilco.sparse import reduced_posterior

    task = load_task(task_name)(**options)
    spec = task.spec
    learner = McPilco(spec, {"centres": "initial"} | (learner_options or {}) | {"particles": particles}, 0)
    X, Y, log_ell, log_alpha, log_sigma = random_rollout_data(task, learner.layout, n)
    posteriors = {f"all {n} (full GP)": full_posterior(X, Y, log_ell, log_alpha, log_sigma)} if full else {}
    for m in bases:
        posteriors[f"{m} (FITC)"] = reduced_posterior(X, Y, X, log_ell, log_alpha, log_sigma, m)
    cost = CostMoments(spec.cost, learner.cost_width, device)
    mean = torch.as_tensor(spec.init_mean, dtype=torch.float64, device=device)
    cov = torch.as_tensor(spec.init_cov, dtype=torch.float64, device=device)
    objectives = {}
    for label, posterior in posteriors.items():
        controller = learner.new_controller(torch.Generator().manual_seed(0))
        objectives[label] = ParticleObjective(controller.to(device), posterior.detach().to(device), learner.layout, cost, mean, cov,
                                              learner.horizon, particles)
    return objectives, learner.horizon


def step_ms(objective, repeats: int, device: torch.device) -> float:
    """Median ms of one Adam step's J_hat + gradient (:meth:`ParticleObjective.value_and_grad`: the random
    numbers drawn on the host, the estimate, its gradient and the host's read of J_hat): CPU time on the
    CPU, wall time on a GPU (where the first call also captures the CUDA graph, if ``cuda_graph``)."""
    generator = torch.Generator().manual_seed(0)
    clock = time.perf_counter if device.type == "cuda" else time.process_time
    objective.value_and_grad(generator, 0.25)  # warm-up (and capture)
    times = []
    for _ in range(repeats):
        start = clock()
        objective.value_and_grad(generator, 0.25)  # ends with a host read of J_hat: the wall is the real latency
        times.append(clock() - start)
    return 1e3 * statistics.median(times)


@contextlib.contextmanager
def composed_prediction():
    """Inside the block the particles predict through the torch composition differentiated by autograd
    (``predict_latent(..., fused=False)``, the path before the fused pass) instead of the fused pass."""
    import plugins.mc_pilco.particles as particles
    from plugins.pilco.gp import predict_latent

    particles.predict_latent = functools.partial(predict_latent, fused=False)
    try:
        yield
    finally:
        particles.predict_latent = predict_latent


def compare_prediction(objective, repeats: int) -> tuple[float, float, float, float]:
    """``(ms fused, ms composed, |dJ| relative, max |d grad| relative)``: CPU ms per Adam step with the fused
    prediction and with the composition, timed alternately (``repeats`` each, medians), and how far J_hat and
    its gradient are apart on the same random numbers (dropout 0.25)."""
    fused, composed = [], []
    outputs = []
    for side in (fused, composed) * (repeats + 1):
        context = composed_prediction() if side is composed else contextlib.nullcontext()
        with context:
            start = time.process_time()
            value, _, grads = objective.value_and_grad(torch.Generator().manual_seed(1), 0.25)
            side.append(time.process_time() - start)
        if len(outputs) < 2:
            outputs.append((value, torch.cat([g.reshape(-1) for g in grads])))
    (v1, g1), (v2, g2) = outputs
    return (1e3 * statistics.median(fused[1:]), 1e3 * statistics.median(composed[1:]), abs(v1 - v2) / abs(v2),
            float((g1 - g2).abs().max() / g2.abs().max()))


def estimates(objective, sets: int = 20) -> np.ndarray:
    with torch.no_grad():
        return np.array([float(objective.value(torch.Generator().manual_seed(100 + s))) for s in range(sets)])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--particles", type=int, default=400)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                        help="where the particles run (cuda: wall time on the GPU; cpu: CPU time on one thread)")
    parser.add_argument("--compare-prediction", action="store_true",
                        help="CPU: also time each row's Adam step with the GP prediction composed by torch and differentiated "
                             "by autograd (before the fused pass), alternating with the fused one, and give how far J_hat and "
                             "its gradient are apart")
    parser.add_argument("--out", type=Path, default=None,
                        help="default: results/benchmarks/mc_pilco_step.md (mc_pilco_step_cuda.md with --device cuda)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch sees no CUDA GPU here; run without --device (CPU)")
    gpu = device.type == "cuda"
    out = args.out or ROOT / "results" / "benchmarks" / ("mc_pilco_step_cuda.md" if gpu else "mc_pilco_step.md")
    torch.set_num_threads(1)
    load = load_average()
    where = f"on the GPU ({torch.cuda.get_device_name(device)}), wall time" if gpu else "one torch thread, CPU time"
    unit = "GPU wall" if gpu else "CPU"
    lines = [f"# MC-PILCO: {unit} per Adam step, and the estimate on fewer basis points", "",
             f"Command: `{command_line(__file__, argv)}`  ", f"{machine_line(load)}  ",
             f"{args.particles} particles, dropout 0.25 in the timed steps; J_hat without dropout; {where}.", "",
             f"| task | planning basis | horizon | {unit} ms per Adam step{', every operation launched' if gpu else ''} | speed-up |"
             + (" ms per Adam step, replayed as a CUDA graph (the default) | graph speed-up |" if gpu else "")
             + f" a search of 1500 steps (the default), {unit} min "
             "| J_hat (20 sets of random numbers: mean) | its Monte-Carlo standard error "
             "| J_hat minus the full GP's, same random numbers (mean [min, max]) |",
             "|---" * (11 if gpu else 9) + "|"]
    compared = []
    for task in args.tasks:
        options, n, bases = SIZES[task]
        objectives, horizon = particle_objectives(task, options, n, bases, args.particles, device)
        reference = None
        base_ms = None
        for label, objective in objectives.items():
            ms = step_ms(objective, args.repeats, device)
            graph = ""
            if gpu:  # the learner's default: replayed as a CUDA graph; the row's own ms: every operation launched
                objective.cuda_graph = False
                ms = step_ms(objective, args.repeats, device)
                objective.cuda_graph = True
                graph_ms = step_ms(objective, args.repeats, device)
                graph = f" {graph_ms:.1f} | {ms / graph_ms:.1f}x |" if objective.graph_error is None else f" ({objective.graph_error}) | |"
            values = estimates(objective)
            if reference is None:
                reference, base_ms = values, ms
            diff = values - reference
            lines.append(f"| {task} | {label} | {horizon} | {ms:.0f} | {base_ms / ms:.1f}x |{graph} {1500 * (graph_ms if gpu else ms) / 6e4:.1f} | {values.mean():.3f} | "
                         f"{values.std(ddof=1) / np.sqrt(len(values)):.3f} | {diff.mean():+.3f} [{diff.min():+.3f}, {diff.max():+.3f}] |")
        if args.compare_prediction and not gpu:  # from the learner's own initial controller (spread centres), where
            # J_hat is smooth in theta: from the reference's centres rounding differences grow over the horizon
            for label, objective in particle_objectives(task, options, n, bases, args.particles, device,
                                                        learner_options={"centres": "spread"})[0].items():
                compared.append((task, label, *compare_prediction(objective, args.repeats)))
    if compared:
        lines += ["", "The GP prediction of each step: the fused pass with its closed-form gradient (the default) against the "
                  "torch composition differentiated by autograd (before it), from the learner's initial controller (spread "
                  "centres; from the reference's J_hat is rough and rounding differences grow over the horizon), timed alternately in this process "
                  f"({args.repeats} each, medians), and how far J_hat and its gradient are apart on the same random numbers:", "",
                  "| task | planning basis | CPU ms per Adam step, fused | composed | speed-up | J_hat, relative difference "
                  "| gradient, largest difference relative to its largest entry |", "|---|---|---|---|---|---|---|"]
        for task, label, fused, composed, dj, dg in compared:
            lines.append(f"| {task} | {label} | {fused:.0f} | {composed:.0f} | {composed / fused:.2f}x | {dj:.1e} | {dg:.1e} |")
    write_report(lines, out)


if __name__ == "__main__":
    main()
