"""One-way conversion of a run's files from the older, pickled formats (``harness store migrate``).

Older harness versions stored, per run, checkpoints ``checkpoints/ckpt_trialNNN.pkl`` (a pickled
:class:`~harness.checkpoint.Checkpoint` behind a SHA-256 header), policies
``policies/policy_trialNNN.pkl`` (pickles; SB3 learners: SB3's ``.zip``, whose metadata is
cloudpickled) and, for PILCO, GP files ``trialNNN/model_trialNNN.pt`` holding pickled objects.
Reading any of them runs code that whoever wrote the file chose, so the harness refuses them
(:class:`~harness.datafile.LegacyFormatError`). :func:`migrate_run` reads each such file of a run
**once, on the user's explicit request**, and writes its data-only equivalent to the run:
``ckpt_trialNNN.ckpt`` and ``policy_trialNNN.policy`` beside the old files (MLflow cannot delete
artifacts; where a trial has both, the harness reads the new one and never the old), the ``.pt``
files replaced in place by tensors and plain values (``torch.load(weights_only=True)`` reads them).
A converted file is not converted again.
"""

from __future__ import annotations

import dataclasses
import hashlib
import pickle
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from harness import datafile
from harness.checkpoint import PREFIX as CHECKPOINT_PREFIX
from harness.checkpoint import Checkpoint, checkpoint_name, save_checkpoint
from harness.datafile import DataFileError
from harness.learner import POLICY_PREFIX

#: what an older harness wrote in front of a pickled checkpoint
_OLD_MAGIC = b"HARNESS-CKPT\n"
#: the warning shown before anything is read
WARNING = ("reading files in the old pickled format runs code stored in them: convert only runs of a store you trust "
           "(written by your own harness runs)")


def to_plain(value: Any) -> Any:
    """``value`` with every dataclass instance replaced by the dict of its fields, recursively (what the
    learners' and the interaction's states hold now instead of objects, e.g. episodes, GP hyperparameters)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: to_plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [to_plain(v) for v in value]
    if isinstance(value, tuple):
        return tuple(to_plain(v) for v in value)
    return value


def read_legacy_checkpoint(path: Path) -> Checkpoint:
    """An older harness's checkpoint, as a checkpoint of this format. **Runs code from the file** (a pickle)."""
    blob = Path(path).read_bytes()
    if not blob.startswith(_OLD_MAGIC):
        raise DataFileError(f"{Path(path).name} is not a checkpoint of an older harness (no HARNESS-CKPT header): not converted")
    header_end = blob.index(b"\n", len(_OLD_MAGIC))
    digest, payload = blob[len(_OLD_MAGIC):header_end], blob[header_end + 1:]
    if hashlib.sha256(payload).hexdigest().encode() != digest:
        raise DataFileError(f"checkpoint {Path(path).name} is corrupt (checksum mismatch: written partially?): not converted")
    old = pickle.loads(payload)
    if not isinstance(old, Checkpoint) or old.version != 1:
        raise DataFileError(f"{Path(path).name} holds a {type(old).__name__}, not an older harness's checkpoint: not converted")
    return Checkpoint(dict(old.identity), int(old.trial), to_plain(old.history), to_plain(old.interaction), to_plain(old.learner),
                      to_plain(old.rng))


def convert_model_file(path: Path) -> bool:
    """Rewrite a torch file that ``torch.load(weights_only=True)`` refuses with its objects as plain data
    (dataclasses as dicts); ``False`` if it already loads. **Runs code from the file** when it converts."""
    import torch

    try:
        torch.load(path, weights_only=True)
        return False
    except pickle.UnpicklingError:
        pass
    torch.save(to_plain(torch.load(path, weights_only=False)), path)
    torch.load(path, weights_only=True)  # what readers do: it must pass now
    return True


def legacy_files(names: list[str]) -> list[str]:
    """The artifact names (of one run) in an older format that have no converted counterpart yet,
    checkpoints and policies (``.pt`` files are judged by their content: :func:`convert_model_file`)."""
    return [name for prefix in (CHECKPOINT_PREFIX, POLICY_PREFIX)
            for name in datafile.trial_files(names, prefix).values() if datafile.is_legacy(name)]


def migrate_run(store: Any, run_id: str, say: Callable[[str], None] = print) -> list[str]:
    """Convert every file of run ``run_id`` of ``store`` (a :class:`harness.store.Store`) in an older,
    pickled format (see the module docstring); returns the artifact names written. **Runs code from
    those files**: only on the user's explicit request."""
    from harness.discovery import load_learner, load_task
    from harness.testrun import task_options

    run = store.run(run_id)
    params = run.params
    names = [a.path for folder in ("checkpoints", "policies") for a in run.artifacts(folder)]
    models = [a.path for top in run.artifacts() if top.is_dir and top.path.startswith("trial")
              for a in run.artifacts(top.path) if a.path.endswith(".pt")]
    written: list[str] = []
    with tempfile.TemporaryDirectory(prefix="harness-migrate-") as tmp:
        work = Path(tmp)
        for sub in ("old", "new", "models"):
            (work / sub).mkdir()
        spec = None
        for name in legacy_files(names):
            local = run.copy(name, work / "old" / Path(name).name)
            folder = str(Path(name).parent)
            if folder == "checkpoints":
                checkpoint = read_legacy_checkpoint(local)
                path = save_checkpoint(checkpoint, work / "new" / checkpoint_name(checkpoint.trial))
            else:
                learner_cls = load_learner(params["learner"])
                if spec is None:
                    spec = load_task(params["task"])(**task_options(params)).spec
                policy = learner_cls.read_legacy_policy(local, spec)
                path = learner_cls.save_policy(policy, work / "new" / Path(name).stem)
            store.log_artifact(run_id, path, folder)
            written.append(f"{folder}/{path.name}")
            say(f"run {run_id}: {name} -> {written[-1]}")
        for name in models:
            local = run.copy(name, work / "models" / Path(name).name)
            if convert_model_file(local):
                store.log_artifact(run_id, local, str(Path(name).parent))
                written.append(name)
                say(f"run {run_id}: {name} rewritten as tensors and plain values")
    run.close()
    return written


def runs_with_legacy_files(store: Any) -> list[str]:
    """The ids of the store's runs that have a checkpoint or policy in an older format not converted yet."""
    found = []
    for run in store.search():
        names = [a.path for folder in ("checkpoints", "policies") for a in run.artifacts(folder)]
        if legacy_files(names):
            found.append(run.run_id)
    return found
