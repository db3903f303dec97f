"""How many tensor operations one PILCO J + dJ launches, and where in the rollout they come from.

Usage::

    python benchmarks/objective_op_count.py [--tasks double-pendulum unicycle] [--out results/benchmarks/objective_op_count.md]

On a GPU every operation that is not a view is one kernel launch, and with J + dJ replayed as a CUDA
graph the launches, not the arithmetic, set its time (``results/benchmarks/device_trial_double-pendulum.md``:
32k launches, 125 ms of kernel time launched one by one, 70 ms replayed). This counts them on the
CPU with the torch kernel and every output pair in one block (as on a GPU), at the sizes of
``benchmarks/task_objectives.py``, and attributes each to the region of the rollout running it: the
dynamics GP's moment matching (forward and backward), the RBF policy's moment matching, and
everything else per step (trigonometric augmentation, squashing, the joint covariances of the
propagation step, the cost): the "glue". No timing: the counts do not depend on the machine.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ["HARNESS_PILCO_BLOCK_KB"] = str(10**8)  # every pair in one block, as on a GPU (read at import)

from benchmarks.report_file import command_line, write_report  # noqa: E402

#: aten operators that make views or metadata only (no kernel on a GPU)
VIEWS = {"slice", "unsqueeze", "numpy_T", "select", "mT", "reshape", "diagonal", "squeeze", "view", "expand", "t", "transpose",
         "permute", "as_strided", "detach", "alias", "new_empty", "empty", "_unsafe_view", "split", "unbind", "matmul",
         "contiguous", "lift_fresh"}


def count(task: str, options: dict[str, str], n: int, horizon: int) -> Counter:
    """Non-view aten operations of one J + dJ per region (``dynamics GP``, ``policy GP``, ``glue``)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    import plugins.pilco.moments as moments
    from benchmarks.task_objectives import task_objective
    from plugins.pilco.objective import PolicyObjective

    base = task_objective(task, options, n, horizon)
    obj = PolicyObjective(base.controller, base.posterior, base.layout, base.cost.cost, base.init_mean.numpy(),
                          base.init_cov.numpy(), base.horizon, base.mean_only, base.cost.width, kernel="torch")
    theta = obj.get_flat()
    obj(theta)
    region = ["glue"]
    originals = {name: getattr(moments.MomentMatchingGP, name) for name in ("forward", "backward")}

    def tracked(name):
        def method(self, *args, **kwargs):
            region.append("dynamics GP" if self is obj.dynamics else "policy GP")
            try:
                return originals[name](self, *args, **kwargs)
            finally:
                region.pop()
        return method

    class Count(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.counts: Counter = Counter()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.overloadpacket.__name__ not in VIEWS:
                self.counts[region[-1]] += 1
            return func(*args, **(kwargs or {}))

    for name in originals:
        setattr(moments.MomentMatchingGP, name, tracked(name))
    try:
        with Count() as mode:
            obj(theta)
    finally:
        for name, method in originals.items():
            setattr(moments.MomentMatchingGP, name, method)
    return mode.counts


def main(argv: list[str] | None = None) -> None:
    from benchmarks.task_objectives import TASK_CONFIGS

    names = {config[0]: name for name, config in TASK_CONFIGS.items()}
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(names), choices=list(names))
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "objective_op_count.md")
    args = parser.parse_args(argv)
    lines = ["# Tensor operations per PILCO J + dJ, by region of the rollout", "", f"Command: `{command_line(__file__, argv)}`", "",
             "Non-view aten operations (on a GPU: kernel launches), torch kernel, all output pairs in one block.", "",
             "| objective | all | per step | dynamics GP | policy GP | glue (trig, squash, propagation step, cost) |",
             "|---|---|---|---|---|---|"]
    for task in args.tasks:
        name = names[task]
        _, options, n, horizon = TASK_CONFIGS[name]
        c = count(task, options, n, horizon)
        total = sum(c.values())
        share = {k: f"{c[k]} ({c[k] / total:.0%}, {c[k] / horizon:.0f} per step)" for k in ("dynamics GP", "policy GP", "glue")}
        lines.append(f"| {name} | {total} | {total / horizon:.0f} | {share['dynamics GP']} | {share['policy GP']} | {share['glue']} |")
        print(lines[-1], flush=True)
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
