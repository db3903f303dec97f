"""Record the fixture ``env_trajectories.npz``: seeded random-action rollouts of every simulated task.

Usage (from the repository root)::

    python tests/tasks/data/record_env_trajectories.py

The committed fixture was recorded with the code of commit ``fa0d849`` (before the fused RK4
steppers and the direct MuJoCo stepping), so ``tests/tasks/test_env_trajectories.py`` checks
that the faster paths reproduce the old observations, rewards and flags from the same seeds and
actions. Each task: ``STEPS`` uniform random actions from ``default_rng(SEED)``, ``reset(seed=SEED)``
first, then ``reset()`` (no seed: the env's own stream continues) whenever an episode ends.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))

SEED = 3
STEPS = 200
#: task name -> (module, class, options); short horizons so that resets are part of the record.
TASKS = {
    "cartpole": ("tasks.cartpole", "CartPole", {"horizon": 40}),
    "double-pendulum": ("tasks.double_pendulum", "CartDoublePendulum", {"horizon": 50}),
    "unicycle": ("tasks.unicycle", "Unicycle", {"horizon": 30, "init": "paper"}),  # the recording's start (then the default)
    "dmc-cartpole": ("tasks.dmc_cartpole", "DMCCartpole", {"horizon": 60, "measurement_noise": 0.01}),
}


def rollout(task) -> dict[str, np.ndarray]:
    """``STEPS`` steps with resets; arrays: obs ``(STEPS, D)``, state ``(STEPS, D)``, reward, flags, resets' obs."""
    env = task.make_env()
    spec = task.spec
    rng = np.random.default_rng(SEED)
    actions = rng.uniform(spec.action_low, spec.action_high, size=(STEPS, spec.action_dim))
    obs0, _ = env.reset(seed=SEED)
    rec: dict[str, list] = {k: [] for k in ("obs", "state", "reward", "terminated", "truncated", "reset_obs", "dmc_reward")}
    rec["reset_obs"].append(obs0)
    for k in range(STEPS):
        obs, reward, terminated, truncated, info = env.step(actions[k])
        rec["obs"].append(obs)
        rec["state"].append(info["state"])
        rec["reward"].append(reward)
        rec["terminated"].append(terminated)
        rec["truncated"].append(truncated)
        rec["dmc_reward"].append(info.get("dmc_reward", np.nan))
        if terminated or truncated:
            rec["reset_obs"].append(env.reset()[0])
    out = {k: np.asarray(v) for k, v in rec.items()}
    out["actions"] = actions
    return out


def main() -> None:
    import importlib

    arrays = {}
    for name, (module, cls, options) in TASKS.items():
        task = getattr(importlib.import_module(module), cls)(**options)
        for key, value in rollout(task).items():
            arrays[f"{name}/{key}"] = value
        print(name, "resets:", len(arrays[f"{name}/reset_obs"]) - 1, "terminated:", int(arrays[f"{name}/terminated"].sum()))
    np.savez_compressed(Path(__file__).with_name("env_trajectories.npz"), **arrays)


if __name__ == "__main__":
    main()
