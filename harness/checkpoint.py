"""Per-trial checkpoints: everything needed to continue a run exactly where it stopped.

A checkpoint is written after every hand-over (once the evaluation is logged), atomically, and
attached to the run as ``checkpoints/ckpt_trialNNN.ckpt``. It holds the run configuration, the
trial history, the interaction (episodes, counters, environment RNG state), the learner's state
and the global RNG states (Python's ``random``, NumPy's, torch's), as plain data in the data-only
format of :mod:`harness.datafile`: reading a checkpoint runs no code from it, and its SHA-256
detects a file cut short by a crash, which is then skipped in favour of the previous one.
Checkpoints of older harness versions (pickles, ``.pkl``) are refused with the command that
converts them (:mod:`harness.migration`).
"""

from __future__ import annotations

import random
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness import datafile
from harness.datafile import DataFileError

#: version of the checkpoint's content (1: the pickled checkpoints of older harness versions)
FORMAT_VERSION = 2
KIND = "checkpoint"
PREFIX = "ckpt_trial"
_FIELDS = {"identity": dict, "trial": int, "history": list, "interaction": dict, "learner": dict, "rng": dict, "version": int}


@dataclass
class Checkpoint:
    """State of a run after ``trial`` hand-overs (every field plain data, :mod:`harness.datafile`).

    Attributes:
        identity: the resolved run definition (learner, task, seed, options, limits); a resume
            must match it exactly.
        trial: completed hand-overs.
        history: the per-trial records logged so far.
        interaction: :meth:`harness.interaction.Interaction.state_dict`.
        learner: the learner's ``state_dict()``.
        rng: Python, NumPy-global and torch-global RNG states (:func:`global_rng_state`).
    """

    identity: dict[str, Any]
    trial: int
    history: list[dict[str, float]]
    interaction: dict[str, Any]
    learner: dict[str, Any]
    rng: dict[str, Any] = field(default_factory=dict)
    version: int = FORMAT_VERSION


def checkpoint_name(trial: int) -> str:
    """The file name of trial ``trial``'s checkpoint, ``ckpt_trialNNN.ckpt``."""
    return f"{PREFIX}{trial:03d}{datafile.CHECKPOINT_SUFFIX}"


def global_rng_state() -> dict[str, Any]:
    """Python's ``random`` state ``(3, (625 ints), None)``, NumPy's global state ``('MT19937', (624,) uint32,
    pos, has_gauss, cached)`` and, where torch is loaded, torch's CPU generator state (a ``uint8`` tensor)."""
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
    """Write ``checkpoint`` to ``path`` atomically; returns ``path``.

    Raises :class:`~harness.datafile.NotPlainDataError` naming the entry that is not plain data.
    """
    tree = {name: getattr(checkpoint, name) for name in _FIELDS}
    return datafile.write(Path(path), KIND, tree)


def load_checkpoint(path: Path) -> Checkpoint:
    """Read and verify a checkpoint; a :class:`~harness.errors.CheckpointError` if it is missing, cut,
    foreign or changed (:class:`~harness.datafile.LegacyFormatError`: an older harness's pickle)."""
    path = Path(path)
    _, tree = datafile.read(path, KIND)
    if not isinstance(tree, dict) or set(tree) != set(_FIELDS):
        keys = sorted(tree) if isinstance(tree, dict) else type(tree).__name__
        raise DataFileError(f"checkpoint {path.name} holds {keys}, not a checkpoint's entries {sorted(_FIELDS)}: refused")
    wrong = [name for name, kind in _FIELDS.items() if not isinstance(tree[name], kind) or isinstance(tree[name], bool)]
    if wrong:
        raise DataFileError(f"checkpoint {path.name} has malformed entries ({', '.join(wrong)}): refused")
    if tree["version"] != FORMAT_VERSION:
        raise DataFileError(f"checkpoint {path.name} has version {tree['version']}; resume needs version {FORMAT_VERSION}")
    return Checkpoint(**tree)


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
