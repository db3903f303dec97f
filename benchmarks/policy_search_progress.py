"""How far one PILCO policy search gets: J(theta) against J+dJ evaluations for several optimiser settings.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/policy_search_progress.py --task double-pendulum --set horizon=60 \
        [--rollouts 1] [--seeds 0 1] [--budget 300] [--configs default memory100 ...]

The situation is the ``pilco`` learner's first policy search on the task: its preset's random
rollouts (``--rollouts`` of them; the preset's count by default) through a counted
:class:`~harness.interaction.Interaction`, the dynamics GP fitted by :class:`~plugins.pilco.gp.GPModel`
exactly as the learner fits it, the preset's controller fresh from the seed, J over the planning
horizon from ``N(mu0, Sigma0)``. Every configuration starts from the same theta with the same
model and the same budget of J+dJ evaluations, so their traces differ only by the optimiser.

Writes ``results/benchmarks/policy_search_progress_<task>.md`` (J after 50/100/.../budget
evaluations, median over seeds, and the line searches used) and a ``.png`` of the traces.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.discovery import load_task  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from harness.interaction import Interaction  # noqa: E402
from plugins.pilco.gp import GPModel  # noqa: E402
from plugins.pilco.learner import Pilco  # noqa: E402
from plugins.pilco.policy import transitions  # noqa: E402
from plugins.pilco.objective import PolicyObjective  # noqa: E402
from plugins.pilco.policy_search import optimise_policy  # noqa: E402
from plugins.random_learner import UniformRandomPolicy  # noqa: E402

#: name -> keyword arguments of optimise_policy (beside the evaluation budget)
CONFIGS: dict[str, dict] = {
    "default": {"max_iterations": 150, "memory": 10},
    "memory100": {"max_iterations": 150, "memory": 100},
    "unlimited-iterations": {"max_iterations": 10_000, "memory": 10},
    "memory100-unlimited-iterations": {"max_iterations": 10_000, "memory": 100},
}


def first_search_objective(task_name: str, options: dict[str, str], seed: int, rollouts: int | None):
    """The learner's trial-1 :class:`PolicyObjective` (fitted GP, fresh controller) on the task."""
    task = load_task(task_name)(**options)
    spec = task.spec
    learner = Pilco(spec, {}, seed)
    interaction = Interaction(task.make_env(), spec, seed=seed)
    scale = learner.preset.random_scale
    explore = UniformRandomPolicy(scale * spec.action_low, scale * spec.action_high, seed)
    for _ in range(rollouts or learner.preset.initial_rollouts):
        interaction.rollout(explore)
    x, y = transitions(interaction.episodes, learner.layout)
    model = GPModel(sparse_threshold=learner.preset.sparse_threshold, num_pseudo=learner.num_pseudo)
    model.fit(x, y, seed=seed + 1)
    controller = learner.new_controller(torch.Generator().manual_seed(seed))
    objective = PolicyObjective(controller, model.posterior(), learner.layout, spec.cost, spec.init_mean, spec.init_cov,
                                learner.horizon, width=learner.cost_width)
    return objective, x.shape[0]


def traced_search(objective: PolicyObjective, budget: int, config: dict) -> tuple[list[float], object]:
    """Run one policy search from the objective's current theta; the J of every evaluation in order."""
    trace: list[float] = []
    inner = objective.value_and_grad

    def recording(theta):
        value, grad = inner(theta)
        trace.append(value)
        return value, grad

    objective.value_and_grad = recording
    try:
        result = optimise_policy(objective, max_evaluations=budget, **config)
    finally:
        objective.value_and_grad = inner
    return trace, result


def best_so_far(trace: list[float], length: int) -> np.ndarray:
    """Running minimum of the finite J values, padded with its last value to ``length``."""
    values = np.array([v if math.isfinite(v) else np.inf for v in trace])
    run = np.minimum.accumulate(values)
    return np.concatenate([run, np.full(max(0, length - run.size), run[-1])])[:length]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="double-pendulum")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="task option")
    parser.add_argument("--rollouts", type=int, default=None, help="random rollouts before the search (default: preset)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--budget", type=int, default=300, help="J+dJ evaluations per search")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    options = dict(kv.split("=", 1) for kv in args.set)
    checkpoints = [c for c in (25, 50, 100, 150, 200, 300, 400, 600, 800, 1000) if c < args.budget] + [args.budget]
    traces: dict[str, list[np.ndarray]] = {name: [] for name in args.configs}
    rows = []
    for seed in args.seeds:
        objective, n = first_search_objective(args.task, options, seed, args.rollouts)
        theta0 = objective.get_flat()
        for name in args.configs:
            objective.set_flat(theta0)
            start = time.process_time()
            trace, result = traced_search(objective, args.budget, CONFIGS[name])
            cpu = time.process_time() - start
            traces[name].append(best_so_far(trace, args.budget + 1))
            rows.append((seed, name, n, result.J_before, result.J_after, result.iterations, result.evaluations, cpu, result.message))
            print(f"seed {seed} {name:32s} n={n} J {result.J_before:.2f} -> {result.J_after:.2f} "
                  f"({result.iterations} line searches, {result.evaluations} evaluations, {cpu:.0f} s CPU; {result.message})", flush=True)

    task_slug = args.task
    out = Path(args.out) if args.out else ROOT / "results" / "benchmarks" / f"policy_search_progress_{task_slug}.md"
    lines = [
        f"# One PILCO policy search on `{args.task}`: J(theta) against J+dJ evaluations",
        "",
        f"Command: `{command_line(__file__, env='OMP_NUM_THREADS=1')}`  ",
        f"Date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Situation: the learner's first policy search "
        f"(preset random rollouts{'' if args.rollouts is None else f' x {args.rollouts}'}, GP fitted as in the learner, "
        "fresh preset controller); every configuration starts from the same theta and model.",
        "",
        "Best J so far after k evaluations, median over seeds " + ", ".join(map(str, args.seeds)) + ":",
        "",
        "| optimiser | " + " | ".join(f"k={c}" for c in checkpoints) + " | line searches (median) |",
        "|---|" + "---|" * (len(checkpoints) + 1),
    ]
    for name in args.configs:
        runs = np.stack(traces[name])
        meds = [float(np.median(runs[:, c])) for c in checkpoints]
        its = float(np.median([r[5] for r in rows if r[1] == name]))
        lines.append(f"| {name} (`{CONFIGS[name]}`) | " + " | ".join(f"{m:.2f}" for m in meds) + f" | {its:.0f} |")
    lines += ["", "Per seed:", "", "| seed | optimiser | n data | J before | J after | line searches | evaluations | CPU s | stop |",
              "|---|---|---|---|---|---|---|---|---|"]
    for seed, name, n, jb, ja, it, ev, cpu, msg in rows:
        lines.append(f"| {seed} | {name} | {n} | {jb:.2f} | {ja:.2f} | {it} | {ev} | {cpu:.0f} | {msg} |")
    write_report(lines, out)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.6), dpi=110)
    for k, name in enumerate(args.configs):
        for j, run in enumerate(traces[name]):
            ax.plot(np.arange(run.size), run, color=f"C{k}", alpha=0.8, lw=1.2, label=name if j == 0 else None)
    ax.set(xlabel="J + dJ evaluations", ylabel="best J so far", title=f"first policy search on {args.task}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"))
    print(f"wrote {out.with_suffix('.png')}")


if __name__ == "__main__":
    exit_on_error(main)
