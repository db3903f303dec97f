"""Where a run came from: git commit of the harness and versions of the packages that matter."""

from __future__ import annotations

import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

#: packages whose versions are recorded with every run
TRACKED_PACKAGES = ("pilco-harness", "torch", "numpy", "scipy", "gymnasium", "mlflow", "stable-baselines3", "dm-control", "mujoco")


#: changes under these top-level folders do not make the source "dirty" (the committed results
#: store is written by the runs themselves)
NOT_SOURCE = ("results/",)


def git_sha(directory: Path | None = None) -> str:
    """Commit of the harness source tree (``+dirty`` if it has uncommitted changes outside
    :data:`NOT_SOURCE`), or ``unknown``."""
    where = directory or Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=5, check=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=where, capture_output=True, text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    changed = [line[3:] for line in status.splitlines() if line.strip()]  # "XY path"
    return sha + ("+dirty" if any(not path.startswith(NOT_SOURCE) for path in changed) else "")


def package_versions() -> dict[str, str]:
    """``{package: version}`` for the installed packages among :data:`TRACKED_PACKAGES`."""
    out = {}
    for name in TRACKED_PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out


#: run tag naming the process that logs into the run (:func:`process_token`), set when the run is
#: started or resumed; lets a report tell a live RUNNING run from one whose process died unmarked
PROCESS_TAG = "harness.process"


def _start_ticks(pid: int) -> str | None:
    """Start time of process ``pid`` in clock ticks since boot (Linux ``/proc``), or ``None``."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) ": field 3 (state) onwards
    return fields[19] if len(fields) > 19 else None  # field 22: starttime


def process_token(pid: int | None = None) -> str:
    """``host:pid:start`` naming process ``pid`` (default: this one) for as long as it lives: a
    later process that reuses the pid has another start time. ``start`` is empty without ``/proc``."""
    import os
    import socket

    pid = os.getpid() if pid is None else pid
    return f"{socket.gethostname()}:{pid}:{_start_ticks(pid) or ''}"


def process_alive(token: str) -> bool | None:
    """Whether the process ``token`` (:func:`process_token`) names still runs; ``None`` when this
    machine cannot tell (another host, no ``/proc``, a token without a start time or malformed)."""
    import socket

    try:
        host, pid, start = token.rsplit(":", 2)
        pid_number = int(pid)
    except ValueError:
        return None
    if host != socket.gethostname() or not start or not Path("/proc/self/stat").exists():
        return None
    return _start_ticks(pid_number) == start
