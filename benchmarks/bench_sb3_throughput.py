"""Environment steps per second of our tasks inside stable-baselines3 (SAC and PPO), one torch thread.

For each (learner, task, configuration) the learner's own model is built on the interaction's
``as_env()`` view (sin/cos features, actions in [-1, 1]) and ``model.learn`` is timed for a
fixed number of counted steps after a warm-up chunk (imports, first updates). The raw step rate
of each task's environment (zero action, no SB3) is measured too. No evaluation episodes run.

    .venv/bin/python benchmarks/bench_sb3_throughput.py --out results/benchmarks/sb3_throughput.md
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402
from harness.discovery import load_task  # noqa: E402
from harness.interaction import Interaction  # noqa: E402
from plugins.sb3_learners import PPOLearner, SACLearner, make_agent_env  # noqa: E402

#: (learner class, task, options, timed steps); the SAC rows compare batching and net width
CASES = [
    (SACLearner, "cartpole", {"train_freq": 1, "gradient_steps": 1}, 480),
    (SACLearner, "cartpole", {"train_freq": 8, "gradient_steps": 8}, 480),
    (SACLearner, "cartpole", {}, 480),
    (SACLearner, "cartpole", {"net_width": 64}, 480),
    (SACLearner, "dmc-cartpole", {}, 500),
    (SACLearner, "double-pendulum", {}, 500),
    (SACLearner, "unicycle", {}, 536),
    (PPOLearner, "cartpole", {}, 2560),
    (PPOLearner, "dmc-cartpole", {}, 3200),
    (PPOLearner, "double-pendulum", {}, 3200),
    (PPOLearner, "unicycle", {}, 2144),
]


def raw_env_rate(task_name: str, seconds: float = 2.0) -> tuple[float, float]:
    """Steps per wall second and per CPU second of the task's env alone (zero action)."""
    task = load_task(task_name)()
    env = task.make_env()
    env.reset(seed=0)
    zero = np.zeros(task.spec.action_dim)
    n, start, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - start < seconds:
        _, _, terminated, truncated, _ = env.step(zero)
        n += 1
        if terminated or truncated:
            env.reset()
    rates = n / (time.perf_counter() - start), n / (time.process_time() - cpu)
    env.close()
    return rates


def sb3_rate(learner_cls, task_name: str, options: dict, steps: int) -> tuple[float, float, dict]:
    """Counted steps per wall second and per CPU second of this process (robust to other jobs on
    the shared cores) of ``model.learn(steps)``, after a warm-up chunk past ``learning_starts``."""
    import torch

    torch.set_num_threads(1)
    task = load_task(task_name)()
    learner = learner_cls(task.spec, options, seed=0)
    hp = learner.hyperparameters()
    interaction = Interaction(task.make_env(), task.spec, seed=0)
    model = learner.build_model(make_agent_env(interaction.as_env(), task.spec), hp)
    warm = int(hp.get("learning_starts", 0)) + int(hp.get("n_steps", 0)) + 2 * task.spec.horizon
    model.learn(warm, reset_num_timesteps=False, log_interval=None)
    before, start, cpu = interaction.steps, time.perf_counter(), time.process_time()
    model.learn(steps, reset_num_timesteps=False, log_interval=None)
    done = interaction.steps - before
    rate, cpu_rate = done / (time.perf_counter() - start), done / (time.process_time() - cpu)
    interaction.close()
    return rate, cpu_rate, hp


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=None, help="write a markdown table here")
    parser.add_argument("--quick", action="store_true", help="only cart-pole rows")
    args = parser.parse_args()

    cases = [c for c in CASES if not args.quick or c[1] == "cartpole"]
    tasks = sorted({c[1] for c in cases})
    load_at_start = load_average()
    lines = [
        "## Raw environment (zero action, no learner)",
        "",
        "| task | steps per wall s | steps per CPU s |",
        "|---|---|---|",
    ]
    for name in tasks:
        rate, cpu_rate = raw_env_rate(name)
        print(f"raw {name}: {rate:.0f} steps/s wall, {cpu_rate:.0f} per CPU s", flush=True)
        lines.append(f"| {name} | {rate:,.0f} | {cpu_rate:,.0f} |")
    lines += ["", "## Inside SB3 `model.learn` (counted interaction steps per second)", "",
              "Per CPU second of this process is the comparable figure (other jobs share the cores and change",
              "the wall rate from minute to minute); per wall second is what a run experienced.", "",
              "| learner | task | options | net | training schedule | timed steps | steps per wall s | steps per CPU s |",
              "|---|---|---|---|---|---|---|---|"]
    for learner_cls, task_name, options, steps in cases:
        rate, cpu_rate, hp = sb3_rate(learner_cls, task_name, options, steps)
        net = f"{hp['net_width']}x{hp['net_layers']}"
        if "train_freq" in hp:
            sched = "episode / as many" if hp["train_freq"] == 0 else f"{hp['train_freq']} / {hp['gradient_steps']}"
        else:
            sched = f"n_steps {hp['n_steps']}, batch {hp['batch_size']}"
        opts = " ".join(f"{k}={v}" for k, v in options.items()) or "(preset)"
        print(f"{learner_cls.name} {task_name} {opts}: {rate:.1f} steps/s wall, {cpu_rate:.1f} per CPU s", flush=True)
        lines.append(f"| {learner_cls.name} | {task_name} | {opts} | {net} | {sched} | {steps} | {rate:,.1f} | {cpu_rate:,.1f} |")
    header = ["# Environment steps per second inside stable-baselines3", "", f"Command: `{command_line(__file__)}`  ",
              f"{machine_line(load_at_start)} One torch thread; a single run per row.", ""]
    write_report(header + lines, args.out)


if __name__ == "__main__":
    main()
