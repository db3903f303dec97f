"""Is a stuck PILCO run at a local optimum of J, or is J's optimum itself where the run sits?

Usage::

    OMP_NUM_THREADS=1 python benchmarks/plateau_search_check.py RUN_ID [--trial K] [--fresh 3] [--budgets 1] \\
        [--set planning_horizon=100 ...] [--episodes 100] [--seed 777] [--tracking-uri URI] [--out FILE]

A PILCO run whose evaluation cost has stopped falling (the double pendulum's tuning seeds sit at
44-50 of 60 for twenty trials) is stuck either because each policy search ends in a local optimum of
J that other starting points escape, or because under the model no policy is predicted to do much
better. The two call for different remedies (more or fresh searches against better data). This
replays trial ``K``'s policy search (default: the run's last trial with a model) under the run's own
GP of that trial and the learner's own settings (options, planning horizon, cost width, budgets,
kernel; :class:`plugins.pilco.learner.Pilco` built from the run's params) from several starts:

* **the run's search again**: from the policy handed over at trial ``K - 1`` (where the run's
  search started), the preset's budget; its J should be close to the run's logged ``J_after``
  (not equal: a different machine's or commit's rounding moves the L-BFGS path);
* **continued**: from the run's own trial-``K`` policy, one more preset budget (was the search
  cut off by its budget?);
* **fresh 1..F**: from fresh initial controllers (the learner's own initialisation, generator
  seeds 1..F), the preset's budget each (what ``fresh_start_tol`` would add), or ``--budgets B`` of
  them in a row (each search continuing from the last: where a fresh start converges), with J after
  each;
* **perturbed 1..P** (``--perturbed P --perturb-scale S``): from the run's trial-``K`` policy with every
  parameter tensor moved by ``S`` times its own spread (standard deviation over its entries, or its
  magnitude for a single number) times standard normal noise (generator seeds 1..P), the preset's
  budget each: does a search that keeps most of what the run learned, but not its exact optimum,
  find a lower J (a basin-hopping restart)?

``--set KEY=VALUE`` replays every search with a learner option changed, e.g. ``planning_horizon=100``
(J over 100 predicted steps; the real test episodes keep the task's horizon) or ``cost_width=1.0``
(the planning cost's width): would planning differently have moved a stuck run's policy, under the
same model, towards one that succeeds?

Each policy found (and the run's own trial-``K`` policy) is then run on ``--episodes`` test
episodes of the real task from the same initial states: success rate (Wilson 95 % interval) and
mean episode cost, beside its J. Lower J that does not turn into more successes says the model,
not the search, is what holds the run.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, machine_line, write_report  # noqa: E402
from benchmarks.swingup_failure_modes import add_test_arguments  # noqa: E402
from harness.statistics import wilson_interval  # noqa: E402
from harness.errors import CheckpointError, exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from harness.options import parse_assignments  # noqa: E402
from harness.runner import RunConfig, new_learner, prepare  # noqa: E402
from harness.testrun import task_options  # noqa: E402
from plugins.pilco.policy import PilcoPolicy  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402


@dataclass
class Row:
    """One start: its name, J before and after its search (None: no search), the search's J + dJ
    evaluations and wall seconds, and the found policy's real test success count and mean cost."""

    start: str
    J_before: float | None
    J_after: float
    evaluations: int | None
    seconds: float | None
    successes: int
    mean_cost: float
    J_budgets: tuple[float, ...] = ()


def learner_for(run: SavedPilcoRun, changes: dict[str, str] | None = None):
    """The run's learner as :func:`harness.runner.run` built it (:func:`~harness.runner.new_learner`: its recorded
    ``learner.*`` options, its seed), with the options in ``changes`` replaced."""
    params = run.params
    options = {k[len("learner."):]: v for k, v in params.items() if k.startswith("learner.") and v != "None"}
    config = RunConfig(params["learner"], params["task"], int(params["seed"]), learner_options={**options, **(changes or {})},
                       task_options=task_options(params))
    return new_learner(prepare(config))


def perturbed_copy(controller, scale: float, seed: int):
    """A copy of ``controller`` moved as the learner's restarts move it (:func:`plugins.pilco.policy.perturbed_state`,
    generator ``seed``)."""
    import copy

    from plugins.pilco.policy import perturbed_state

    moved = copy.deepcopy(controller)
    moved.load_state_dict(perturbed_state(controller, scale, torch.Generator().manual_seed(seed)))
    return moved


def check(run: SavedPilcoRun, trial: int, fresh: int, evaluator: Evaluator, log=print, budgets: int = 1,
          changes: dict[str, str] | None = None, perturbed: int = 0, perturb_scale: float = 0.1) -> tuple[list[Row], int, float]:
    """The rows of the table for ``trial`` of ``run`` (see the module docstring; fresh starts get ``budgets``
    searches in a row; ``perturbed`` starts from the trial's policy moved by ``perturb_scale`` (:func:`perturbed_copy`);
    learner options in ``changes`` replaced; J over the run's own planning horizon at that
    trial unless ``changes`` sets ``planning_horizon``),
    the planning horizon used and the run's logged ``J_after`` of that trial."""
    if trial not in run.model_trials() or trial not in run.policy_trials():
        raise CheckpointError(f"run {run.run_id} has no model and policy of trial {trial} (models: {run.model_trials()[-1:]})")
    learner = learner_for(run, changes)
    if "planning_horizon" not in (changes or {}):  # the run's own horizon at that trial (a schedule may have grown it)
        learner.schedule.horizon = run.planning_horizon_at(trial)
    horizon = learner.horizon
    logged = run.metric("J_after").get(trial, float("nan"))
    posterior = run.model(trial).posterior(max_basis=learner.options["planning_basis"])

    def tested(name: str, controller, searches: list, objective=None) -> Row:
        """``objective``: the one the searches ran on (else J is computed afresh)."""
        objective = objective or learner.planning_objective(controller, posterior, threads=1)
        with torch.no_grad():
            J = float(objective.step_costs()[0].sum())
        result = evaluator(PilcoPolicy.snapshot(controller, learner.layout))
        row = Row(name, searches[0].J_before if searches else None, J, sum(s.evaluations for s in searches) if searches else None,
                  sum(s.seconds for s in searches) if searches else None, round(result.success_rate * evaluator.n_episodes),
                  result.mean_cost, tuple(s.J_after for s in searches) if len(searches) > 1 else ())
        log(f"{name}: J {row.J_before if row.J_before is not None else '-'} -> {J:.2f}"
            + (f" (after each budget: {', '.join(f'{j:.2f}' for j in row.J_budgets)})" if row.J_budgets else "")
            + f", {row.successes} of {evaluator.n_episodes} test episodes, mean cost {row.mean_cost:.2f}")
        return row

    def searched(name: str, controller, times: int = 1) -> Row:
        objective = learner.planning_objective(controller, posterior, threads=1)
        # the learner's own search and budgets, `times` in a row
        return tested(name, controller, [learner.search_policy(objective, learner.kernel, 1) for _ in range(times)], objective)

    rows = [tested(f"the run's trial-{trial} policy (no search)", run.policy(trial).controller, [])]
    if trial - 1 in run.policy_trials():
        rows.append(searched(f"the run's search again (from policy {trial - 1})", run.policy(trial - 1).controller))
    rows.append(searched(f"continued (from policy {trial}, one more budget)", run.policy(trial).controller))
    for s in range(1, fresh + 1):
        rows.append(searched(f"fresh {s} (initial controller, generator seed {s}{f', {budgets} budgets' if budgets > 1 else ''})",
                             learner.new_controller(torch.Generator().manual_seed(s)), budgets))
    for s in range(1, perturbed + 1):
        rows.append(searched(f"perturbed {s} (policy {trial}, scale {perturb_scale:g}, generator seed {s})",
                             perturbed_copy(run.policy(trial).controller, perturb_scale, s)))
    return rows, horizon, logged


def table(rows: list[Row], episodes: int) -> list[str]:
    lines = ["| start | J before | J after | J + dJ evaluations | search wall (s) | real success (95 % CI) | real mean cost |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        low, high = wilson_interval(r.successes, episodes)
        each = f" ({' -> '.join(f'{j:.2f}' for j in r.J_budgets)})" if r.J_budgets else ""
        lines.append(f"| {r.start} | {'–' if r.J_before is None else f'{r.J_before:.2f}'} | {r.J_after:.2f}{each} | "
                     f"{'–' if r.evaluations is None else r.evaluations} | {'–' if r.seconds is None else f'{r.seconds:.0f}'} | "
                     f"{r.successes} of {episodes} ({100 * low:.0f}-{100 * high:.0f} %) | {r.mean_cost:.2f} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_id")
    parser.add_argument("--trial", type=int, default=None, help="default: the run's last trial with a model")
    parser.add_argument("--fresh", type=int, default=3, help="searches from fresh initial controllers")
    parser.add_argument("--budgets", type=int, default=1, help="preset budgets in a row for each fresh start")
    parser.add_argument("--perturbed", type=int, default=0, help="searches from the trial's policy with perturbed parameters")
    parser.add_argument("--perturb-scale", type=float, default=0.1, help="the perturbation, in units of each parameter "
                        "tensor's own spread")
    parser.add_argument("--set", dest="changes", action="append", default=[], metavar="KEY=VALUE",
                        help="a learner option changed for every search, e.g. planning_horizon=100 or cost_width=1.0")
    parser.add_argument("--planning-horizon", type=int, default=None, metavar="H", help="the same as --set planning_horizon=H")
    add_test_arguments(parser)
    args = parser.parse_args(argv)
    changes = dict(parse_assignments(args.changes))
    if args.planning_horizon is not None:
        changes["planning_horizon"] = str(args.planning_horizon)
    torch.set_num_threads(1)
    start = time.perf_counter()
    with SavedPilcoRun(args.run_id, args.tracking_uri) as run:
        trial = args.trial if args.trial is not None else max(run.model_trials())
        evaluator = Evaluator(run.task, n_episodes=args.episodes, seed=args.seed)
        try:
            rows, horizon, logged = check(run, trial, args.fresh, evaluator, budgets=args.budgets, changes=changes,
                                          perturbed=args.perturbed, perturb_scale=args.perturb_scale)
        finally:
            evaluator.close()
        params = run.params
        run_horizon = run.planning_horizon_at(trial)
    lines = [
        f"# Policy searches from several starts under one trial's model: {params['learner']} on {params['task']}, "
        f"seed {params['seed']}, run `{args.run_id[:8]}`, trial {trial}", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        machine_line().rstrip(".") + f"; wall time {time.perf_counter() - start:.0f} s.", "",
        f"J: PILCO's closed-form expected cost over {horizon} planning steps under the run's trial-{trial} GP "
        f"(the run logged J_after = {logged:.2f} for its trial-{trial} policy"
        + (f", over its own {run_horizon} steps" if horizon != run_horizon else "") + ")"
        + (f"; every search and J with {', '.join(f'{k}={v}' for k, v in changes.items())}" if changes else "") + ". Each search: the learner's own "
        f"L-BFGS-B with its preset's budget{f' (fresh starts: {args.budgets} in a row, J after each in brackets)' if args.budgets > 1 else ''}. Real: {args.episodes} test episodes from the task's initial distribution "
        f"(seed {args.seed}, the same initial states for every policy; success as the task defines it; mean cost "
        "summed over the episode).", "",
        *table(rows, args.episodes),
    ]
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
