"""How far to trust a PILCO run's predicted cost: closed form vs the same model sampled vs the real system.

Usage::

    .venv/bin/python benchmarks/pilco_prediction_check.py RUN_ID [--trial K] [--particles 4000] [--episodes 200]
        [--tracking-uri URI] [--out results/benchmarks]

For trial ``K`` of a finished or running PILCO run (default: its last saved trial) it loads the
trained GP (``trialK/model_trialK.pt``) and the policy handed over at that trial
(``policies/policy_trialK.policy``) from the tracking store and reports, per predicted step:

* **closed form**: PILCO's moment-matching expected cost (what the policy search minimised);
* **sampled**: the same model and policy by Monte Carlo (:func:`plugins.pilco.sampling.sampled_costs`):
  the gap to the closed form is the Gaussian approximation's error over many steps;
* **real**: the policy on the real task (the harness's evaluator, ``--episodes`` episodes from the
  initial distribution, a terminated episode holding its last cost): the gap to *sampled* is model bias.

``--lqr-speeds 0.3 0.5`` (unicycle only) adds, under the same model, the riding LQRs of
:mod:`tasks.unicycle_lqr` as PILCO linear controllers: whether the model knows of a better policy
than the one the search found. Writes ``prediction_check_<task>_<run>_t<K>.md`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.policy import linear_policy_from_gain  # noqa: E402
from plugins.pilco.sampling import sampled_costs  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402
from tasks.unicycle_lqr import riding_lqr  # noqa: E402


def held_costs(episodes, horizon: int) -> np.ndarray:
    """Per-episode, per-step real costs ``(episodes, horizon)``: a terminated episode (a fall) holds
    its last cost to the end; steps an unterminated episode did not reach are NaN."""
    out = np.full((len(episodes), horizon), np.nan)
    for row, ep in zip(out, episodes):
        if ep.terminated:
            row[:] = ep.costs[-1]
        row[: ep.steps] = ep.costs[:horizon]
    return out


def real_costs(evaluator: Evaluator, policy, horizon: int) -> tuple[np.ndarray, float]:
    """Per-step mean cost ``(horizon,)`` over the evaluator's episodes (a terminated episode holds
    its last cost) and the success rate."""
    result = evaluator(policy)
    return held_costs(result.episodes, horizon).mean(axis=0), result.success_rate


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_id")
    parser.add_argument("--trial", type=int, default=None)
    parser.add_argument("--particles", type=int, default=4000)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    parser.add_argument("--lqr-speeds", type=float, nargs="*", default=[], help="unicycle: riding LQRs (m/s) to compare under the same model")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    with SavedPilcoRun(args.run_id, args.tracking_uri) as run:
        trial = args.trial if args.trial is not None else max(run.model_trials())
        saved = run.saved_model(trial)
        posterior, policy = run.model(trial).posterior(), run.policy(trial)
        horizon = run.planning_horizon_at(trial)
        noise = run.plans_with_noise
        lqr_policies = [linear_policy_from_gain(run.task.spec, *riding_lqr(run.task, speed)) for speed in args.lqr_speeds]
        objectives = [run.objective(trial, p, posterior, task_cost=True) for p in [policy, *lqr_policies]]
    params, task = run.params, run.task
    evaluator = Evaluator(task, n_episodes=args.episodes, seed=200_000)

    def check(policy, objective) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        with torch.no_grad():
            closed = objective.step_costs()[0].numpy()
        return (closed, sampled_costs(objective, args.particles, seed=0), *real_costs(evaluator, policy, horizon))

    closed, sampled, real, success = check(policy, objectives[0])
    references = []
    for speed, lqr, objective in zip(args.lqr_speeds, lqr_policies, objectives[1:]):
        c, smp, r, ok = check(lqr, objective)
        references.append((f"riding LQR {speed:g} m/s", c.sum(), smp.sum(), r.sum(), ok))

    steps = sorted({1, 2, 5, 10, 15, 20, 30, 40, 50, horizon} & set(range(1, horizon + 1)))
    lines = [
        f"# Prediction check: {params['learner']} on {params['task']}, run `{args.run_id}`, trial {trial}", "",
        f"Command: `{command_line(__file__, argv)}`  ",
        f"Task options: {', '.join(f'{k[5:]}={v}' for k, v in sorted(params.items()) if k.startswith('task.')) or 'defaults'}; "
        f"GP on {int(saved['gp']['inputs'].shape[0])} points; planning horizon {horizon}; J as the run planned it "
        f"({'with' if noise else 'without'} measurement noise at the policy's input), with the task's cost width.", "",
        "Expected cost of the policy handed over at this trial, per predicted step: **closed form** = PILCO's "
        "moment matching (what the policy search minimised); **sampled** = the same GP and policy by Monte Carlo "
        f"({args.particles} particles); **real** = the real task ({args.episodes} episodes, a fall held to the end). "
        "closed form - sampled: error of the Gaussian approximation; sampled - real: model bias.", "",
        "| | closed form | sampled (same model) | real |", "|---|---|---|---|",
        f"| J = sum over {horizon} steps | {closed.sum():.2f} | {sampled.sum():.2f} | {real.sum():.2f} |",
    ]
    lines += [f"| step {t} | {closed[t - 1]:.3f} | {sampled[t - 1]:.3f} | {real[t - 1]:.3f} |" for t in steps]
    lines += ["", f"Real success rate of this policy: {100 * success:.1f} % of {args.episodes} episodes."]
    if references:
        lines += ["", "Under the same model, reference policies (J = sum over the horizon):", "",
                  "| policy | closed form | sampled (same model) | real | real success |", "|---|---|---|---|---|",
                  f"| learned (trial {trial}) | {closed.sum():.2f} | {sampled.sum():.2f} | {real.sum():.2f} | {100 * success:.1f} % |"]
        lines += [f"| {n} | {c:.2f} | {smp:.2f} | {r:.2f} | {100 * ok:.1f} % |" for n, c, smp, r, ok in references]
    write_report(lines, args.out / f"prediction_check_{params['task']}_{args.run_id[:8]}_t{trial}.md")


if __name__ == "__main__":
    exit_on_error(main)
