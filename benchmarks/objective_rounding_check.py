"""How far apart the Q kernels' J and dJ are at a run's own policy, against J's own rounding sensitivity there.

Usage::

    .venv/bin/python benchmarks/objective_rounding_check.py RUN_ID --trial 21 --horizon 60 \\
        --tracking-uri sqlite:///$PWD/results/runs/mlflow.db --out results/benchmarks/objective_rounding_<task>.md

Loads the GP trained at ``--trial`` and the policy handed over there (``SavedPilcoRun``; the run's
local files), builds PILCO's objective over ``--horizon`` steps with the task's cost (its own width)
and start distribution, and evaluates J + dJ at the policy's theta with each kernel (torch, the
reference; numba; fused), one thread. For scale, J + dJ with the torch kernel at theta moved by 1-2
ulps per entry (two random draws): two computations that round differently cannot agree more
closely than that.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    from plugins.pilco.moments import MomentMatchingGP
    from plugins.pilco.objective import PolicyObjective
    from plugins.pilco.saved_run import SavedPilcoRun

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_id")
    parser.add_argument("--trial", type=int, required=True, help="the trial whose GP and handed-over policy are used")
    parser.add_argument("--horizon", type=int, required=True, help="planning horizon (steps)")
    parser.add_argument("--tracking-uri", default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load = load_average()
    with SavedPilcoRun(args.run_id, args.tracking_uri) as run:
        model, policy, spec = run.model(args.trial), run.policy(args.trial), run.task.spec
        objective = PolicyObjective(policy.controller, model.posterior(), policy.layout, spec.cost, spec.init_mean,
                                    spec.init_cov, args.horizon)
        task = run.params.get("task")
    theta = objective.get_flat()
    results = {}
    for kernel in ("torch", "numba", "fused"):
        objective.dynamics = MomentMatchingGP(objective.posterior, kernel=kernel)
        results[kernel] = objective(theta)
    J_ref, g_ref = results["torch"]

    def apart(J, g):
        return abs(J - J_ref) / abs(J_ref), np.linalg.norm(g - g_ref) / np.linalg.norm(g_ref)

    rows = [(kernel, *results[kernel], *apart(*results[kernel])) for kernel in results]
    objective.dynamics = MomentMatchingGP(objective.posterior, kernel="torch")
    for seed in (0, 1):
        signs = np.random.default_rng(seed).choice([-2.0, -1.0, 1.0, 2.0], theta.shape)
        J, g = objective(theta * (1 + np.finfo(float).eps * signs))
        rows.append((f"torch, theta +- 1-2 ulp (draw {seed})", J, g, *apart(J, g)))
    lines = [f"# J and dJ of each Q kernel at a run's own policy ({task}, run `{args.run_id[:8]}`, trial {args.trial})", "",
             f"Command: `{command_line(__file__, argv)}`  ", machine_line(load) + "  ",
             f"The GP of trial {args.trial} and the policy handed over there; {args.horizon} steps, the task's cost and "
             "start distribution; one torch thread.", "",
             "| computation | J | relative difference of J from torch's | of dJ (2-norm) |", "|---|---|---|---|"]
    lines += [f"| {name} | {J:.15g} | {dJ:.1e} | {dg:.1e} |" for name, J, _, dJ, dg in rows]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
