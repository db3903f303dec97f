"""What training the FITC pseudo-inputs on fewer points (``gp_pseudo_subset``) costs in model quality, and saves in time.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/pseudo_subset_check.py RUN_ID --train-episodes 30
        [--subsets 0 900 600] [--seeds 0 1] [--test-episodes 10] [--episodes 100] [--tracking-uri URI] [--out DIR]

A late double-pendulum GP fit spends most of its time optimising the pseudo-inputs, and one evaluation of
that objective costs ``O(E n M^2)`` (``results/benchmarks/fitc_eval_profile.md``), so it grows with the
data. This refits the dynamics GP of a run that drew fresh pseudo-inputs every trial (``gp_refresh_pseudo``)
as the run's learner would at the trial after its first ``--train-episodes`` episodes: warm-started from the
hyperparameters the run saved at the trial before (``trialK/gp_hyperparameters_trialK.json``), with the run's
budgets, once per subset size (0: all points, the run's own setting) and seed (the random draws). Each model
is scored on the ``--test-episodes`` the run recorded next (one-step NLPD and SMSE, as
``benchmarks/gp_budget_check.py``), by its FITC NLL on all its training points, and (where the store keeps
the run's policies) by the closed-form J it gives the policy the run handed over after those test episodes,
beside that policy's real cost over ``--episodes`` episodes. Fit time: CPU seconds on one thread. Choose a run of tuning seeds (100 and up).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.gp_budget_check import closed_form_J, one_step_scores  # noqa: E402
from benchmarks.pilco_prediction_check import real_costs  # noqa: E402
from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.gp import GPHyperparameters  # noqa: E402
from plugins.pilco.policy import transitions  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402


def saved_hyperparameters(run: SavedPilcoRun, trial: int, num_pseudo: int, dim: int) -> GPHyperparameters:
    """The hyperparameters the run saved at ``trial`` (``gp_hyperparameters_trialKKK.json``) as a warm start; its
    pseudo-inputs are a placeholder of the right shape (zeros), which a refit with ``refresh_pseudo`` replaces by a
    fresh draw from the data, as the run's own next fit did."""
    saved = json.loads(run.file(f"trial{trial:03d}/gp_hyperparameters_trial{trial:03d}.json").read_text())
    t = lambda v: torch.log(torch.tensor(v, dtype=torch.float64))  # noqa: E731
    return GPHyperparameters(t(saved["length_scales"]), t(saved["signal_std"]), t(saved["noise_std"]),
                             torch.zeros(num_pseudo, dim, dtype=torch.float64))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_id")
    parser.add_argument("--train-episodes", type=int, default=30)
    parser.add_argument("--test-episodes", type=int, default=10)
    parser.add_argument("--subsets", type=int, nargs="+", default=[0, 900, 600], help="points training the pseudo-inputs (0: all)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--episodes", type=int, default=100, help="episodes for the later policy's real cost")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    with SavedPilcoRun(args.run_id, args.tracking_uri) as run:
        check(run, args, argv)


def check(run: SavedPilcoRun, args: argparse.Namespace, argv: list[str] | None) -> None:
    """Refit, score and write the report."""
    load_start = load_average()
    k, k_test = args.train_episodes, args.test_episodes
    episodes = run.episodes()
    if not 1 <= k < len(episodes) - k_test + 1:
        sys.exit(f"run {args.run_id} recorded {len(episodes)} episodes: --train-episodes {k} leaves fewer than "
                 f"--test-episodes {k_test} to test on (lower one of them)")
    if run.option_used("gp_refresh_pseudo") != "True":
        sys.exit(f"run {args.run_id} kept its pseudo-inputs from trial to trial (gp_refresh_pseudo unset), and the store "
                 "keeps no pseudo-inputs to warm-start from: choose a run with learner.gp_refresh_pseudo=True")
    settings, task = run.settings, run.task
    layout = run.layout
    x_train, y_train = transitions(episodes[:k], layout)
    x_test, y_test = transitions(episodes[k:k + k_test], layout)
    trial = k - run.initial_rollouts + 1  # the trial whose GP trains on the first k episodes
    num_pseudo = int(settings["num_pseudo"])
    warm = saved_hyperparameters(run, trial - 1, num_pseudo, x_train.shape[1])
    later = [t for t in run.policy_trials() if t > trial]  # a store may keep no policies of a tuning run
    policy_trial = min(trial + k_test, max(later)) if later else None
    if policy_trial is not None:
        policy, horizon = run.policy(policy_trial), run.planning_horizon_at(policy_trial)
        per_step, success = real_costs(Evaluator(task, n_episodes=args.episodes, seed=200_000), policy, horizon)
        real = float(per_step.sum())
        print(f"policy of trial {policy_trial}: real J {real:.2f}, success {100 * success:.0f} %", flush=True)
    print(f"{len(x_train)} training / {len(x_test)} held-out transitions", flush=True)

    rows = []
    for subset in args.subsets:
        for seed in args.seeds:
            model = run.gp_model(pseudo_subset=subset or None, refresh_pseudo=True)
            start = time.process_time()
            report = model.fit(x_train, y_train, warm_start=warm, seed=seed)
            cpu = time.process_time() - start
            fitc = report.fitc_nll  # on all training points, also where the pseudo-inputs trained on a subset
            nlpd, smse = one_step_scores(model, x_test, y_test)
            J = math.nan if policy_trial is None else closed_form_J(run.objective(policy_trial, policy, model.posterior(), task_cost=True))
            rows.append((subset, seed, cpu, fitc, nlpd, smse, J))
            print(f"subset {subset or 'all'} seed {seed}: fit {cpu:.0f} s CPU, FITC NLL {fitc:.1f}, NLPD {nlpd:.3f}, "
                  f"SMSE {smse:.4f}, J {J:.2f}", flush=True)

    lines = [
        f"# Pseudo-inputs trained on fewer points: {run.params['learner']} on {run.params['task']}, run `{args.run_id}`", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"{machine_line(load_start)}  ",
        f"Refit of trial {trial}'s GP on the run's first {k} episodes ({len(x_train)} transitions, {num_pseudo} fresh pseudo-inputs, "
        f"warm-started from the trial-{trial - 1} hyperparameters, the run's budgets), scored on the next {k_test} episodes "
        f"({len(x_test)} transitions). FITC NLL on all {len(x_train)} training points (nats, lower is better); NLPD in nats per "
        "held-out transition; " + (
            f"J: closed-form expected cost over {horizon} steps of the policy handed over at trial {policy_trial}, task's cost "
            f"width; its **real** cost over {args.episodes} episodes is **{real:.2f}** (success {100 * success:.0f} %)."
            if policy_trial is not None else "J: not scored (the store keeps no policy of this run after the trial).")
        + " Fit: CPU seconds on one thread.", "",
        "| pseudo-inputs trained on | seed | fit CPU s | FITC NLL (all points) | held-out NLPD | held-out SMSE |"
        + (" J of the later policy | J - real |" if policy_trial is not None else ""),
        "|---|---|---|---|---|---|" + ("---|---|" if policy_trial is not None else ""),
    ]
    lines += [f"| {f'{s} points' if s else f'all {len(x_train)}'} | {seed} | {cpu:.0f} | {fitc:.1f} | {nlpd:.3f} | {smse:.4f} |"
              + (f" {J:.2f} | {J - real:+.2f} |" if policy_trial is not None else "") for s, seed, cpu, fitc, nlpd, smse, J in rows]
    write_report(lines, args.out / f"pseudo_subset_check_{run.params['task']}_{args.run_id[:8]}_k{k}.md")


if __name__ == "__main__":
    exit_on_error(main)
