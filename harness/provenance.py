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
