"""What planning on fewer basis points costs: model quality, J, the policy it finds, and time.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/planning_basis_check.py --checkpoints CKPT [CKPT ...]
        --test CKPT:FIRST-LAST [--basis 300 200 150 100] [--episodes 50] [--out FILE]

Reads PILCO runs' checkpoints (``checkpoints/ckpt_trialNNN`` of a run in the store; an older
harness's pickle is read as ``harness store migrate`` reads it, so only checkpoints of your own
runs): the data, the GP hyperparameters (``M`` FITC pseudo-inputs, or a full GP on its training
inputs) and the policy handed over at that trial after planning with that GP. Then builds the planning
posterior of the learner option ``planning_basis`` for each count in ``--basis``
(:func:`plugins.pilco.sparse.reduced_posterior`: that many of the model's basis points, chosen
greedily where they explain the kernel at the training inputs best, same hyperparameters and data), the same subset with its pseudo-inputs then
optimised on the FITC likelihood (``--refine`` L-BFGS evaluations, the learner's pseudo-input
optimisation: what a model trained with ``num_pseudo`` = that count would plan with), and a control
that keeps a uniformly random subset of the same size. Each is scored on

* **held-out one-step quality**: NLPD (nats per transition, summed over the state dimensions) and
  SMSE on episodes ``FIRST``-``LAST`` of checkpoint ``--test`` (as ``gp_heldout_check``);
* **J** of the run's policy under it, beside J under the whole model and the policy's **real** cost
  over the same horizon (mean of ``--episodes`` simulated episodes);
* **time**: CPU seconds of one J + dJ on one thread (the better of two), the planning arithmetic a
  trial repeats 150-300 times; and the CPU seconds the refinement of the pseudo-inputs took;
* with ``--search N``: a policy search of at most ``N`` J + dJ evaluations from fresh initial
  parameters (drawn as the learner draws its first controller, seeded by the run's seed) under the posterior, and what the policy it finds
  costs under the **whole** model and in simulation: what planning on fewer points loses in the
  policy it produces.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.gp_budget_check import predictive_scores  # noqa: E402
from benchmarks.pilco_prediction_check import real_costs  # noqa: E402
from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from harness.errors import exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from plugins.pilco.gp import predict_latent  # noqa: E402
from harness.checkpoint import load_checkpoint  # noqa: E402
from harness.datafile import is_legacy  # noqa: E402
from harness.interaction import Episode  # noqa: E402
from harness.migration import read_legacy_checkpoint  # noqa: E402
from harness.runner import config_from_identity, new_learner, prepare  # noqa: E402
from plugins.pilco.gp import GPModel, optimise_pseudo_inputs  # noqa: E402
from plugins.pilco.policy import PilcoPolicy, transitions  # noqa: E402
from plugins.pilco.objective import PolicyObjective  # noqa: E402
from plugins.pilco.policy_search import optimise_policy  # noqa: E402
from plugins.pilco.posterior import GPPosterior  # noqa: E402
from plugins.pilco.sparse import fitc_posterior, select_basis  # noqa: E402


class CheckpointedRun:
    """A PILCO run at one checkpoint: its task, episodes, GP and handed-over policy.

    Attributes:
        label: ``<run id[:8]> t<trial>`` from the checkpoint's path (``.../<run id>/artifacts/checkpoints/...``).
        seed, trial: the run's seed and the checkpoint's trial.
        task: the task with the run's options; ``episodes``: every episode recorded so far.
        learner: the learner built with the run's options (its layout, preset, planning horizon, width).
        model: the GP of that trial (trained on ``episodes``); ``policy``: the policy handed over.
    """

    def __init__(self, path: Path) -> None:
        checkpoint = read_legacy_checkpoint(path) if is_legacy(path.name) else load_checkpoint(path)
        identity = checkpoint.identity
        parts = path.resolve().parts
        self.label = f"{parts[-4][:8]} t{checkpoint.trial}" if len(parts) >= 4 else f"{path.name}"
        self.seed, self.trial = identity["seed"], checkpoint.trial
        prep = prepare(config_from_identity(identity))
        self.task, self.learner = prep.task, new_learner(prep)
        self.episodes = [Episode(**e) for e in checkpoint.interaction["episodes"]]
        state = checkpoint.learner
        x, y = transitions(self.episodes, self.learner.layout)
        hyp = state["hyperparameters"]
        self.model = GPModel()
        pseudo = hyp.get("pseudo_inputs")
        self.model.load_state_dict({**{k: hyp[k] for k in ("log_ell", "log_alpha", "log_sigma")}, "inputs": x, "targets": y,
                                    "pseudo_inputs": pseudo if pseudo is not None else np.zeros((0, x.shape[1])),
                                    "sparse": pseudo is not None})
        controller = self.learner.new_controller(torch.Generator().manual_seed(0))
        controller.load_state_dict({k: torch.as_tensor(v) for k, v in state["controller"].items()})
        self.policy = PilcoPolicy(controller, self.learner.layout)
        self.horizon = int(state.get("planning_horizon") or self.learner.horizon)


def parse_test(text: str) -> tuple[Path, int, int]:
    """``"CKPT:20-27"`` -> ``(Path("CKPT"), 20, 27)``."""
    try:
        path, span = text.rsplit(":", 1)
        first, last = (int(v) for v in span.split("-"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--test {text!r}: expected CHECKPOINT:FIRST-LAST, e.g. .../ckpt_trial027.pkl:20-27") from None
    if not 0 <= first <= last:
        raise argparse.ArgumentTypeError(f"--test {text!r}: need 0 <= FIRST <= LAST")
    return Path(path), first, last


def heldout_scores(posterior: GPPosterior, x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``(NLPD, SMSE)`` of a posterior on inputs ``x (m, d)`` and targets ``y (m, E)`` (observation noise included)."""
    with torch.no_grad():
        mean, var = predict_latent(posterior, torch.as_tensor(x))
        var = var + torch.exp(2.0 * posterior.log_sigma)[None, :]
    return predictive_scores(mean.numpy(), var.numpy(), y)


def j_and_time(objective: PolicyObjective) -> tuple[float, float]:
    """``(J, CPU seconds of the faster of two J + dJ evaluations)`` of ``objective`` at its current parameters."""
    theta = objective.get_flat()
    best = float("inf")
    for _ in range(2):
        start = time.process_time()
        J, _ = objective.value_and_grad(theta)
        best = min(best, time.process_time() - start)
    return J, best


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoints", type=Path, nargs="+", required=True)
    parser.add_argument("--test", type=parse_test, required=True)
    parser.add_argument("--basis", type=int, nargs="+", default=[300, 200, 150, 100])
    parser.add_argument("--episodes", type=int, default=50, help="simulated episodes for each policy's real cost")
    parser.add_argument("--refine", type=int, default=100, help="FITC L-BFGS evaluations refining a reduced basis")
    parser.add_argument("--search", type=int, default=0, help="J + dJ evaluations of a policy search per posterior (0: none)")
    parser.add_argument("--out", type=Path, default=None, help="markdown file (default: print only)")
    args = parser.parse_args(argv)
    if any(b < 1 for b in args.basis):
        sys.exit("--basis: every count must be at least 1")
    missing = [str(p) for p in [*args.checkpoints, args.test[0]] if not p.is_file()]
    if missing:
        sys.exit(f"no such checkpoint file: {', '.join(missing)}")
    torch.set_num_threads(1)
    load_at_start = load_average()

    test_path, first, last = args.test
    test = CheckpointedRun(test_path)
    if last >= len(test.episodes):
        sys.exit(f"--test: {test.label} holds {len(test.episodes)} episodes (0..{len(test.episodes) - 1}); asked for up to {last}")
    test_episodes = test.episodes[first:last + 1]

    rows, n_test = [], 0
    for path in args.checkpoints:
        run = CheckpointedRun(path)
        if run.task.spec.name != test.task.spec.name:
            sys.exit(f"{path}: a run on {run.task.spec.name}, the test set is from {test.task.spec.name}")
        spec, horizon = run.task.spec, run.horizon
        learner = run.learner

        def objective_of(policy, posterior: GPPosterior) -> PolicyObjective:
            """J of ``policy`` under ``posterior`` as the run planned: its horizon, width, mean_only, planning noise."""
            return PolicyObjective(policy.controller, posterior, policy.layout, spec.cost, spec.init_mean, spec.init_cov,
                                   horizon, mean_only=learner.mean_only, width=learner.cost_width,
                                   policy_noise_std=learner.policy_noise_std, threads=1)

        x_test, y_test = transitions(test_episodes, run.learner.layout)
        n_test = len(x_test)
        per_step, _ = real_costs(Evaluator(run.task, n_episodes=args.episodes, seed=200_000), run.policy, horizon)
        real = float(per_step.sum())
        model = run.model
        h = model.hyperparameters
        state = model.state_dict()
        inputs, targets = state["inputs"], state["targets"]
        basis = h.pseudo_inputs if h.pseudo_inputs is not None else inputs
        whole = model.posterior()
        J0, t0 = j_and_time(objective_of(run.policy, whole))
        fresh = run.learner.new_controller(torch.Generator().manual_seed(run.seed)).state_dict()

        def score(label: str, posterior: GPPosterior, refine_seconds: float | None) -> None:
            J, seconds = (J0, t0) if posterior is whole else j_and_time(objective_of(run.policy, posterior))
            nlpd, smse = heldout_scores(posterior, x_test, y_test)
            found = ()
            if args.search:
                policy = copy.deepcopy(run.policy)
                policy.controller.load_state_dict(fresh)
                objective = objective_of(policy, posterior)
                start = time.process_time()
                optimise_policy(objective, max_iterations=args.search, max_evaluations=args.search)
                search_seconds = time.process_time() - start
                J_whole, _ = j_and_time(objective_of(policy, whole))
                per_step, success = real_costs(Evaluator(run.task, n_episodes=args.episodes, seed=300_000), policy, horizon)
                found = (search_seconds, objective.value().item(), J_whole, float(per_step.sum()), success)
            rows.append((*head, label, nlpd, smse, J, seconds, refine_seconds, found))
            print(f"  {label}: NLPD {nlpd:.3f} SMSE {smse:.4f} J {J:.2f} (real {real:.2f}) {seconds:.3f} s per J + dJ"
                  + (f"; search {found[0]:.0f} s CPU: J {found[1]:.2f}, under the whole model {found[2]:.2f}, "
                     f"real {found[3]:.2f} ({100 * found[4]:.0f} % success)" if found else ""), flush=True)

        own = " (own episodes)" if run.label.split()[0] == test.label.split()[0] else ""
        head = (run.label + own, run.seed, len(inputs), real)
        print(f"{run.label}: {len(inputs)} points, basis {basis.shape[0]}", flush=True)
        score(f"all {basis.shape[0]} (the model)", whole, None)
        generator = torch.Generator().manual_seed(run.trial)
        for count in sorted({b for b in args.basis if b < basis.shape[0]}, reverse=True):
            score(f"{count}, greedy", model.posterior(max_basis=count), None)
            start = time.process_time()
            z, _, _ = optimise_pseudo_inputs(inputs, targets, h, basis[select_basis(basis, inputs, h.log_ell, count)], args.refine)
            refine_seconds = time.process_time() - start
            score(f"{count}, greedy + {args.refine} FITC evaluations", fitc_posterior(inputs, targets, z, h.log_ell, h.log_alpha,
                                                                                  h.log_sigma), refine_seconds)
            keep = torch.randperm(basis.shape[0], generator=generator)[:count]
            score(f"{count}, random", fitc_posterior(inputs, targets, basis[keep], h.log_ell, h.log_alpha, h.log_sigma), None)

    lines = [
        f"# Planning on fewer basis points ({test.task.spec.name}): model quality, J, dJ and time", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"{machine_line(load_at_start)}  ",
        f"Held-out set: episodes {first}-{last} of `{test.label}` ({n_test} transitions); NLPD in nats per transition "
        "(summed over the state dimensions; lower is better), SMSE averaged over the state dimensions. J: the closed-form "
        "expected cost of the policy the run handed over at that trial (planned with the whole model); real: its mean cost "
        f"over the planning horizon in {args.episodes} simulated episodes. "
        "CPU s: one J + dJ on one thread (better of two); refine: CPU s of the pseudo-input refinement."
        + (f" Search: {args.search} J + dJ evaluations from fresh initial parameters (the learner's draw, seeded by the run's seed) "
           "under that posterior; "
           "the found policy's J under it, under the whole model, and its real cost and success rate over "
           f"{args.episodes} simulated episodes." if args.search else ""), "",
        "| run, trial | seed | points | real cost | planning basis | NLPD | SMSE | J | J - real | CPU s per J + dJ | refine CPU s |"
        + (" search CPU s | found: J | J whole model | real cost | success |" if args.search else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|---|---|" if args.search else ""),
    ]
    for r, seed, n, real, b, nlpd, smse, J, sec, refine, found in rows:
        line = (f"| `{r}` | {seed} | {n} | {real:.2f} | {b} | {nlpd:.3f} | {smse:.4f} | {J:.2f} | {J - real:+.2f} | {sec:.3f} | "
                f"{'' if refine is None else f'{refine:.0f}'} |")
        if args.search:
            line += f" {found[0]:.0f} | {found[1]:.2f} | {found[2]:.2f} | {found[3]:.2f} | {100 * found[4]:.0f} % |"
        lines.append(line)
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
