"""Does a PILCO policy search exploit its one GP? Replay a trial's search under several GPs of the same data.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/ensemble_search_check.py RUN_ID --trial K [--draws 1 2 3] [--single 1]
        [--episodes 200] [--tracking-uri URI] [--out results/benchmarks]

A sparse GP trains its hyperparameters on a random subset of the data (``gp_hyper_subset``, by default the
sparse threshold's count), drawn afresh every trial. Trial ``K``'s GP is refitted as the run fitted it (same
data, warm start from the run's trial ``K - 1`` GP, the run's budgets and ``gp_refresh_pseudo``) once per
``--draws`` seed, i.e. with other random subsets. Then, from the policy the run handed over at trial ``K - 1``
(where the run's own search started) and with the learner's own search and budgets:

* **single draw s** (``--single``): the search under draw ``s``'s GP alone, as the run searched under its own;
* **mean of the draws**: the search on the mean of J over every draw's GP (J and dJ averaged; each GP sees
  the same policy parameters), a policy that must look good under all of them.

Every policy (and the run's own trial-``K`` policy, searched under the run's own draw) is scored by J
(moment matching, the run's planning settings) under the run's GP and each draw's, and by ``--episodes``
real test episodes from the same initial states (mean cost over the planning horizon, a fall held to the
end; success rate with its 95 % interval). A policy whose J is low only under the GP it was searched on
has found a property of that GP, not of the system. Writes
``ensemble_search_check_<task>_<run>_t<K>.md`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.pilco_prediction_check import real_costs  # noqa: E402
from benchmarks.plateau_search_check import learner_for  # noqa: E402
from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from harness.statistics import rate_interval  # noqa: E402
from plugins.pilco.policy import PilcoPolicy, transitions  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402


class MeanObjective:
    """J and dJ averaged over several objectives of the same controller (one per GP): what
    :func:`~plugins.pilco.policy_search.optimise_policy` needs of an objective (``get_flat``,
    ``set_flat``, ``value_and_grad``)."""

    def __init__(self, objectives: list) -> None:
        self.objectives = objectives

    def get_flat(self) -> np.ndarray:
        return self.objectives[0].get_flat()

    def set_flat(self, theta: np.ndarray) -> None:
        for objective in self.objectives:
            objective.set_flat(theta)

    def value_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        values, grads = zip(*(objective.value_and_grad(theta) for objective in self.objectives))
        return float(np.mean(values)), np.mean(grads, axis=0)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_id")
    parser.add_argument("--trial", type=int, required=True)
    parser.add_argument("--draws", type=int, nargs="+", default=[1, 2, 3], help="seeds of the GP refits' random draws")
    parser.add_argument("--single", type=int, nargs="*", default=None,
                        help="draws to search under alone (default: the first of --draws)")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    args = parser.parse_args(argv)
    single = args.draws[:1] if args.single is None else args.single
    if not set(single) <= set(args.draws):
        sys.exit(f"--single {single}: each must be one of --draws {args.draws}")
    torch.set_num_threads(1)
    with SavedPilcoRun(args.run_id, args.tracking_uri) as run:
        check(run, args, single, argv)


def check(run: SavedPilcoRun, args: argparse.Namespace, single: list[int], argv: list[str] | None) -> None:
    """Refit, search, score and write the report."""
    trial = args.trial
    if trial - 1 not in run.model_trials() or not {trial - 1, trial} <= set(run.policy_trials()):
        sys.exit(f"run {args.run_id} needs the GP of trial {trial - 1} and the policies of trials {trial - 1} and {trial}")
    learner = learner_for(run)
    learner.schedule.horizon = horizon = run.planning_horizon_at(trial)
    layout = learner.layout
    x, y = transitions(run.episodes()[:trial - 1 + run.initial_rollouts], layout)
    gps = {"run's own": run.model(trial)}
    for seed in args.draws:
        start = time.process_time()
        gps[f"draw {seed}"] = run.refit_model(trial, x, y, seed)
        print(f"draw {seed}: refit in {time.process_time() - start:.0f} s CPU", flush=True)
    posteriors = {name: gp.posterior(max_basis=learner.options["planning_basis"]) for name, gp in gps.items()}

    def J_under(controller) -> dict[str, float]:
        """J of ``controller`` under every GP."""
        with torch.no_grad():
            return {name: float(learner.planning_objective(controller, p, threads=1).step_costs()[0].sum())
                    for name, p in posteriors.items()}

    evaluator = Evaluator(run.task, n_episodes=args.episodes, seed=200_000)
    rows = []

    def score(name: str, controller, search=None) -> None:
        per_step, success = real_costs(evaluator, PilcoPolicy.snapshot(controller, layout), horizon)
        Js = J_under(controller)
        rows.append((name, search, Js, float(per_step.sum()), success))
        print(f"{name}: J " + ", ".join(f"{k} {v:.2f}" for k, v in Js.items()) + f"; real {per_step.sum():.2f}, "
              f"success {100 * success:.1f} %" + (f" ({search.evaluations} J + dJ, {search.seconds:.0f} s)" if search else ""), flush=True)

    score(f"the run's trial-{trial} policy (searched under its own GP)", run.policy(trial).controller)
    for seed in single:
        controller = run.policy(trial - 1).controller
        search = learner.search_policy(learner.planning_objective(controller, posteriors[f"draw {seed}"], threads=1), learner.kernel, 1)
        score(f"searched under draw {seed} alone", controller, search)
    controller = run.policy(trial - 1).controller
    mean = MeanObjective([learner.planning_objective(controller, posteriors[f"draw {s}"], threads=1) for s in args.draws])
    search = learner.search_policy(mean, learner.kernel, 1)
    score(f"searched on the mean J of draws {', '.join(map(str, args.draws))}", controller, search)

    names = list(gps)
    lines = [
        f"# Ensemble search check: {run.params['learner']} on {run.params['task']}, run `{args.run_id}`, trial {trial}", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"Trial {trial}'s GP refitted on the same {len(x)} transitions from the run's trial-{trial - 1} GP with the run's budgets, "
        f"its random draws (hyperparameter subset, pseudo-inputs) seeded {', '.join(map(str, args.draws))} instead of the run's "
        f"({run.gp_fit_seed(trial)}). Searches start from the run's trial-{trial - 1} policy with the learner's own search and "
        f"budgets. J: moment matching over {horizon} steps as the run planned it (cost width, planning noise) under each GP; "
        f"real: mean cost over the same {horizon} steps of {args.episodes} test episodes (a fall held to the end) and their success "
        "rate with its 95 % Wilson interval. One thread, CPU.", "",
        "| policy | J + dJ evaluations | " + " | ".join(f"J under {n} GP" for n in names) + " | real cost | real success |",
        "|---|---|" + "---|" * len(names) + "---|---|",
    ]
    for name, search, Js, real, success in rows:
        low, high = rate_interval(success, args.episodes)
        lines.append(f"| {name} | {search.evaluations if search else '-'} | " + " | ".join(f"{Js[n]:.2f}" for n in names)
                     + f" | {real:.2f} | {100 * success:.1f} % [{100 * low:.1f}, {100 * high:.1f}] |")
    write_report(lines, args.out / f"ensemble_search_check_{run.params['task']}_{args.run_id[:8]}_t{trial}.md")


if __name__ == "__main__":
    exit_on_error(main)
