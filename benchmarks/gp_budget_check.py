"""Which GP training budget gives the better dynamics model: the same data, several budgets.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gp_budget_check.py RUN_ID [--train-episodes 20]
        [--configs 100:400 300:400 100:800 300:800 100:300:600] [--seeds 0] [--policy-trial K] [--episodes 100]
        [--particles 0] [--lqr-speeds 0.3] [--warm-start [--warm-only]] [--tracking-uri URI] [--out results/benchmarks]

Takes the recorded episodes of a PILCO run, trains the dynamics GP from scratch on the first
``--train-episodes`` of them once per budget ``FITC_EVALS:HYPER_SUBSET[:PSEUDO_INPUTS]`` (the learner
options ``gp_fitc_evals``, ``gp_hyper_subset`` and ``num_pseudo``; ``all`` trains the hyperparameters
on every point, as the reference code does; with ``PSEUDO_INPUTS`` the model is FITC with that many
above as many points, and a full GP below) and seed (the random hyperparameter subset and first
pseudo-inputs), and scores every model on what the run recorded *after* those episodes (the region
the later, better policies visited):

* **one-step NLPD**: mean negative log predictive density of the held-out state differences
  (nats per transition, summed over the state dimensions; lower is better);
* **SMSE**: held-out mean squared error over the variance of the targets, averaged over the state
  dimensions (0 = perfect, 1 = no better than the mean);
* **J of a later policy**: the closed-form expected cost (PILCO's moment matching, what the policy
  search minimises, as the run's search at ``--policy-trial`` planned it: horizon, planning noise;
  the task's cost width) of the policy the run handed over at ``--policy-trial`` (default: its last),
  beside that policy's real cost over ``--episodes`` episodes: how far each model misjudges it;
  ``--particles N`` adds the same model's J by Monte Carlo (model bias without moment matching's error);
  ``--lqr-speeds`` (unicycle) scores the riding LQRs of :mod:`tasks.unicycle_lqr` the same way under every
  model: whether a search through that model would rank the learned policy above one that rides.

The run's own GP of the trial that trained on the same episodes (warm-started over the trials
before, with the run's budget) is scored too. From scratch the first pseudo-input optimisation gets
3x its budget (as in a run's first sparse trial). ``--warm-start`` adds, per budget, two refits from
the run's GP of the trial before (what the run itself does each trial): keeping its pseudo-inputs,
or drawing fresh ones from the data with the same budget (``--seeds`` draw the random hyperparameter subset and
pseudo-inputs), and once more with the run's own draw (:meth:`SavedPilcoRun.gp_fit_seed`, its
``gp_refresh_pseudo``): with the run's budget that row is the run's own GP again, so the other seeds' rows
say what the draw alone changes; ``--warm-only`` leaves out the fits from scratch. Writes
``gp_budget_check_<task>_<run>_seeds<S>[_warm][_lqr].md`` into ``--out``.
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

from benchmarks.pilco_prediction_check import real_costs  # noqa: E402
from tasks.unicycle_lqr import riding_lqr  # noqa: E402
from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.gp import GPModel  # noqa: E402
from plugins.pilco.policy import linear_policy_from_gain, transitions  # noqa: E402
from plugins.pilco.sampling import sampled_costs  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402


def parse_config(text: str) -> tuple[int, int | None, int | None]:
    """``"300:800"`` -> ``(300, 800, None)``; ``"100:all"`` -> ``(100, None, None)`` (every point);
    ``"100:300:600"`` -> ``(100, 300, 600)`` (600 pseudo-inputs instead of the run's)."""
    try:
        fitc, subset, *pseudo = text.split(":")
        if len(pseudo) > 1:
            raise ValueError(text)
        return int(fitc), None if subset == "all" else int(subset), int(pseudo[0]) if pseudo else None
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"config {text!r}: expected FITC_EVALS:HYPER_SUBSET[:PSEUDO_INPUTS], e.g. 300:800, 100:all or 100:300:600") from None


def one_step_scores(model: GPModel, x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Held-out ``(NLPD, SMSE)`` of ``model`` on inputs ``x (m, d)``, targets ``y (m, E)``.

    NLPD: mean over the ``m`` transitions of ``-sum_a log N(y_a | mean_a, var_a + noise_a)`` (nats).
    SMSE: ``mean_a [ mean_i (y_ia - mean_ia)^2 / var_i(y_ia) ]``.
    """
    with torch.no_grad():
        mean, var = model.predict(torch.as_tensor(x), include_noise=True)
    return predictive_scores(mean.numpy(), var.numpy(), y)


def predictive_scores(mean: np.ndarray, var: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``(NLPD, SMSE)`` of Gaussian predictions ``mean, var (m, E)`` (noise included) of targets ``y (m, E)``."""
    nlpd = 0.5 * (np.log(2 * math.pi * var) + (y - mean) ** 2 / var)
    smse = ((y - mean) ** 2).mean(0) / y.var(0)
    return float(nlpd.sum(1).mean()), float(smse.mean())


def closed_form_J(objective) -> float:
    """PILCO's moment-matching ``J = sum_t E[c(x_t)]`` of ``objective``."""
    with torch.no_grad():
        return float(objective.step_costs()[0].sum())


def sampled_J(objective, particles: int) -> float:
    """The same model's expected cost by Monte Carlo (``particles`` trajectories; NaN for 0 particles)."""
    return float(sampled_costs(objective, particles, seed=0).sum()) if particles else math.nan


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_id")
    parser.add_argument("--train-episodes", type=int, default=20)
    parser.add_argument("--configs", type=parse_config, nargs="+",
                        default=[(100, 400, None), (300, 400, None), (100, 800, None), (300, 800, None)])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--policy-trial", type=int, default=None)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--particles", type=int, default=0,
                        help="also the later policy's J by Monte Carlo through each model (this many trajectories; 0: off)")
    parser.add_argument("--lqr-speeds", type=float, nargs="*", default=[],
                        help="unicycle: also score riding LQRs (m/s) under every model, beside the learned policy")
    parser.add_argument("--warm-start", action="store_true",
                        help="also refit from the run's GP at trial K-1 (as the run did), keeping its pseudo-inputs or drawing fresh ones")
    parser.add_argument("--warm-only", action="store_true", help="with --warm-start: no fits from scratch")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    with SavedPilcoRun(args.run_id, args.tracking_uri) as run:
        check(run, args, argv)


def check(run: SavedPilcoRun, args: argparse.Namespace, argv: list[str] | None) -> None:
    """Fit, score and write the report (``run`` stays open: the objectives read its settings)."""
    k = args.train_episodes
    episodes = run.episodes()
    if not 1 <= k < len(episodes):
        sys.exit(f"run {args.run_id} recorded {len(episodes)} episodes; --train-episodes must leave some to test on (1..{len(episodes) - 1})")
    policy_trial = args.policy_trial or max(run.policy_trials())
    policy = run.policy(policy_trial)
    horizon = run.planning_horizon_at(policy_trial)
    settings = run.settings
    own_trial = k - run.initial_rollouts + 1  # the trial whose GP was trained on the first k episodes
    own = run.model(own_trial) if own_trial in run.model_trials() else None
    previous = run.model(own_trial - 1) if args.warm_start and own_trial - 1 in run.model_trials() else None
    if args.warm_only and not args.warm_start:
        sys.exit("--warm-only needs --warm-start (it leaves out the fits from scratch)")
    if args.warm_start and previous is None:
        sys.exit(f"--warm-start: run {args.run_id} saved no GP at trial {own_trial - 1} (the one before the first {k} episodes' trial)")
    params, task = run.params, run.task
    layout = run.layout
    x_train, y_train = transitions(episodes[:k], layout)
    x_test, y_test = transitions(episodes[k:], layout)
    threshold = int(settings["preset"]["sparse_threshold"])
    num_pseudo = int(settings["num_pseudo"])
    evaluator = Evaluator(task, n_episodes=args.episodes, seed=200_000)
    per_step, success = real_costs(evaluator, policy, horizon)
    real = float(per_step.sum())
    print(f"{len(x_train)} training / {len(x_test)} held-out transitions; policy of trial {policy_trial}: real J {real:.2f}, "
          f"success {100 * success:.0f} %", flush=True)
    references = []  # (speed, policy, real J, real success) of each riding LQR
    for speed in args.lqr_speeds:
        lqr = linear_policy_from_gain(task.spec, *riding_lqr(task, speed))
        lqr_step, lqr_success = real_costs(evaluator, lqr, horizon)
        references.append((speed, lqr, float(lqr_step.sum()), lqr_success))
        print(f"riding LQR {speed:g} m/s: real J {references[-1][2]:.2f}, success {100 * lqr_success:.0f} %", flush=True)

    rows = []

    def score(label: str, seed: str, cpu: str, model: GPModel) -> None:
        """Held-out scores and the later policy's J under ``model``, as a row."""
        posterior = model.posterior()
        nlpd, smse = one_step_scores(model, x_test, y_test)
        Js = []  # (closed form, sampled) of the learned policy, then of each riding LQR
        for p in [policy, *(lqr for _, lqr, _, _ in references)]:
            objective = run.objective(policy_trial, p, posterior, task_cost=True)
            Js.append((closed_form_J(objective), sampled_J(objective, args.particles)))
        rows.append((label, seed, cpu, nlpd, smse, Js))
        print(f"{label} seed {seed}: fit {cpu} s CPU, NLPD {nlpd:.3f}, SMSE {smse:.4f}, J (closed, sampled) "
              + ", ".join(f"{a:.2f}/{b:.2f}" for a, b in Js), flush=True)

    def fit_and_score(label: str, seed: int, fitc_evals: int, subset: int | None, pseudo: int | None, warm_start=None,
                      refresh: bool = False) -> None:
        """Train a GP on the training transitions, score it on the held-out ones, add a row."""
        m = num_pseudo if pseudo is None else pseudo
        model = run.gp_model(sparse_threshold=threshold if pseudo is None else m, num_pseudo=m, max_evals_fitc=fitc_evals,
                             hyper_subset=len(x_train) if subset is None else subset, refresh_pseudo=refresh)
        start = time.process_time()
        model.fit(x_train, y_train, warm_start=warm_start, seed=seed)
        score(label, str(seed), f"{time.process_time() - start:.0f}", model)

    if own is not None:
        score(f"run's own GP at trial {own_trial} ({run.option_used('gp_fitc_evals') or '?'}:"
              f"{run.option_used('gp_hyper_subset') or '?'}, warm-started)", "", "", own)
    for fitc_evals, subset, pseudo in args.configs:
        for seed in args.seeds:
            label = f"{fitc_evals}:{'all' if subset is None else subset}" + (f":{pseudo}" if pseudo is not None else "")
            if not args.warm_only:
                fit_and_score(label, seed, fitc_evals, subset, pseudo)
            if previous is not None and pseudo is None:  # the run's previous GP as warm start, same FITC budget either way
                for refresh, what in ((False, "its pseudo-inputs"), (True, "fresh pseudo-inputs")):
                    fit_and_score(f"{label} from the run's trial-{own_trial - 1} GP, {what}", seed, fitc_evals, subset, None,
                                  previous.hyperparameters, refresh)
        if previous is not None and pseudo is None:  # the run's own draw: its budget gives the run's own GP back
            refresh = run.option_used("gp_refresh_pseudo") == "True"
            fit_and_score(f"{label} from the run's trial-{own_trial - 1} GP, {'fresh' if refresh else 'its'} pseudo-inputs, "
                          "the run's draw", run.gp_fit_seed(own_trial), fitc_evals, subset, None, previous.hyperparameters, refresh)

    sampled = args.particles > 0
    lines = [
        f"# GP training budget check: {params['learner']} on {params['task']}, run `{args.run_id}`", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"Run options: {', '.join(f'{key}={v}' for key, v in sorted(params.items()) if key.startswith(('task.', 'learner.gp_'))) or 'defaults'}.", "",
        f"Trained on the run's first {k} episodes ({len(x_train)} transitions; FITC with {num_pseudo} pseudo-inputs above "
        f"{threshold} points), scored on its remaining {len(episodes) - k} episodes ({len(x_test)} transitions). "
        f"Budget = `gp_fitc_evals:gp_hyper_subset[:pseudo-inputs]` (pseudo-input evaluations per trial, 3x from scratch : points "
        f"training the hyperparameters : FITC pseudo-inputs, where not the run's {num_pseudo}). J: closed-form expected cost over "
        f"{horizon} steps of the policy handed over at trial {policy_trial}, as that trial's search planned it but with the task's "
        f"cost width" + (f"; sampled: the same model by Monte Carlo ({args.particles} trajectories)" if sampled else "") +
        f"; its **real** cost over {args.episodes} episodes is **{real:.2f}** (success {100 * success:.0f} %). "
        "Fit time: CPU seconds on one thread."
        + "".join(f" Riding LQR {speed:g} m/s (`tasks.unicycle_lqr`, as a PILCO linear controller): real cost {r:.2f} over the "
                  f"same episodes (success {100 * ok:.0f} %)." for speed, _, r, ok in references), "",
        "| budget | seed | fit CPU s | held-out NLPD (nats/transition) | held-out SMSE | J of the later policy | J - real |"
        + (" J sampled | sampled - real |" if sampled else "")
        + "".join(f" LQR {speed:g}: J |" + (" sampled |" if sampled else "") for speed, *_ in references),
        "|---|---|---|---|---|---|---|" + ("---|---|" if sampled else "") + ("---|" * (1 + sampled)) * len(references),
    ]
    lines += [f"| {label} | {seed} | {cpu} | {nlpd:.3f} | {smse:.4f} | {Js[0][0]:.2f} | {Js[0][0] - real:+.2f} |"
              + (f" {Js[0][1]:.2f} | {Js[0][1] - real:+.2f} |" if sampled else "")
              + "".join(f" {J:.2f} |" + (f" {J_smp:.2f} |" if sampled else "") for J, J_smp in Js[1:])
              for label, seed, cpu, nlpd, smse, Js in rows]
    write_report(lines, args.out / f"gp_budget_check_{params['task']}_{args.run_id[:8]}_seeds{'-'.join(map(str, args.seeds))}"
                 f"{'_warm' if args.warm_start else ''}{'_lqr' if references else ''}.md")


if __name__ == "__main__":
    exit_on_error(main)
