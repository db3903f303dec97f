"""Per-trial checkpoints: everything needed to continue a run exactly where it stopped.

A checkpoint is written after every hand-over (once the evaluation is logged), atomically
(temporary file + ``os.replace``), and attached to the run as ``checkpoints/ckpt_trialNNN.pkl``.
It holds the run configuration, the trial history, the interaction (episodes, counters,
environment RNG state), the learner's state and the global RNG states, with a SHA-256 of the
payload so that a file cut short by a crash is detected and skipped in favour of the previous one.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import random
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import CheckpointError

FORMAT_VERSION = 1
_MAGIC = b"HARNESS-CKPT\n"


@dataclass
class Checkpoint:
    """State of a run after ``trial`` hand-overs.

    Attributes:
        identity: the resolved run definition (learner, task, seed, options, limits); a resume
            must match it exactly.
        trial: completed hand-overs.
        history: the per-trial records logged so far.
        interaction: :meth:`harness.interaction.Interaction.state_dict`.
        learner: the learner's ``state_dict()``.
        rng: Python, NumPy-global and torch-global RNG states.
    """

    identity: dict[str, Any]
    trial: int
    history: list[dict[str, float]]
    interaction: dict[str, Any]
    learner: dict[str, Any]
    rng: dict[str, Any] = field(default_factory=dict)
    version: int = FORMAT_VERSION


def global_rng_state() -> dict[str, Any]:
    state: dict[str, Any] = {"python": random.getstate(), "numpy": np.random.get_state()}
    torch = sys.modules.get("torch")
    if torch is not None:
        state["torch"] = torch.get_rng_state()
    return state


def set_global_rng_state(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    if "torch" in state:
        import torch

        torch.set_rng_state(state["torch"])


def save_checkpoint(checkpoint: Checkpoint, path: Path) -> Path:
    """Write ``checkpoint`` to ``path`` atomically; returns ``path``."""
    path = Path(path)
    payload = pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL)
    digest = hashlib.sha256(payload).hexdigest().encode()
    fd, tmp = tempfile.mkstemp(prefix=".ckpt-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(_MAGIC + digest + b"\n" + payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: Path) -> Checkpoint:
    """Read and verify a checkpoint; :class:`CheckpointError` if it is missing, cut or foreign."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: {exc.strerror}") from exc
    if not blob.startswith(_MAGIC):
        raise CheckpointError(f"{path.name} is not a harness checkpoint")
    header_end = blob.index(b"\n", len(_MAGIC))
    digest, payload = blob[len(_MAGIC):header_end], blob[header_end + 1:]
    if hashlib.sha256(payload).hexdigest().encode() != digest:
        raise CheckpointError(f"checkpoint {path.name} is corrupt (checksum mismatch: written partially?)")
    try:
        checkpoint = pickle.loads(payload)
    except Exception as exc:
        raise CheckpointError(f"checkpoint {path.name} cannot be read ({type(exc).__name__}: {exc})") from exc
    if not isinstance(checkpoint, Checkpoint) or checkpoint.version != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path.name} has an unsupported format; resume needs format {FORMAT_VERSION}")
    return checkpoint


def identity_mismatch(saved: dict[str, Any], current: dict[str, Any], defaults: dict[str, Any] | None = None,
                      ignore: set[str] | None = None) -> str | None:
    """A one-line description of the first differences between two run identities, or ``None``.

    ``defaults``: the current options' defaults (identity keys); a key the checkpoint lacks whose
    current value is its default is an option added since the run started, not a difference.
    ``ignore``: keys that are no difference whatever their values (execution options, which older
    checkpoints hold in their identity).
    """
    defaults = defaults or {}
    added = {k for k in set(current) - set(saved) if k in defaults and current[k] == defaults[k]}
    keys = sorted((set(saved) | set(current)) - added - (ignore or set()))
    diffs = [f"{k}: checkpoint {saved.get(k)!r} vs now {current.get(k)!r}" for k in keys if saved.get(k) != current.get(k)]
    if not diffs:
        return None
    return "; ".join(diffs[:3]) + (f" (+{len(diffs) - 3} more)" if len(diffs) > 3 else "")
