"""Unicycle: does PILCO's own objective prefer its learned linear policy or a riding LQR?

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/unicycle_objective_check.py \\
        [--run-id a3e1c149352342babeb677f26a9ff0ac] [--trials 17 11] [--speeds 0.3 0.5 1] \\
        [--horizons 40 67] [--episodes 100] [--search-trials 17] [--search-speeds 0.3] [--refit-full] \\
        [--tracking-uri sqlite:///<repo>/results/runs/mlflow.db]

Question: PILCO's learned linear policy reaches ~17 % success on the unicycle, the riding LQRs of
:mod:`tasks.unicycle_lqr` written as PILCO's squashed linear controller 95-100 %
(``results/benchmarks/unicycle_linear_ceiling.md``). Is the policy search stuck in a local optimum
of J(theta) (the LQR has a *lower* J under the learner's own GP and moment matching), or does the
model/objective itself prefer the learned policy (the LQR's J is higher)?

For each trial K of the PILCO run (``--trials``) it loads the GP the learner trained at trial K
(``trialK/model_trialK.pt``) and the policy it handed over at trial K (``policies/policy_trialK.policy``),
and the riding LQRs (``--speeds``, via :func:`plugins.pilco.policy.linear_policy_from_gain`, as
``benchmarks/unicycle_linear_ceiling.py``). Under that GP it evaluates the learner's objective
(:class:`plugins.pilco.objective.PolicyObjective`: the task's ``N(mu0, Sigma0)``, the run's cost
width, the saved state layout, ``mean_only`` off as in ``pilco``) over each of ``--horizons``
steps, plus the same model by Monte Carlo (:func:`plugins.pilco.sampling.sampled_costs`). On the
real task (the harness's :class:`~harness.evaluation.Evaluator`, ``--episodes`` episodes, seeds
100000 + i, measurement noise on, a fall held to the end) it reports each policy's summed cost over
the same horizons and its success rate, and the success rate of the same episodes without
measurement noise (PILCO's planning feeds the policy the noise-free state; J with the noise on the
policy's input, the learner's ``plan_with_noise``, is a column too). GP diagnostics on those real episodes, within the
trial's planning horizon: the GP's latent predictive variance relative to its signal variance
(0 = at the data, 1 = prior), the median one-step error of the GP mean on the true (noise-free)
states relative to the GP's noise std (both averaged over the 10 outputs), and the fraction of the
episodes' start states from which a deterministic rollout of the GP mean under the policy falls,
next to the fraction of real episodes that fell. With ``--refit-full`` every policy is also
scored under a full GP refitted to the trial's data (the run's model is FITC above 300 points):
is the sparse approximation the source of the model's bias?

Then (``--search-trials`` x ``--search-speeds``) it runs the learner's own policy search
(:func:`plugins.pilco.policy_search.optimise_policy`, the saved preset's L-BFGS budget, at the
planning horizon the learner used at that trial, read from the run's ``planning_horizon`` metric)
starting from the LQR's parameters, and reports where J goes, how far theta moves, and how the
resulting policy does on the real task.

Writes ``results/benchmarks/unicycle_objective_check.md`` (``--out``).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import itertools
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
from harness.errors import NumericalError, exit_on_error  # noqa: E402
from benchmarks.pilco_prediction_check import held_costs  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from harness.testrun import task_options  # noqa: E402
from plugins.pilco.gp import GPModel  # noqa: E402
from plugins.pilco.policy import PilcoPolicy, linear_policy_from_gain, transitions  # noqa: E402
from plugins.pilco.objective import PolicyObjective  # noqa: E402
from plugins.pilco.policy_search import optimise_policy  # noqa: E402
from plugins.pilco.sampling import sampled_costs  # noqa: E402
from plugins.pilco.saved_run import SavedPilcoRun  # noqa: E402
from tasks.unicycle_lqr import riding_lqr  # noqa: E402

DEFAULT_RUN = "a3e1c149352342babeb677f26a9ff0ac"
DEFAULT_URI = f"sqlite:///{ROOT / 'results' / 'runs' / 'mlflow.db'}"


def objective_for(policy: PilcoPolicy, model: GPModel, spec, horizon: int, width, mean_only: bool,
                  policy_noise_std=None) -> PolicyObjective:
    """The learner's J(theta) for ``policy`` under ``model`` (as in :meth:`Pilco.learn`)."""
    return PolicyObjective(policy.controller, model.posterior(), policy.layout, spec.cost, spec.init_mean, spec.init_cov,
                           horizon, mean_only=mean_only, width=width, policy_noise_std=policy_noise_std)


def predicted_J(objective: PolicyObjective, particles: int) -> tuple[float, float]:
    """(moment-matching J, Monte-Carlo J through the same GP); NaN where the closed form breaks down."""
    try:
        with torch.no_grad():
            closed = float(objective.value())
    except (NumericalError, torch.linalg.LinAlgError):
        closed = math.nan
    sampled = float(sampled_costs(objective, particles, seed=0).sum()) if particles else math.nan
    return closed, sampled


def real_summary(result, horizons: list[int]) -> dict:
    """Success, falls and summed real cost over each horizon (a fall holds its last cost)."""
    per_ep = held_costs(result.episodes, max(horizons))
    return {
        "success": result.success_rate,
        "falls": float(np.mean([ep.terminated for ep in result.episodes])),
        "cost": {h: float(np.nanmean(per_ep[:, :h].sum(axis=1))) for h in horizons},
    }


def gp_diagnostics(model: GPModel, episodes, layout, steps: int) -> tuple[float, float]:
    """GP accuracy along real episodes, first ``steps`` steps (a fall's last transition dropped):
    mean over the 10 outputs of (latent predictive variance / signal variance) and of the median
    over transitions of the one-step |error| of the GP mean on the *true* (noise-free) states and
    state changes divided by the GP's noise std (the learner's data are noisy observations; the
    noise std is what the GP deems unexplainable; the median, as the few steps of a fall carry
    errors orders of magnitude larger than the rest)."""
    cut = []
    for ep in episodes:
        ep = dataclasses.replace(ep, observations=ep.states)  # true states as GP inputs and targets
        if ep.steps > steps:
            ep = dataclasses.replace(ep, observations=ep.observations[: steps + 1], states=ep.states[: steps + 1],
                                     actions=ep.actions[:steps], costs=ep.costs[:steps], terminated=False)
        cut.append(ep)
    x, y = transitions(cut, layout)
    mean, var = model.predict(x)
    hyp = model.hyperparameters
    signal_var = torch.exp(2.0 * hyp.log_alpha).numpy()
    noise_std = torch.exp(hyp.log_sigma).numpy()
    var_ratio = float(np.mean(var.numpy() / signal_var[None, :]))
    err = float(np.mean(np.median(np.abs(y - mean.numpy()), axis=0) / noise_std))
    return var_ratio, err


def gp_mean_falls(model: GPModel, policy: PilcoPolicy, episodes, task, steps: int) -> float:
    """Fraction of the real episodes' true start states whose deterministic rollout of the GP mean
    under ``policy`` (no noise) reaches the task's fall region within ``steps`` steps."""
    layout = policy.layout
    x = torch.as_tensor(np.array([ep.states[0] for ep in episodes]), dtype=torch.float64)
    fell = np.zeros(len(episodes), dtype=bool)
    with torch.no_grad():
        for _ in range(steps):
            a = layout.augment(x)
            u = policy.controller(a[:, layout.policy_index])
            mean, _ = model.predict(torch.cat([a[:, layout.model_index], u], dim=1))
            x = x + mean
            fell |= np.array([task.fallen(s) for s in x.numpy()])
    return float(fell.mean())


def real_falls_within(episodes, steps: int) -> float:
    return float(np.mean([ep.terminated and ep.steps <= steps for ep in episodes]))


def theta_of(policy: PilcoPolicy) -> np.ndarray:
    return torch.cat([p.detach().reshape(-1) for p in policy.controller.parameters()]).numpy().copy()


def fmt(v: float, digits: int = 2) -> str:
    return "fail" if not math.isfinite(v) else f"{v:.{digits}f}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-id", default=DEFAULT_RUN)
    parser.add_argument("--trials", type=int, nargs="+", default=[17, 11])
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.3, 0.5, 1.0])
    parser.add_argument("--horizons", type=int, nargs="+", default=[40, 67])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--particles", type=int, default=500, help="Monte-Carlo particles through the GP (0 = off)")
    parser.add_argument("--search-trials", type=int, nargs="*", default=[17])
    parser.add_argument("--search-speeds", type=float, nargs="*", default=[0.3])
    parser.add_argument("--refit-full", action="store_true",
                        help="also score every policy under a full GP refitted to the trial's data (warm-started at the "
                             "saved hyperparameters): is the sparse (FITC) approximation the model's bias?")
    parser.add_argument("--tracking-uri", default=DEFAULT_URI)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "unicycle_objective_check.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    t_start = time.perf_counter()

    horizons = sorted(set(args.horizons))
    loaded = {}
    with SavedPilcoRun(args.run_id, args.tracking_uri, task="unicycle") as run:
        plan_h = {step: int(value) for step, value in run.metric("planning_horizon").items()}
        J_after = run.metric("J_after")
        for trial in sorted(set(args.trials) | set(args.search_trials)):
            saved, model, policy = run.saved_model(trial), run.model(trial), run.policy(trial)
            if policy.layout != saved["layout"]:
                sys.exit(f"trial {trial}: the policy's layout {policy.layout} differs from the model's {saved['layout']}")
            loaded[trial] = (saved, model, policy)
    params, task = run.params, run.task
    spec = task.spec
    mean_only = run.mean_only
    width = None if params.get("learner.cost_width") in (None, "None") else float(params["learner.cost_width"])

    models: dict[int, list[tuple[str, GPModel]]] = {}
    for trial in args.trials:
        saved, model, _ = loaded[trial]
        models[trial] = [("FITC (run)" if model.sparse else "full (run)", model)]
        if args.refit_full:
            t = time.perf_counter()
            full = GPModel(sparse_threshold=10**9, max_evals_full=int(params.get("learner.gp_max_evals", 300)))
            fit = full.fit(saved["gp"]["inputs"], saved["gp"]["targets"], warm_start=model.hyperparameters)
            models[trial].append(("full refit", full))
            print(f"trial {trial}: full GP refit on {fit.n_points} points, NLL {fit.nll:.1f} ({time.perf_counter() - t:.0f} s)",
                  flush=True)

    lqrs = {v: linear_policy_from_gain(spec, *riding_lqr(task, v)) for v in args.speeds + args.search_speeds}
    for v, p in lqrs.items():
        if p.layout != loaded[args.trials[0]][0]["layout"]:
            sys.exit(f"LQR {v} m/s: layout {p.layout} differs from the learner's")

    evaluator = Evaluator(task, n_episodes=args.episodes, seed=100_000)
    # the same episodes without measurement noise: how much of a failure is the policy's noise sensitivity
    # (the GP-mean rollouts and PILCO's planning see no measurement noise in the policy's input)
    noise_free = Evaluator(load_task("unicycle")(**{**task_options(params), "measurement_noise": 0.0}),
                           n_episodes=args.episodes, seed=100_000)
    real_cache: dict[str, tuple[dict, list]] = {}

    def real(name: str, policy: PilcoPolicy) -> tuple[dict, list]:
        if name not in real_cache:
            t = time.perf_counter()
            result = evaluator(policy)
            real_cache[name] = ({**real_summary(result, horizons), "success_noise_free": noise_free(policy).success_rate},
                                result.episodes)
            print(f"  real {name}: success {100 * result.success_rate:.0f} %  ({time.perf_counter() - t:.0f} s)", flush=True)
        return real_cache[name]

    # ---- J of the learned policy and the LQRs under each trial's model --------------------------
    rows = []
    for trial in args.trials:
        saved, _, learned = loaded[trial]
        H = plan_h[trial]
        print(f"trial {trial}: GP on {saved['gp']['inputs'].shape[0]} points, planning horizon {H}", flush=True)
        candidates = [(f"learned (trial {trial})", f"learned{trial}", learned)]
        candidates += [(f"riding LQR {v:g} m/s", f"lqr{v:g}", lqrs[v]) for v in args.speeds]
        for (label, key, policy), (model_name, model) in itertools.product(candidates, models[trial]):
            t = time.perf_counter()
            J = {h: predicted_J(objective_for(policy, model, spec, h, width, mean_only), args.particles) for h in horizons}
            J_noisy = predicted_J(objective_for(policy, model, spec, H, width, mean_only, spec.measurement_noise_std), 0)[0]
            summary, episodes = real(key, policy)
            var_ratio, nrmse = gp_diagnostics(model, episodes, policy.layout, H)
            falls_gp, falls_real = gp_mean_falls(model, policy, episodes, task, H), real_falls_within(episodes, H)
            rows.append((trial, label, model_name, J, J_noisy, summary, var_ratio, nrmse, falls_gp, falls_real))
            print(f"  {label:22s} {model_name:11s} J " + "  ".join(f"H{h} {J[h][0]:.2f} (MC {J[h][1]:.2f})" for h in horizons)
                  + f"  noisy input H{H} {J_noisy:.2f}  real " + "  ".join(f"H{h} {summary['cost'][h]:.2f}" for h in horizons)
                  + f"  var/prior {var_ratio:.3f}  err/noise {nrmse:.3f}  falls({H}) GP-mean {falls_gp:.2f} real {falls_real:.2f}  ({time.perf_counter() - t:.0f} s)", flush=True)

    # ---- the learner's policy search started from the LQRs ---------------------------------------
    searches = []
    short = lambda label: label.split()[0]  # noqa: E731  ('u_t turntable torque [Nm]' -> 'u_t')
    names = [f"W[{short(u)},{short(x)}]" for u in spec.action_names for x in spec.state_names] + [f"b[{short(u)}]" for u in spec.action_names]
    for trial in args.search_trials:
        saved, model, learned = loaded[trial]
        H, preset = plan_h[trial], saved["preset"]
        for v in args.search_speeds:
            start_policy = lqrs[v]
            policy = PilcoPolicy(copy.deepcopy(start_policy.controller), start_policy.layout)
            objective = objective_for(policy, model, spec, H, width, mean_only)
            t = time.perf_counter()
            search = optimise_policy(objective, preset.policy_max_iterations, preset.policy_max_evaluations)
            seconds = time.perf_counter() - t
            theta0, theta1, theta_l = theta_of(start_policy), theta_of(policy), theta_of(learned)
            J67 = {h: predicted_J(objective_for(policy, model, spec, h, width, mean_only), 0)[0] for h in horizons}
            summary, _ = real(f"search{trial}-{v:g}", policy)
            searches.append({
                "trial": trial, "speed": v, "H": H, "J_before": search.J_before, "J_after": search.J_after, "J": J67,
                "evals": search.evaluations, "iters": search.iterations, "failed": search.failed_evaluations,
                "message": search.message, "seconds": seconds,
                "moved": float(np.linalg.norm(theta1 - theta0) / np.linalg.norm(theta0)),
                "moved_abs": float(np.linalg.norm(theta1 - theta0)),
                "largest": [(names[i], theta0[i], theta1[i]) for i in np.argsort(-np.abs(theta1 - theta0))[:3]],
                "to_learned_before": float(np.linalg.norm(theta0 - theta_l) / np.linalg.norm(theta_l)),
                "to_learned_after": float(np.linalg.norm(theta1 - theta_l) / np.linalg.norm(theta_l)),
                "real": summary,
            })
            print(f"search trial {trial} from LQR {v:g}: J {search.J_before:.2f} -> {search.J_after:.2f} in {search.evaluations} "
                  f"evaluations ({seconds:.0f} s; {search.message}); real success {100 * summary['success']:.0f} %", flush=True)

    # ---- report ------------------------------------------------------------------------------------
    hcols = " | ".join(f"J({h}) MM | J({h}) MC" for h in horizons)
    rcols = " | ".join(f"real cost({h})" for h in horizons)
    lines = [
        "# Unicycle: PILCO's own objective J(theta), learned linear policy vs riding LQRs", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"Run `{args.run_id}` ({params['learner']} on {params['task']}, task options "
        f"{', '.join(f'{k[5:]}={v}' for k, v in sorted(params.items()) if k.startswith('task.'))}; learner options "
        f"planning_horizon={params.get('learner.planning_horizon')}, grow_horizon_below={params.get('learner.grow_horizon_below')}, "
        f"cost_width={params.get('learner.cost_width')}). Planning horizon used at each trial (run metric): "
        + ", ".join(f"trial {t}: {plan_h[t]}" for t in sorted(set(args.trials) | set(args.search_trials))) + ".", "",
        "**J(H) MM** = the learner's objective (moment matching, sum of expected cost over H steps from the task's "
        "N(mu0, Sigma0), cost width 1, saved layout) under the GP trained at that trial (**GP**: the run's own model, "
        "FITC or full; *full refit*: a full GP refitted to the same data, warm-started at the run's hyperparameters); "
        "**J(Hp) MM, noisy policy input** = the same over the trial's planning horizon Hp with the task's measurement "
        "noise on the policy's input (learner option `plan_with_noise`); **J(H) MC** = the same GP and "
        f"policy by Monte Carlo ({args.particles} particles, seed 0); *fail* = the closed form broke down (Cholesky). "
        f"**real cost(H)** = mean over {args.episodes} real episodes (seeds 100000 + i, measurement noise on) of the "
        "cost summed over the first H steps, a fall holding its last cost; success = the task's rule; *no measurement "
        "noise*: the same episodes with the task's measurement noise off (the policy acts on the true state, as in "
        "PILCO's planning). "
        "**GP var/prior** = GP latent predictive variance / signal variance and **1-step err/noise** = median one-step |error| "
        "of the GP mean on true (noise-free) states and state changes / the GP's noise std, both on the real "
        "episodes' transitions within the trial's planning horizon, averaged over the 10 outputs. **falls(Hp) "
        "GP-mean / real** = fraction of the real episodes' start states from which the deterministic GP-mean rollout "
        "under the policy reaches the fall region (|theta| or |psi_f| > pi/2) within the planning horizon Hp / "
        "fraction of the real episodes that fell within Hp.", "",
        f"| trial | policy | GP | {hcols} | J(Hp) MM, noisy policy input | {rcols} | success | success, no measurement noise | falls | GP var/prior | 1-step err/noise | falls(Hp) GP-mean / real |",
        "|---|---|---|" + "---|" * (3 * len(horizons) + 7),
    ]
    for trial, label, model_name, J, J_noisy, s, var_ratio, nrmse, falls_gp, falls_real in rows:
        lines.append(f"| {trial} | {label} | {model_name} | " + " | ".join(f"{fmt(J[h][0])} | {fmt(J[h][1]) if args.particles else '-'}" for h in horizons) + f" | {fmt(J_noisy)} | "
                     + " | ".join(f"{s['cost'][h]:.2f}" for h in horizons)
                     + f" | {100 * s['success']:.0f} % | {100 * s['success_noise_free']:.0f} % | {100 * s['falls']:.0f} % | {var_ratio:.4f} | {nrmse:.2f} | "
                     f"{100 * falls_gp:.0f} % / {100 * falls_real:.0f} % |")
    for trial in args.trials:
        if trial in J_after:
            lines.append("")
            lines.append(f"Check: the run logged J_after = {J_after[trial]:.4f} for trial {trial} (planning horizon "
                         f"{plan_h[trial]}); recomputed here: "
                         f"{next(r[3][plan_h[trial]][0] for r in rows if r[0] == trial and r[1].startswith('learned')):.4f}."
                         if plan_h[trial] in horizons else f"Run's J_after for trial {trial}: {J_after[trial]:.4f}.")
    if searches:
        jcols = " | ".join(f"J({h}) MM after" for h in horizons)
        lines += [
            "", "## The learner's policy search started from the riding LQR", "",
            "L-BFGS-B of `optimise_policy` with the saved preset's budget (policy_max_iterations, policy_max_evaluations) "
            "at the trial's planning horizon, under the same GP. *moved* = |theta_after - theta_LQR| / |theta_LQR|; "
            "*to learned* = |theta - theta_learned| / |theta_learned| before -> after (theta = the 22 controller "
            "parameters, pre-squash W and b, in `controller.parameters()` order); *largest changes* = the three "
            f"parameters that moved most, LQR -> after. Real columns: {args.episodes} episodes of the policy the "
            "search returned.", "",
            f"| trial | start | H | J before | J after | evaluations (iterations, failed) | {jcols} | moved (abs) | "
            f"to learned | largest changes | real cost(67) | success | falls | seconds |",
            "|---|---|---|---|---|---|" + "---|" * len(horizons) + "---|---|---|---|---|---|---|",
        ]
        for s in searches:
            lines.append(
                f"| {s['trial']} | riding LQR {s['speed']:g} m/s | {s['H']} | {s['J_before']:.2f} | {s['J_after']:.2f} | "
                f"{s['evals']} ({s['iters']}, {s['failed']}) | " + " | ".join(fmt(s["J"][h]) for h in horizons)
                + f" | {s['moved']:.4f} ({s['moved_abs']:.4f}) | {s['to_learned_before']:.3f} -> {s['to_learned_after']:.3f} | "
                + ", ".join(f"{n}: {a:.4f} -> {b:.4f}" for n, a, b in s["largest"]) + " | "
                f"{s['real']['cost'][max(horizons)]:.2f} | {100 * s['real']['success']:.0f} % | {100 * s['real']['falls']:.0f} % | "
                f"{s['seconds']:.0f} |")
        lines += ["", "scipy's messages: " + "; ".join(f"trial {s['trial']}, {s['speed']:g} m/s: {s['message']}" for s in searches)]
    lines += ["", f"Total wall time {time.perf_counter() - t_start:.0f} s (one thread)."]
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
