"""benchmarks/device_run.py: a run without a store, stopped after its first trial and continued from the
checkpoint it copied out, makes the same trials as the run left alone."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ARGS = ["--learner", "pilco", "--task", "cartpole", "--seed", "3", "--set", "learner.policy_max_evaluations=5",
        "--set", "learner.num_centres=5", "--max-trials", "3"]


def _run(extra: list[str], stop_after_first: bool = False) -> subprocess.CompletedProcess | int:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    command = [sys.executable, str(ROOT / "benchmarks" / "device_run.py"), *ARGS, *extra]
    if not stop_after_first:
        return subprocess.run(command, env=env, capture_output=True, text=True, timeout=300, check=True)
    with subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as process:
        for line in process.stdout:
            if "trial 1/3" in line:
                process.send_signal(signal.SIGUSR1)  # stop once the trial in progress is done
        return process.wait(timeout=300)


def _rows(path: Path) -> dict[int, dict]:
    return {int(r["trial"]): r for r in json.loads(path.read_text())}


@pytest.mark.skipif(not hasattr(signal, "SIGUSR1"), reason="needs SIGUSR1")
def test_resume_from_copied_checkpoint(tmp_path):
    _run(["--out", str(tmp_path / "whole.md")])
    whole = _rows(tmp_path / "whole.json")
    assert sorted(whole) == [1, 2, 3] and all(r["trial_wall_seconds"] > 0 for r in whole.values())

    _run(["--out", str(tmp_path / "first.md")], stop_after_first=True)
    first = _rows(tmp_path / "first.json")
    stopped_after = max(first)
    assert stopped_after < 3 and (tmp_path / "first.ckpt").is_file()
    last_line = (tmp_path / "first.md").read_text().strip().splitlines()[-1]
    assert "in progress" not in last_line and "SIGUSR1" in last_line and "first.ckpt" in last_line, last_line

    done = _run(["--out", str(tmp_path / "rest.md"), "--resume-checkpoint", str(tmp_path / "first.ckpt")])
    rest = _rows(tmp_path / "rest.json")
    assert sorted(rest) == list(range(stopped_after + 1, 4)), done.stdout
    assert f"after trial {stopped_after} (not re-run)" in (tmp_path / "rest.md").read_text()
    for trial, row in rest.items():  # the continuation is the uninterrupted run's
        assert row["eval_cost"] == pytest.approx(whole[trial]["eval_cost"], rel=1e-9)
        assert row["J_after"] == pytest.approx(whole[trial]["J_after"], rel=1e-9)
        assert 0 < row["trial_wall_seconds"] < row["wall_seconds"]


def test_missing_checkpoint_is_one_line(tmp_path):
    command = [sys.executable, str(ROOT / "benchmarks" / "device_run.py"), *ARGS, "--out", str(tmp_path / "x.md"),
               "--resume-checkpoint", str(tmp_path / "none.ckpt")]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert result.stderr.strip().splitlines()[-1].startswith("error: no checkpoint file")
