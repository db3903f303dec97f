"""Where does the GP's rollout of a unicycle policy part from the real rides? State by state, step by step.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/unicycle_drift_check.py RUN_ID --trial K [--particles 2000] [--episodes 200]
        [--steps 10 20 40 60] [--tracking-uri URI] [--out results/benchmarks]

The prediction check (``pilco_prediction_check.py``) shows *that* the model's expected cost of a unicycle policy
falls behind the real one late in the ride. This says *where*: the policy handed over at trial ``K`` is rolled
out through trial ``K``'s GP by sampling (``--particles`` trajectories, the run's planning noise; the same Monte
Carlo as ``J_sampled``) and on the real task (``--episodes`` test episodes). At each of ``--steps``:

* **fallen**: the fraction of real episodes that ended in a fall by that step, and the fraction of sampled
  trajectories past the same boundary (``|theta| > pi/2`` or ``|psi_f| > pi/2``, :meth:`Unicycle.fallen`) at it;
  and, since the GP has no data beyond a fall, the fractions that have been past ``--tilt`` (rad) by then, a tilt
  that its data do cover;
* per state entry, the **mean and standard deviation** over the real episodes still up and over the sampled
  trajectories still up: the entry whose spread the model underestimates is the one it does not see drift;
* the real **torques** between consecutive ``--steps`` (from step 0), as fractions of their bounds: mean ``|u|`` and
  the share of steps at 95 % of the bound or more, for the episodes that fell and for those up at the end
  (did the falls follow from a torque limit?);
* the GP's **one-step predictions along the real rides** (trial ``K``'s GP on the test episodes' own transitions, as
  :func:`~plugins.pilco.policy.transitions` builds its data) in the same windows, by fate: the mean over transitions
  and state entries of the squared error over the predicted variance (1 for a calibrated model) and the SMSE
  (squared error over the variance of the targets of all test transitions, averaged over the entries);
* whether those one-step errors **persist**: per state entry, the correlation of the standardised errors
  ``(y - mean) / sd`` of the same ride ``k`` steps apart (``k`` = 2 and 5; at ``k`` = 1 two consecutive targets
  share one noisy observation, which makes them anti-correlated) over the steps before ``--persist-before``. A
  model sampled with independent errors at every step (moment matching, particles) assumes 0.

``--train-on true-states`` replaces trial ``K``'s GP by one trained again as the run trained it
(:meth:`SavedPilcoRun.refit_model`, the run's own draw) on the same episodes' true, noise-free states instead of
the observations the run had (``observations``: on what the run had, which gives the run's GP back): does the
measurement noise in the GP's inputs, which flattens a regression's slopes, make the model's falls slower?
``true-inputs`` and ``true-targets`` take the true states for one side of each transition and the observations for
the other (is it the noise in the inputs or in the targets?). ``--train-on smoothed`` trains it on the observations smoothed along each episode (a Savitzky-Golay filter, quadratic,
``--smooth-window`` steps; what a learner could do without the true states).

``--train-on gp-smoothed`` trains it on state estimates a learner can make: each episode smoothed through the current GP
(starting from trial ``K``'s, trained on the observations), the GP trained again on the estimates (as the run trained it),
``--smooth-rounds`` times (:func:`plugins.pilco.smoothing.smooth_and_refit`, the learner's ``gp_data=smoothed``; the
smoother's model-error allowance ``--process-std`` times the measurement noise std); the file says how far the estimates
are from the true states, against the observations. Its one-step table, like a true-state file's, scores a GP trained on
noise-free targets against noisy ones: the errors over the variance are not a calibration there.

``--lqr-speed S`` checks the riding LQR at ``S`` m/s (:mod:`tasks.unicycle_lqr`, as a PILCO linear controller) under
the same GP instead of the run's policy.

Writes ``drift_check_unicycle_<run>_t<K>[_<train-on>][_lqr<S>].md`` into ``--out`` (``gp-smoothed`` with its settings:
``gp-smoothed-r<rounds>-q<process std>``).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.pilco_prediction_check import held_costs  # noqa: E402
from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.gp_data import GP_DATA_OPTIONS  # noqa: E402
from plugins.pilco.policy import linear_policy_from_gain, transitions  # noqa: E402
from plugins.pilco.sampling import sample_states, states_costs  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402
from plugins.pilco.smoothing import smooth_and_refit  # noqa: E402
from tasks.unicycle_lqr import riding_lqr  # noqa: E402


def up_statistics(states: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation ``(D,)`` of ``states (N, D)`` over the rows with ``up (N,)`` true (NaN if none)."""
    if not up.any():
        return np.full(states.shape[1], np.nan), np.full(states.shape[1], np.nan)
    return states[up].mean(0), states[up].std(0)


def smoothed(observations: np.ndarray, window: int) -> np.ndarray:
    """``observations (T+1, D)`` smoothed along time: a quadratic Savitzky-Golay filter over ``window`` steps
    (an episode shorter than the window: unchanged)."""
    from scipy.signal import savgol_filter

    if len(observations) < window:
        return observations
    return savgol_filter(observations, window, 2, axis=0, mode="interp")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_id")
    parser.add_argument("--trial", type=int, required=True)
    parser.add_argument("--particles", type=int, default=2000)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--steps", type=int, nargs="+", default=[10, 20, 40, 60])
    parser.add_argument("--smooth-window", type=int, default=5, help="--train-on smoothed: odd window of the filter, in steps")
    learner_default = {option.name: option.default for option in GP_DATA_OPTIONS}
    parser.add_argument("--smooth-rounds", type=int, default=learner_default["smooth_rounds"],
                        help="--train-on gp-smoothed: rounds of smoothing and refitting (default: the learner's smooth_rounds)")
    parser.add_argument("--process-std", type=float, nargs="+", default=[learner_default["smooth_process_std"]],
                        help="--train-on gp-smoothed: the smoother's model-error allowance per step, as a multiple of the "
                        "measurement noise std (one value, or one per state entry; default: the learner's smooth_process_std)")
    parser.add_argument("--train-on", choices=("observations", "true-states", "true-inputs", "true-targets", "smoothed", "gp-smoothed"),
                        default=None,
                        help="refit trial K's GP on the run's observations or on the true states (default: the run's GP as saved)")
    parser.add_argument("--lqr-speed", type=float, default=None, help="check the riding LQR at this speed (m/s) instead of the run's policy")
    parser.add_argument("--tilt", type=float, default=0.3, help="also count rides ever past this |theta| or |psi_f| (rad)")
    parser.add_argument("--persist-before", type=int, default=40, help="the error correlations use the steps before this one")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    with SavedPilcoRun(args.run_id, args.tracking_uri, task="unicycle") as run:
        policy = run.policy(args.trial)
        if args.lqr_speed is not None:
            policy = linear_policy_from_gain(run.task.spec, *riding_lqr(run.task, args.lqr_speed))
        horizon = run.planning_horizon_at(args.trial)
        steps = [t for t in args.steps if 1 <= t <= horizon]
        if not steps:
            sys.exit(f"--steps {args.steps}: none within trial {args.trial}'s planning horizon of {horizon} steps")
        model = run.model(args.trial)
        smoothing_lines: list[str] = []
        if args.train_on is not None:
            data = run.episodes()[:args.trial - 1 + run.initial_rollouts]
            true = [replace(ep, observations=ep.states) for ep in data]
            if args.train_on == "smoothed":
                data = [replace(ep, observations=smoothed(ep.observations, args.smooth_window)) for ep in data]
            if args.train_on == "gp-smoothed":
                noise = run.task.spec.measurement_noise_std
                model, rounds = smooth_and_refit(model, lambda x, y: run.refit_model(args.trial, x, y), policy.layout, data, noise,
                                                 args.smooth_rounds, (np.asarray(args.process_std) * noise) ** 2)
                truth = np.concatenate([ep.observations for ep in true])
                observed = np.sqrt(((np.concatenate([ep.observations for ep in data]) - truth) ** 2).mean(0))
                for k, r in enumerate(rounds, 1):
                    estimated = np.sqrt(((np.concatenate([ep.observations for ep in r.episodes]) - truth) ** 2).mean(0))
                    smoothing_lines.append(f"Smoothing round {k}: rms error of the estimates over that of the observations, per state "
                                           f"entry: {' '.join(f'{v:.2f}' for v in estimated / observed)} (all entries: "
                                           f"{np.sqrt((estimated ** 2).sum() / (observed ** 2).sum()):.3f}).")
                    print(smoothing_lines[-1], flush=True)
            else:
                inputs = transitions(true if args.train_on in ("true-states", "true-inputs") else data, policy.layout)[0]
                targets = transitions(true if args.train_on in ("true-states", "true-targets") else data, policy.layout)[1]
                model = run.refit_model(args.trial, inputs, targets)
        objective = run.objective(args.trial, policy, model.posterior(), task_cost=True)
        sampled = sample_states(objective, args.particles, seed=0).numpy()  # (H + 1, particles, D)
        task, names = run.task, run.task.spec.state_names
        episodes = Evaluator(task, n_episodes=args.episodes, seed=200_000)(policy).episodes
        J_sampled = float(states_costs(objective, torch.as_tensor(sampled)).sum())  # the trajectories above, not new ones
        with torch.no_grad():
            J_closed = float(objective.step_costs()[0].sum())
        J_real = float(held_costs(episodes, horizon)[:, :task.spec.horizon].mean(axis=0).sum())  # the steps a real ride has

    lines = [
        f"# Drift check: {run.params['learner']} on unicycle, run `{args.run_id}`, "
        + (f"the riding LQR at {args.lqr_speed:g} m/s" if args.lqr_speed is not None else f"the policy of trial {args.trial}")
        + f" under trial {args.trial}'s GP", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"Model: trial {args.trial}'s GP" + {None: "", "observations": ", trained again as the run trained it",
                                              "true-states": ", trained again as the run trained it but on the true (noise-free) states "
                                              "of the same episodes",
                                              "true-inputs": ", trained again as the run trained it but with the true states as its inputs (targets: the observed changes)",
                                              "true-targets": ", trained again as the run trained it but with the true state changes as its targets "
                                              "(inputs: the observations)",
                                              "smoothed": ", trained again as the run trained it but on the observations smoothed "
                                              f"along each episode (Savitzky-Golay, quadratic, {args.smooth_window} steps)",
                                              "gp-smoothed": f", trained again as the run trained it on state estimates: {args.smooth_rounds} rounds of "
                                              "smoothing each episode through the current GP (plugins.pilco.smoothing, model-error allowance "
                                              f"{args.process_std} x the measurement noise std) and refitting"}[args.train_on] + f", {args.particles} sampled trajectories over {horizon} steps (planning noise as the run "
        f"planned); real: {args.episodes} test episodes (true states). Fallen: past |theta| or |psi_f| = pi/2 (real: the episode "
        "ended in a fall by that step). Per entry: mean / standard deviation over the episodes and trajectories still up.", "",
        *(line for text in smoothing_lines for line in (text, "")),
        f"Expected cost over the {horizon} steps (the task's cost): **sampled through this GP {J_sampled:.2f}**, closed form (moment "
        f"matching) {J_closed:.2f}, **real {J_real:.2f}** (a fall holds its last cost).", "",
        f"| step | fallen: real | fallen: model | past {args.tilt:g} rad: real | past {args.tilt:g} rad: model | "
        + " | ".join(f"{n}: real | model" for n in names) + " |",
        "|---|---|---|---|---|" + "---|---|" * len(names),
    ]
    tilt_entries = [names.index("theta [rad]"), names.index("psi_f [rad]")]
    for t in steps:
        real = np.array([ep.states[min(t, len(ep.states) - 1)] for ep in episodes])  # a fallen episode: its last state
        real_up = np.array([len(ep.states) - 1 >= t and not (ep.terminated and len(ep.states) - 1 == t) for ep in episodes])
        model_up = np.array([not task.fallen(s) for s in sampled[t]])
        (rm, rs), (mm, ms) = up_statistics(real, real_up), up_statistics(sampled[t], model_up)
        real_tilted = np.mean([np.any(np.abs(ep.states[:t + 1, tilt_entries]) > args.tilt) for ep in episodes])
        model_tilted = np.mean(np.any(np.abs(sampled[:t + 1, :, tilt_entries]) > args.tilt, axis=(0, 2)))
        lines.append(f"| {t} | {100 * (1 - real_up.mean()):.1f} % | {100 * (1 - model_up.mean()):.1f} % | "
                     f"{100 * real_tilted:.1f} % | {100 * model_tilted:.1f} % | "
                     + " | ".join(f"{rm[i]:+.3f} / {rs[i]:.3f} | {mm[i]:+.3f} / {ms[i]:.3f}" for i in range(len(names))) + " |")
        print(lines[-1], flush=True)
    fell = np.array([ep.terminated for ep in episodes])
    bounds = np.asarray(task.spec.action_high, dtype=float)
    lines += ["", "Real torques as fractions of their bounds (" + ", ".join(task.spec.action_names) + "), by fate: mean |u| / bound "
              "and the share of steps at >= 95 % of it, over the steps each episode took in the window.", "",
              "| steps | fell: mean | fell: at the bound | up at the end: mean | up at the end: at the bound |", "|---|---|---|---|---|"]
    for lo, hi in zip([0, *steps[:-1]], steps):
        cells = []
        for group in (fell, ~fell):
            u = [np.abs(ep.actions[lo:hi]) / bounds for ep, g in zip(episodes, group) if g and len(ep.actions) > lo]
            u = np.concatenate(u) if u else np.full((1, len(bounds)), np.nan)
            cells += [" / ".join(f"{v:.2f}" for v in u.mean(0)), " / ".join(f"{v:.2f}" for v in (u >= 0.95).mean(0))]
        lines.append(f"| {lo}-{hi} | " + " | ".join(cells) + " |")

    # one-step predictions along the real rides: per episode its transitions (a fall's last one dropped), step t at row t
    data = [(transitions([ep], policy.layout), ep.terminated) for ep in episodes if ep.steps - ep.terminated > 0]
    with torch.no_grad():
        predicted = [[t.numpy() for t in model.predict(torch.as_tensor(x), include_noise=True)] for (x, _), _ in data]
    target_var = np.concatenate([y for (_, y), _ in data]).var(0)
    lines += ["", f"Trial {args.trial}'s GP one step ahead on the real rides' transitions, by fate: mean squared error over the "
              "predicted variance (1: calibrated) and SMSE (over the variance of all test targets), averaged over the "
              f"{len(names)} entries.", "",
              "| steps | fell: error / variance | fell: SMSE | up at the end: error / variance | up at the end: SMSE |", "|---|---|---|---|---|"]
    for lo, hi in zip([0, *steps[:-1]], steps):
        cells = []
        for fate in (True, False):
            z2, se = [], []
            for ((_, y), terminated), (mean, var) in zip(data, predicted):
                if terminated == fate and len(y) > lo:
                    err = (y[lo:hi] - mean[lo:hi]) ** 2
                    z2.append(err / var[lo:hi])
                    se.append(err / target_var)
            cells += [f"{np.concatenate(z2).mean():.2f}", f"{np.concatenate(se).mean():.3f}"] if z2 else ["–", "–"]
        lines.append(f"| {lo}-{hi} | " + " | ".join(cells) + " |")

    lags = (2, 5)
    lines += ["", f"Correlation of the standardised one-step errors of the same ride k steps apart, steps before {args.persist_before}, "
              "per state entry (0 for errors independent from step to step).", "",
              "| state entry | " + " | ".join(f"fell: k = {k} | up at the end: k = {k}" for k in lags) + " |",
              "|---|" + "---|---|" * len(lags)]
    z = [((y - mean) / np.sqrt(var))[:args.persist_before] for ((_, y), _), (mean, var) in zip(data, predicted)]
    fates = [terminated for _, terminated in data]
    for i, name in enumerate(names):
        cells = []
        for k in lags:
            for fate in (True, False):
                pairs = [(e[:-k, i], e[k:, i]) for e, f in zip(z, fates) if f == fate and len(e) > k]
                a, b = (np.concatenate(v) for v in zip(*pairs)) if pairs else (np.zeros(0), np.zeros(0))
                cells.append(f"{np.corrcoef(a, b)[0, 1]:+.2f}" if len(a) > 2 else "–")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    train_on = args.train_on or ""
    if train_on == "gp-smoothed":  # the smoothing's settings in the name: rounds, model-error allowance
        train_on += f"-r{args.smooth_rounds}-q{'-'.join(f'{q:g}' for q in args.process_std)}"
    write_report(lines, args.out / f"drift_check_unicycle_{args.run_id[:8]}_t{args.trial}{'_' + train_on if train_on else ''}"
                 f"{f'_lqr{args.lqr_speed:g}' if args.lqr_speed is not None else ''}.md")


if __name__ == "__main__":
    exit_on_error(main)
