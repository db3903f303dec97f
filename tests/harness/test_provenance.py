"""Provenance: the commit, and "+dirty" only for uncommitted source changes."""

from __future__ import annotations

import subprocess

from harness.provenance import git_sha


def _git(repo, *args):
    subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True)


def test_dirty_flag_ignores_the_results_store(tmp_path):
    _git(tmp_path, "init", "-q")
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "store.db").write_text("a")
    (tmp_path / "code.py").write_text("x = 1\n")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "init")
    sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True, text=True).stdout.strip()
    assert git_sha(tmp_path) == sha
    (tmp_path / "results" / "store.db").write_text("b")  # a run wrote to the committed store
    assert git_sha(tmp_path) == sha
    (tmp_path / "code.py").write_text("x = 2\n")
    assert git_sha(tmp_path) == sha + "+dirty"


def test_process_token_tells_a_live_process_from_a_dead_one_and_from_a_reused_pid():
    import os
    import socket

    from harness.provenance import process_alive, process_token

    mine = process_token()
    assert mine.startswith(f"{socket.gethostname()}:{os.getpid()}:") and process_alive(mine) is True
    child = subprocess.Popen(["sleep", "0.01"])
    token = process_token(child.pid)
    child.wait()
    assert process_alive(token) is False  # exited (and reaped)
    host, pid, start = mine.rsplit(":", 2)
    assert process_alive(f"{host}:{pid}:{int(start) + 1}") is False  # same pid, another start: a reused pid
    assert process_alive(f"another-host-{host}:{pid}:{start}") is None and process_alive("garbage") is None


def test_tracked_runs_name_their_process_on_start_and_resume(tmp_path):
    from harness.provenance import PROCESS_TAG, process_token
    from harness.tracking import MlflowTracker

    tracker = MlflowTracker(f"sqlite:///{tmp_path / 'mlflow.db'}")
    run_id = tracker.start("exp", "run", {"a": 1}, {})
    assert tracker.client.get_run(run_id).data.tags[PROCESS_TAG] == process_token()
    tracker.client.set_tag(run_id, PROCESS_TAG, "elsewhere:1:1")
    MlflowTracker(tracker.tracking_uri).resume(run_id)
    assert tracker.client.get_run(run_id).data.tags[PROCESS_TAG] == process_token()
