"""Where two Q kernels part in a real policy search, against the parting that one ulp of theta causes.

Usage::

    .venv/bin/python benchmarks/kernel_search_paths.py --data benchmarks/data/gp_double-pendulum_50ec8b95_t20.npz \\
        --task double-pendulum --set horizon=60 --out results/benchmarks/kernel_search_paths_double-pendulum.md

The dynamics GP is fitted once on a stored run's data (as ``benchmarks/device_trial.py`` does, with
the run's settings and warm start); then the learner's policy search (L-BFGS-B within the task
preset's budgets) runs from the same fresh controller several times, one torch thread each:

* with each of ``--kernels`` (default: ``numba fused``; ``fused-whole`` is ``fused`` forming the whole ``Q`` of
  the diagonal pairs, ``MomentMatchingGP(symmetric_pairs=False)``, as before it formed half;
  ``fused-full-jacobian`` is ``fused`` saving the whole jacobian, ``lean_jacobian=False``), and
* with the first kernel again from theta moved by one ulp per entry (random signs, fixed seed): the
  control. Kernels that round differently cannot agree more closely than this.

Reported per search: evaluations, iterations, J after, scipy's stop message, CPU seconds, the first
evaluation at which its J departs from the first search's by more than 1e-9 relative, and how soon
it came within 0.1 of its own final J. A figure shows J against evaluation for every search.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import device_trial  # noqa: E402
from benchmarks.policy_search_progress import traced_search  # noqa: E402
from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402


def fitted_posterior(data_path: Path, learner):
    """The GP fitted on the stored data with the run's settings and warm start (CPU)."""
    from plugins.pilco.gp import GPHyperparameters, GPModel

    data = np.load(data_path)
    settings = json.loads(str(data["settings"]))
    warm = GPHyperparameters(*(torch.tensor(data[k]) for k in ("log_ell", "log_alpha", "log_sigma", "pseudo_inputs")))
    model = GPModel(sparse_threshold=settings["sparse_threshold"], num_pseudo=settings["num_pseudo"],
                    max_evals_full=settings["gp_max_evals"], max_evals_fitc=settings["gp_fitc_evals"],
                    hyper_subset=settings["gp_hyper_subset"], refresh_pseudo=settings["gp_refresh_pseudo"])
    model.fit(data["x"], data["y"], warm_start=warm, seed=settings["seed"])
    return model.posterior(), settings["source"]


#: ``--kernels`` name -> (``MomentMatchingGP`` kernel, its other keyword arguments)
KERNELS = {"torch": ("torch", {}), "numba": ("numba", {}), "fused": ("fused", {}),
           "fused-whole": ("fused", {"symmetric_pairs": False}),
           "fused-full-jacobian": ("fused", {"lean_jacobian": False})}


def one_search(learner, posterior, kernel: str, nudge: bool, seed: int) -> dict:
    """The preset's policy search from the fresh controller of ``seed`` with the dynamics GP's ``kernel``."""
    from plugins.pilco.moments import MomentMatchingGP

    controller = learner.new_controller(torch.Generator().manual_seed(seed))
    objective = device_trial.objective_for(learner, posterior, controller)
    name, options = KERNELS[kernel]
    objective.dynamics = MomentMatchingGP(objective.posterior, kernel=name, **options)
    if nudge:
        theta = objective.get_flat()
        signs = np.random.default_rng(0).choice([-1.0, 1.0], theta.shape)
        objective.set_flat(theta * (1 + np.finfo(float).eps * signs))
    start = time.process_time()
    trace, search = traced_search(objective, learner.preset.policy_max_evaluations,
                                  {"max_iterations": learner.preset.policy_max_iterations})
    return dict(kernel=kernel, nudge=nudge, evaluations=search.evaluations, iterations=search.iterations,
                J_after=float(search.J_after), message=search.message, cpu_s=time.process_time() - start, trace=np.array(trace))


def first_departure(trace: np.ndarray, reference: np.ndarray, rel: float = 1e-9) -> int | None:
    """1-based index of the first evaluation whose J differs from ``reference``'s by more than ``rel``."""
    n = min(len(trace), len(reference))
    apart = np.abs(trace[:n] - reference[:n]) > rel * np.abs(reference[:n])
    return int(np.argmax(apart)) + 1 if apart.any() else None


def figure(rows: list[dict], labels: list[str], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for row, label in zip(rows, labels):
        best = np.minimum.accumulate(row["trace"])
        ax.plot(np.arange(1, len(best) + 1), best, label=f"{label}: {row['evaluations']} evaluations, J {row['J_after']:.3f}")
    ax.set_xlabel("J + dJ evaluation")
    ax.set_ylabel("best J so far")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a .npz written by benchmarks/compare_gp_fit.py --extract")
    parser.add_argument("--task", required=True)
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE", help="task option")
    parser.add_argument("--kernels", nargs="+", default=["numba", "fused"], choices=sorted(KERNELS))
    parser.add_argument("--seed", type=int, default=0, help="the fresh controller's seed")
    parser.add_argument("--out", type=Path, default=None, help="markdown file (the figure goes beside it as .png)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load = load_average()
    task_options = dict(s.split("=", 1) for s in args.sets)
    _, learner = device_trial.build(args.task, task_options, "cpu", args.seed)
    posterior, source = fitted_posterior(args.data, learner)
    plan = [(kernel, False) for kernel in args.kernels] + [(args.kernels[0], True)]
    labels = [kernel + (", theta +- 1 ulp" if nudge else "") for kernel, nudge in plan]
    rows = []
    for (kernel, nudge), label in zip(plan, labels):
        rows.append(one_search(learner, posterior, kernel, nudge, args.seed))
        r = rows[-1]
        print(f"{label}: {r['evaluations']} evaluations, {r['iterations']} iterations, J {r['J_after']:.6f}, "
              f"{r['cpu_s']:.0f} s CPU; {r['message']}", flush=True)
    reference = rows[0]["trace"]
    lines = [f"# Where the Q kernels part in a real policy search ({args.task})", "",
             f"Command: `{command_line(__file__, argv)}`  ", machine_line(load) + "  ",
             f"Data: `{args.data.name}` ({source}); task options {task_options}; the GP fitted once, then the preset's "
             f"policy search ({learner.preset.policy_max_iterations} iterations, {learner.preset.policy_max_evaluations} "
             f"evaluations at most) from the fresh controller of seed {args.seed}, one torch thread.", "",
             "| search | evaluations | iterations | J after | J first apart from the first row's (> 1e-9 relative) at evaluation "
             "| within 0.1 of its final J at evaluation | CPU s | scipy's stop |",
             "|---|---|---|---|---|---|---|---|"]
    for r, label in zip(rows, labels):
        apart = first_departure(r["trace"], reference) if r is not rows[0] else None
        best = np.minimum.accumulate(r["trace"])
        near = int(np.argmax(best <= r["J_after"] + 0.1)) + 1
        lines.append(f"| {label} | {r['evaluations']} | {r['iterations']} | {r['J_after']:.6f} | "
                     f"{'—' if r is rows[0] else apart or 'never'} | {near} | {r['cpu_s']:.0f} | {r['message']} |")
    if args.out is not None:
        png = args.out.with_suffix(".png")
        figure(rows, labels, png, f"policy search, {args.task}: best J per evaluation")
        lines += ["", f"![best J per evaluation]({png.name})"]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
