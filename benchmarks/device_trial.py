"""One PILCO trial's computation on a CPU and on a GPU, side by side, from a real run's data.

Usage::

    python benchmarks/device_trial.py --data benchmarks/data/gp_double-pendulum_50ec8b95_t20.npz \\
        --task double-pendulum --set horizon=60 --devices cpu cuda [cuda+compile] [--threads 1] [--profile] \\
        [--out results/benchmarks/device_trial_double-pendulum.md]

The data file (``benchmarks/compare_gp_fit.py --extract``) holds a stored run's transitions up to
a trial, its GP warm start and GP settings. Per device (``cpu`` with ``--threads`` torch threads;
``cuda``), the script does what the ``pilco`` learner does between two rollouts of the system, in
the same order and with the task preset's budgets:

1. the dynamics-model fit (:meth:`GPModel.fit`, warm-started from the file);
2. the policy search from the preset's fresh controller (:func:`optimise_policy`, the preset's
   L-BFGS iteration and evaluation caps), on the model the fit returned;
3. the checks that end a trial: the predicted costs and ``J_sampled`` (500 particles).

Reported per device: wall seconds of each stage and their sum (a trial's computation; the system
rollout and plotting are CPU work of a few seconds either way), evaluations, and the median wall
milliseconds of one J + dJ at the fresh controller (3 warm-ups, ``--repeats`` timed; on a GPU each
timed call ends with the transfer of J and dJ to the host, so the wall is the real latency).
Exactness: J and dJ of the CPU and GPU objectives built on one and the same posterior, at the same
theta, relative differences (the issue's bounds: J 1e-10, dJ 1e-7). On the GPU the objective
replays J + dJ as a CUDA graph (the learner's default, ``cuda_graph``). ``--profile`` adds the
GPU's top kernels and the count of host-device synchronisations in one J + dJ launched without a graph. ``--task-objectives`` adds
J + dJ on both devices at the sizes of ``benchmarks/task_objectives.py`` (and cart-pole n=300), with
their agreement. ``--search-evaluations N`` caps the policy search below the preset (smoke runs).

``cuda+compile`` is ``cuda`` with the learner's ``compile_step`` (each rollout step as ``torch.compile``'d
code, then replayed in the CUDA graph); its first J + dJ includes the compilation, reported apart. With it
among the devices, ``--task-objectives`` adds the compiled objective's columns and the kernels one J + dJ
launches with and without it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(device: torch.device, f, *args, **kwargs):
    _sync(device)
    t0 = time.perf_counter()
    out = f(*args, **kwargs)
    _sync(device)
    return out, time.perf_counter() - t0


def build(task_name: str, task_options: dict[str, str], device: str, seed: int):
    """The task and a ``pilco`` learner on it (``device``: ``cpu``, ``cuda`` or ``cuda+compile``)."""
    from harness.discovery import load_task
    from plugins.pilco.learner import Pilco

    task = load_task(task_name)(**task_options)
    name, _, extra = device.partition("+")
    learner = Pilco(task.spec, {"device": name, "kernel": "auto" if name == "cpu" else "torch",
                                "compile_step": extra == "compile"}, seed)
    return task, learner


def objective_for(learner, posterior, controller):
    """The learner's own planning objective (width, mean_only, planning noise, kernel, device), one CPU thread."""
    return learner.planning_objective(controller, posterior, threads=1)


def time_objective(objective, repeats: int, first: list | None = None) -> float:
    """Median wall ms of one J + dJ (3 warm-ups); ``value_and_grad`` ends with the host copy of J and dJ.
    ``first``: gets the first warm-up's wall seconds appended (compilation, graph capture)."""
    theta = objective.get_flat()
    t0 = time.perf_counter()
    objective(theta)
    if first is not None:
        first.append(time.perf_counter() - t0)
    for _ in range(2):
        objective(theta)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        objective(theta)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def one_trial(args, device: str) -> dict:
    """GP fit, policy search, end-of-trial checks on ``device``; the fitted posterior (on the CPU) too."""
    from plugins.pilco.gp import GPHyperparameters, GPModel
    from plugins.pilco.policy_search import optimise_policy
    from plugins.pilco.sampling import sampled_costs

    data = np.load(args.data)
    settings = json.loads(str(data["settings"]))
    _, learner = build(args.task, args.task_options, device, args.seed)
    dev = learner.device
    torch.set_num_threads(args.threads)
    warm = GPHyperparameters(*(torch.tensor(data[k]) for k in ("log_ell", "log_alpha", "log_sigma", "pseudo_inputs")))
    model = GPModel(device=dev, sparse_threshold=settings["sparse_threshold"], num_pseudo=settings["num_pseudo"],
                    max_evals_full=settings["gp_max_evals"], max_evals_fitc=settings["gp_fitc_evals"],
                    hyper_subset=settings["gp_hyper_subset"], refresh_pseudo=settings["gp_refresh_pseudo"])
    report, gp_s = _timed(dev, model.fit, data["x"], data["y"], warm_start=warm, seed=settings["seed"])
    posterior = model.posterior()
    controller = learner.new_controller(torch.Generator().manual_seed(args.seed))
    objective = objective_for(learner, posterior, controller)
    first: list[float] = []
    per_eval_ms = time_objective(objective, args.repeats, first)
    preset = learner.preset
    cap = args.search_evaluations or preset.policy_max_evaluations
    search, search_s = _timed(dev, optimise_policy, objective, preset.policy_max_iterations, cap)
    _, predicted_s = _timed(dev, objective.predicted_costs)
    sampled, sampled_s = _timed(dev, sampled_costs, objective, 500, seed=1)
    return dict(device=device, gp_s=gp_s, gp_evaluations=report.evaluations, gp_nll=report.nll, per_eval_ms=per_eval_ms,
                search_s=search_s, evaluations=search.evaluations, J_after=float(search.J_after),
                checks_s=predicted_s + sampled_s, J_sampled=float(sampled.sum()),
                total_s=gp_s + search_s + predicted_s + sampled_s, posterior=posterior.detach().to("cpu"), first_s=first[0],
                graph=("not used" if dev.type == "cpu" else "replayed" if objective.graph_error is None
                       else f"capture failed ({objective.graph_error})"))


def agreement(args, posterior, gpu: str = "cuda") -> tuple[float, float, float]:
    """J (CPU), and the relative differences of J and dJ between a CPU and a GPU objective on ``posterior``."""
    values = []
    for device in ("cpu", gpu):
        _, learner = build(args.task, args.task_options, device, args.seed)
        controller = learner.new_controller(torch.Generator().manual_seed(args.seed))
        objective = objective_for(learner, posterior.to(learner.device), controller)
        values.append(objective(objective.get_flat()))
    (J_c, g_c), (J_g, g_g) = values
    return J_c, abs(J_g - J_c) / abs(J_c), float(np.linalg.norm(g_g - g_c) / np.linalg.norm(g_c))


def profile(args, posterior) -> list[str]:
    """The GPU's top kernels in one J + dJ launched operation by operation (no CUDA graph) and the
    host-device synchronisations it makes."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    _, learner = build(args.task, args.task_options, "cuda", args.seed)
    controller = learner.new_controller(torch.Generator().manual_seed(args.seed))
    objective = objective_for(learner, posterior.to(learner.device), controller)
    objective.cuda_graph = False
    theta = objective.get_flat()
    objective(theta)
    with torch_profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        objective(theta)
        torch.cuda.synchronize()
    events = prof.key_averages()
    launches = _launches(events)
    syncs = sum(e.count for e in events if "Synchronize" in e.key or e.key in ("cudaMemcpyAsync", "cudaMemcpy"))
    gpu_total = sum(getattr(e, "self_device_time_total", getattr(e, "self_cuda_time_total", 0)) for e in events) / 1e3
    lines = [f"One J + dJ on the GPU, every operation launched (no graph), under the profiler: {launches} kernel launches, {syncs} host-device copies or "
             f"synchronisations, {gpu_total:.1f} ms of kernel time.", "",
             "| operator | calls | self GPU ms | self CPU ms |", "|---|---|---|---|"]
    key = "self_device_time_total" if hasattr(events[0], "self_device_time_total") else "self_cuda_time_total"
    for e in sorted(events, key=lambda e: -getattr(e, key))[:15]:
        lines.append(f"| `{e.key[:60]}` | {e.count} | {getattr(e, key) / 1e3:.2f} | {e.self_cpu_time_total / 1e3:.2f} |")
    return lines


#: the profiler's names of a kernel launch (runtime and driver API; Triton's kernels come through the driver's)
LAUNCH_EVENTS = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx")


def _launches(events) -> int:
    """Kernel launches among a profile's ``key_averages()``."""
    return sum(e.count for e in events if e.key in LAUNCH_EVENTS)


def kernel_launches(objective) -> int:
    """Kernels one J + dJ of ``objective`` launches (run without its CUDA graph, under the profiler)."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    graph, objective.cuda_graph = objective.cuda_graph, False
    theta = objective.get_flat()
    objective(theta)
    with torch_profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        objective(theta)
        torch.cuda.synchronize()
    objective.cuda_graph = graph
    return _launches(prof.key_averages())


def compiled_columns(make, plain, theta, J_c, g_c, repeats: int) -> list[str]:
    """The ``compile_step`` objective's cells for :func:`task_objectives`: first J + dJ s (compiling, capturing),
    ms replayed, kernels launched by ``plain`` (the uncompiled objective, no graph) / compiled, J and dJ against
    the CPU's ``J_c``, ``g_c``; ``make(compile_step, cuda_graph)`` builds the GPU objective."""
    compiled = make(True, True)
    first: list[float] = []
    t = time_objective(compiled, repeats, first)
    J_k, g_k = compiled(theta)
    graph = f"{t:.2f}" if compiled.graph_error is None else f"capture failed: {compiled.graph_error[:60]}"
    launches = f"{kernel_launches(plain)} / {kernel_launches(make(True, False))}"
    return [f"{first[0]:.1f}", graph, launches, f"{abs(J_k - J_c) / abs(J_c):.1e}",
            f"{np.linalg.norm(g_k - g_c) / np.linalg.norm(g_c):.1e}"]


def task_objectives(repeats: int, compiled: bool = False) -> list[str]:
    """J + dJ wall ms on the CPU (this process's threads) and the GPU (every operation launched, and
    replayed as a CUDA graph) at the real tasks' sizes, and the GPU's agreement with the CPU;
    ``compiled``: the ``compile_step`` objective's columns too (:func:`compiled_columns`)."""
    import copy

    from benchmarks.task_objectives import TASK_CONFIGS, task_objective
    from plugins.pilco.objective import PolicyObjective

    configs = {"cartpole n=300 H=40": ("cartpole", {}, 300, 40), **TASK_CONFIGS}
    head = "| objective | CPU ms | GPU ms, eager | GPU ms, CUDA graph | CPU / graph | J rel. difference | dJ rel. difference |"
    if compiled:
        head += (" compile_step: first J + dJ s | compiled, CUDA graph ms | kernels per J + dJ, uncompiled / compiled |"
                 " J rel. difference | dJ rel. difference |")
    lines = ["", "J + dJ at the real tasks' sizes (`benchmarks/task_objectives.py`), CPU and GPU:", "", head,
             "|" + "---|" * (head.count("|") - 1)]
    for name, (task, options, n, horizon) in configs.items():
        cpu = task_objective(task, options, n, horizon)

        def make(compile_step: bool, graph: bool):
            return PolicyObjective(copy.deepcopy(cpu.controller), cpu.posterior, cpu.layout, cpu.cost.cost, cpu.init_mean.numpy(),
                                   cpu.init_cov.numpy(), cpu.horizon, cpu.mean_only, cpu.cost.width, kernel="torch", device="cuda",
                                   cuda_graph=graph, compile_step=compile_step)

        gpus = [make(False, graph) for graph in (False, True)]
        theta = cpu.get_flat()
        J_c, g_c = cpu(theta)
        J_g, g_g = gpus[1](theta)
        t_cpu, t_eager, t_graph = (time_objective(o, repeats) for o in (cpu, *gpus))
        graph = f"{t_graph:.2f}" if gpus[1].graph_error is None else f"capture failed: {gpus[1].graph_error[:80]}"
        cells = [name, f"{t_cpu:.1f}", f"{t_eager:.1f}", graph, f"{t_cpu / t_graph:.0f}x", f"{abs(J_g - J_c) / abs(J_c):.1e}",
                 f"{np.linalg.norm(g_g - g_c) / np.linalg.norm(g_c):.1e}"]
        if compiled:
            cells += compiled_columns(make, gpus[0], theta, J_c, g_c, repeats)
        lines.append("| " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="a .npz written by benchmarks/compare_gp_fit.py --extract")
    parser.add_argument("--task", required=True)
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE", help="task option")
    parser.add_argument("--devices", nargs="+", default=["cpu", "cuda"], choices=["cpu", "cuda", "cuda+compile"])
    parser.add_argument("--threads", type=int, default=1, help="torch threads on the CPU side")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0, help="the fresh controller's seed")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--task-objectives", action="store_true")
    parser.add_argument("--search-evaluations", type=int, default=None, help="cap on J + dJ evaluations (default: preset)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    args.task_options = dict(s.split("=", 1) for s in args.sets)
    if any(d.startswith("cuda") for d in args.devices) and not torch.cuda.is_available():
        parser.error("--devices cuda: torch sees no CUDA GPU here (leave cuda out)")
    load = load_average()
    rows = []
    for device in args.devices:
        rows.append(one_trial(args, device))
        r = rows[-1]
        print(f"{device}: GP {r['gp_s']:.1f} s, search {r['search_s']:.1f} s ({r['evaluations']} evals), J+dJ {r['per_eval_ms']:.1f} ms, "
              f"checks {r['checks_s']:.1f} s, total {r['total_s']:.1f} s", flush=True)
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    lines = ["# One PILCO trial's computation, CPU and GPU side by side", "",
             f"Command: `{command_line(__file__, argv)}`  ",
             f"{machine_line(load)} GPU: {gpu}.  ",
             f"Data: `{Path(args.data).name}` ({json.loads(str(np.load(args.data)['settings']))['source']}); "
             f"task `{args.task}` {args.task_options}; CPU side: {args.threads} torch thread(s).", "",
             "| device | GP fit s (evals) | J + dJ ms | first J + dJ s | policy search s (evals) | J after | checks s | trial computation s |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['device']} | {r['gp_s']:.1f} ({r['gp_evaluations']}) | {r['per_eval_ms']:.1f} | {r['first_s']:.1f} | "
                     f"{r['search_s']:.1f} ({r['evaluations']}) | {r['J_after']:.4f} | {r['checks_s']:.2f} | {r['total_s']:.1f} |")
    lines += [f"J + dJ on the GPU ({r['device']}): {r['graph']} as a CUDA graph." for r in rows if r["device"] != "cpu"]
    lines += ["First J + dJ: the first of the warm-ups before the search (not in the J + dJ column, nor in the trial's "
              "seconds): the CUDA graph's capture and, with compile_step, torch.compile's build of the step (made once per "
              "process and GP size; in a run it is the first trial's first evaluation)."]
    if [r["device"] for r in rows] == ["cpu", "cuda"]:
        c, g = rows
        lines += ["", f"GPU / CPU speed-up: GP fit {c['gp_s'] / g['gp_s']:.1f}x, J + dJ {c['per_eval_ms'] / g['per_eval_ms']:.1f}x, "
                      f"trial computation {c['total_s'] / g['total_s']:.1f}x. GP NLL cpu {c['gp_nll']:.4f}, cuda {g['gp_nll']:.4f} "
                      "(two fits that round differently part after some L-BFGS steps)."]
    gpus = [d for d in args.devices if d != "cpu"]
    for gpu in gpus:
        J, dJ_rel, dg_rel = agreement(args, rows[0]["posterior"], gpu)
        lines += ["", f"Exactness, CPU vs GPU ({gpu}) objective on the same posterior and theta: J = {J:.12g}, relative difference "
                      f"{dJ_rel:.2e} (bound 1e-10); dJ relative difference {dg_rel:.2e} (bound 1e-7)."]
    if gpus:
        if args.profile:
            lines += [""] + profile(args, rows[0]["posterior"])
            print("\n".join(lines[-18:]), flush=True)
        if args.task_objectives:
            lines += task_objectives(args.repeats, compiled="cuda+compile" in args.devices)
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
