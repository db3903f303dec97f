"""Where one PILCO J + dJ spends its CPU time, by part of the rollout.

Usage::

    python benchmarks/objective_profile.py [--configs "double-pendulum n=400 H=60" "unicycle n=300 H=40"] \\
        [--repeats 5] [--out results/benchmarks/objective_profile.md]

At the sizes of ``benchmarks/task_objectives.py`` (or a cart-pole size of ``benchmarks/ab_objective.py``), with this checkout's defaults (the ``fused`` kernel where
numba is installed), one torch thread. Each part is timed with ``time.process_time`` around the calls that
make it up, summed over ``--repeats`` J + dJ after a warm-up, and reported per J + dJ:

* **Q kernel**: the compiled contraction (``plugins.pilco.fused.kernels(d)``: every generated kernel);
* **compiled glue**: :func:`plugins.pilco.fused.pair_factors` and :func:`plugins.pilco.fused.input_gradients`;
* **symmetric completion**: :func:`plugins.pilco.fused._symmetric_jacobian` (the diagonal pairs' saved gradients);
* **dynamics GP, the rest**: the dynamics GP's moment matching (``MomentMatchingGP._forward``/``_backward``
  of the objective's model) minus the three above: the batched Cholesky, the mean and cross-covariance,
  the drivers' allocations and conversions, the gradient wrt ``S``;
* **policy GP**: the RBF controller's moment matching (its own ``MomentMatchingGP``, torch contraction);
* **rest of the rollout**: everything else (trigonometric moments, squashing, the joint covariances, the
  cost, autograd's bookkeeping, the controller's posterior).

The parts are disjoint and add up to the total. Timing wrappers cost a few microseconds per call
(a few hundred calls per J + dJ).
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from collections import Counter
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402

PARTS = ("Q kernel", "compiled glue", "symmetric completion", "dynamics GP, the rest", "policy GP", "rest of the rollout")


def _timed(acc: Counter, key: str, f):
    @functools.wraps(f)
    def wrapper(*args, **kwargs):
        t0 = time.process_time()
        try:
            return f(*args, **kwargs)
        finally:
            acc[key] += time.process_time() - t0
    return wrapper


def profile(config: str, repeats: int) -> dict[str, float]:
    """CPU seconds per J + dJ of each part of :data:`PARTS`, and ``total``."""
    import plugins.pilco.fused as fused
    import plugins.pilco.moments as moments

    from benchmarks.ab_objective import build

    obj = build(config)  # a task of benchmarks/task_objectives.py or a cart-pole size of benchmarks/bench_objective.py
    theta = obj.get_flat()
    obj(theta)  # compiles the kernels
    acc: Counter = Counter()
    module = fused.kernels(obj.dynamics.input_dim)
    patched = [(module, name, getattr(module, name)) for name in dir(module)
               if name.startswith(("forward", "backward")) and callable(getattr(module, name))]
    patched += [(fused, name, getattr(fused, name)) for name in ("pair_factors", "input_gradients", "_symmetric_jacobian")]
    patched += [(moments.MomentMatchingGP, name, getattr(moments.MomentMatchingGP, name)) for name in ("_forward", "_backward")]
    kind = {"pair_factors": "compiled glue", "input_gradients": "compiled glue", "_symmetric_jacobian": "symmetric completion"}
    for owner, name, f in patched:
        if owner is moments.MomentMatchingGP:
            def method(self, *args, _f=f, **kwargs):
                key = "dynamics GP" if self is obj.dynamics else "policy GP"
                t0 = time.process_time()
                try:
                    return _f(self, *args, **kwargs)
                finally:
                    acc[key] += time.process_time() - t0
            setattr(owner, name, method)
        else:
            setattr(owner, name, _timed(acc, kind.get(name, "Q kernel"), f))
    try:
        obj(theta)
        acc.clear()
        t0 = time.process_time()
        for _ in range(repeats):
            obj(theta)
        total = time.process_time() - t0
    finally:
        for owner, name, f in patched:
            setattr(owner, name, f)
    inner = acc["Q kernel"] + acc["compiled glue"] + acc["symmetric completion"]
    out = {
        "Q kernel": acc["Q kernel"], "compiled glue": acc["compiled glue"], "symmetric completion": acc["symmetric completion"],
        "dynamics GP, the rest": acc["dynamics GP"] - inner, "policy GP": acc["policy GP"],
        "rest of the rollout": total - acc["dynamics GP"] - acc["policy GP"], "total": total,
    }
    return {k: v / repeats for k, v in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", default=["double-pendulum n=400 H=60", "unicycle n=300 H=40"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "objective_profile.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    load0 = load_average()
    rows = []
    for config in args.configs:
        parts = profile(config, args.repeats)
        total = parts["total"]
        cells = " | ".join(f"{1e3 * parts[p]:.0f} ({100 * parts[p] / total:.0f} %)" for p in PARTS)
        rows.append(f"| {config} | {1e3 * total:.0f} | {cells} |")
        print(rows[-1], flush=True)
    lines = [
        "# One PILCO J + dJ by part of the rollout (CPU ms per J + dJ, one thread)",
        "",
        f"Command: `{command_line(__file__)}`  ",
        f"{machine_line(load0)}  ",
        f"{args.repeats} J + dJ per configuration after a warm-up; the parts are defined in the script's docstring and add up to the total.",
        "",
        "| configuration | total | " + " | ".join(PARTS) + " |",
        "|---|---|" + "---|" * len(PARTS),
        *rows,
    ]
    write_report(lines, args.out, echo=False)


if __name__ == "__main__":
    main()
