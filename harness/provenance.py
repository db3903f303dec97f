"""Where a run came from: git commit of the harness and versions of the packages that matter."""

from __future__ import annotations

import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

#: packages whose versions are recorded with every run
TRACKED_PACKAGES = ("pilco-harness", "torch", "numpy", "scipy", "gymnasium", "mlflow", "stable-baselines3", "dm-control", "mujoco")


def git_sha(directory: Path | None = None) -> str:
    """Commit of the harness source tree (``+dirty`` if it has uncommitted changes), or ``unknown``."""
    where = directory or Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=where, capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + ("+dirty" if dirty else "")


def package_versions() -> dict[str, str]:
    """``{package: version}`` for the installed packages among :data:`TRACKED_PACKAGES`."""
    out = {}
    for name in TRACKED_PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out
