"""The fast stepping paths reproduce the old ones: same seeds and actions, same observations and rewards.

``data/env_trajectories.npz`` was recorded with the code of commit ``fa0d849`` (generic
``rk4_zoh`` on the tasks' right-hand sides; dm_control's ``Environment.step``) by
``data/record_env_trajectories.py``; the same script's rollout runs here on the current code.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).with_name("data")
_spec = importlib.util.spec_from_file_location("record_env_trajectories", DATA / "record_env_trajectories.py")
recorder = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(recorder)

FIXTURE = np.load(DATA / "env_trajectories.npz")

#: max-abs tolerance on observations/states against the old code: none, the floats are equal
TOLERANCE = {"cartpole": 0.0, "double-pendulum": 0.0, "unicycle": 0.0, "dmc-cartpole": 0.0}
#: rewards (in [-1, 0]) may differ in the last bit: the cost's sin/cos/exp and its small matrix
#: products go through numpy/BLAS kernels chosen per CPU (on an AMD EPYC without AVX-512 the
#: unicycle's recorded rewards differ by 1.1e-16 at 7 of 200 steps, its states not at all)
REWARD_ULPS = 4 * np.finfo(np.float64).eps


@pytest.mark.parametrize("name", list(recorder.TASKS))
def test_rollout_reproduces_the_recording_of_the_old_code(name):
    module, cls, options = recorder.TASKS[name]
    if name == "dmc-cartpole":
        pytest.importorskip("dm_control")
    task = getattr(importlib.import_module(module), cls)(**options)
    new = recorder.rollout(task)
    old = {key.split("/", 1)[1]: FIXTURE[key] for key in FIXTURE.files if key.startswith(name + "/")}
    np.testing.assert_array_equal(new["actions"], old["actions"])
    for flag in ("terminated", "truncated"):
        np.testing.assert_array_equal(new[flag], old[flag], err_msg=flag)
    for key in ("obs", "state", "reset_obs"):
        np.testing.assert_allclose(new[key], old[key], rtol=0.0, atol=TOLERANCE[name], err_msg=key)
    np.testing.assert_allclose(new["reward"], old["reward"], rtol=0.0, atol=max(TOLERANCE[name], REWARD_ULPS), err_msg="reward")
    np.testing.assert_allclose(new["dmc_reward"], old["dmc_reward"], rtol=0.0, atol=1e-12, equal_nan=True)
