"""One run of a tracking store read back: its settings, tags, metrics and their histories, and its files.

    store = Store(tracking_uri)
    run = store.run(run_id)                     # a TrackingError naming the id if there is none
    run.params["task"], run.time_to_success     # settings; the metric under its current or older name
    run.history("eval_cost")                    # {trial: value}
    run.file("policies/policy_trial003.pkl")    # a local path (downloaded only from a server)

Files of a local store are read where they are (under the store's own folder, wherever it was copied
to: :func:`~harness.store.connection.local_artifact_root`); a server's are downloaded into a
temporary folder that :meth:`RunReader.close` removes.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

from harness.errors import CheckpointError
from harness.store import layout

if TYPE_CHECKING:
    from harness.checkpoint import Checkpoint
    from harness.store.client import Store
    from harness.task import Episode


@dataclass(frozen=True)
class Artifact:
    """One entry of a run's artifacts: ``path`` relative to the run's artifact root, ``size`` in bytes (0 for a folder)."""

    path: str
    is_dir: bool
    size: int = 0

    @property
    def name(self) -> str:
        return Path(self.path).name


class RunReader:
    """A run of ``store`` (an MLflow ``Run`` as the store returned it), for reading.

    Attributes:
        run_id, experiment_id, status (``FINISHED``/``FAILED``/``KILLED``/``RUNNING``), start_time (ms),
        name; params, tags, metrics (each metric's latest value) as plain dicts.
    """

    def __init__(self, store: Store, run: Any) -> None:
        self.store = store
        info, data = run.info, run.data
        self.run_id: str = info.run_id
        self.experiment_id: str = info.experiment_id
        self.status: str = info.status
        self.start_time: int = int(info.start_time or 0)
        self.artifact_uri: str = info.artifact_uri
        self.params: dict[str, str] = dict(data.params)
        self.tags: dict[str, str] = dict(data.tags)
        self.metrics: dict[str, float] = dict(data.metrics)
        self.name: str = self.tags.get(layout.RUN_NAME_TAG, self.run_id)
        self._downloads: tempfile.TemporaryDirectory | None = None

    def __enter__(self) -> RunReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Remove the files downloaded from a server (a local store's files are read in place)."""
        if self._downloads is not None:
            self._downloads.cleanup()
            self._downloads = None

    # ---- what the run is ----------------------------------------------------------------------

    @property
    def role(self) -> str:
        """``cell``, ``sweep``, ``comparison``, ``comparison-row``, or ``""`` for a `harness bench` run."""
        return self.tags.get(layout.ROLE_TAG, "")

    @property
    def cell(self) -> tuple[str, str, int] | None:
        """``(learner, task, seed)`` of a harness run (bench or sweep cell), else ``None``."""
        try:
            return self.tags[layout.LEARNER_TAG], self.tags[layout.TASK_TAG], int(self.tags[layout.SEED_TAG])
        except (KeyError, ValueError):
            return None

    @property
    def sweep_id(self) -> str:
        return self.tags.get(layout.SWEEP_TAG, "")

    @property
    def parent_run_id(self) -> str:
        return self.tags.get(layout.PARENT_TAG, "")

    # ---- metrics ------------------------------------------------------------------------------

    def metric(self, key: str) -> float | None:
        """The latest value of ``key``; ``None`` if never logged or not finite."""
        value = self.metrics.get(key)
        return None if value is None or not math.isfinite(value) else float(value)

    @property
    def solved(self) -> bool:
        """Whether the run solved its task (a FINISHED run tagged solved)."""
        return self.tags.get(layout.SOLVED_TAG) == "true" and self.status == "FINISHED"

    @property
    def time_to_success(self) -> float | None:
        """Interaction seconds to success of a solved run (under the metric's current name or its older one)."""
        if not self.solved:
            return None
        found = self.metric(layout.TIME_TO_SUCCESS)
        return found if found is not None else self.metric(layout.LEGACY_TIME_TO_SUCCESS)

    def reached(self, key: str) -> float:
        """How far the run got in cumulative metric ``key``: its ``<key>_total`` (logged when a run
        segment ends) or its last per-trial ``<key>``, whichever is larger (a run resumed after a kill
        that logged no totals, SIGKILL or a machine's end, has a stale total from an earlier segment)."""
        return max(self.metric(key + layout.TOTAL_SUFFIX) or 0.0, self.metric(key) or 0.0)

    def history(self, key: str) -> dict[int, float]:
        """``{step: value}`` of metric ``key`` (empty if never logged); the step is the trial."""
        return {int(m.step): float(m.value) for m in self.store.client.get_metric_history(self.run_id, key)}

    # ---- files --------------------------------------------------------------------------------

    @cached_property
    def local_root(self) -> Path | None:
        """The folder of the run's artifacts on this machine (``None``: the store serves them)."""
        from harness.store.connection import local_artifact_root

        return local_artifact_root(self.store.uri, self.artifact_uri)

    def artifacts(self, folder: str = "") -> list[Artifact]:
        """The entries directly under ``folder`` (``""``: the top level), sorted by path; empty if
        the folder or the run's artifacts are not there (a store copied without them)."""
        if self.local_root is None:
            return sorted((Artifact(a.path, a.is_dir, int(a.file_size or 0)) for a in self.store.client.list_artifacts(self.run_id, folder or None)),
                          key=lambda a: a.path)
        base = self.local_root / folder
        if not base.is_dir():
            return []
        return [Artifact(str(p.relative_to(self.local_root)), p.is_dir(), 0 if p.is_dir() else p.stat().st_size) for p in sorted(base.iterdir())]

    def all_artifacts(self) -> list[Artifact]:
        """Every file of the run, at any depth."""
        found: list[Artifact] = []
        pending = [""]
        while pending:
            for entry in self.artifacts(pending.pop()):
                if entry.is_dir:
                    pending.append(entry.path)
                else:
                    found.append(entry)
        return sorted(found, key=lambda a: a.path)

    def file(self, path: str) -> Path:
        """A local copy of the run's artifact ``path`` (a local store's own file; a server's, downloaded once).
        A :class:`CheckpointError` naming the run and the path if it has no such artifact."""
        if self.local_root is not None:
            local = self.local_root / path
            if not local.is_file():
                raise CheckpointError(f"run {self.run_id} has no artifact {path!r} (looked in {self.local_root})")
            return local
        if self._downloads is None:
            self._downloads = tempfile.TemporaryDirectory(prefix="harness-run-")
        local = Path(self._downloads.name) / path
        if not local.exists():
            try:
                return Path(self.store.client.download_artifacts(self.run_id, path, self._downloads.name))
            except Exception as exc:  # noqa: BLE001 - MLflow raises several types for a missing artifact
                raise CheckpointError(f"run {self.run_id} has no artifact {path!r} ({exc})") from exc
        return local

    def copy(self, path: str, target: Path) -> Path:
        """Copy the run's artifact ``path`` to the file ``target``."""
        shutil.copyfile(self.file(path), target)
        return Path(target)

    def fetch(self, path: str, destination: Path) -> Path:
        """Copy the run's artifact ``path`` into the folder ``destination`` (its name kept)."""
        destination.mkdir(parents=True, exist_ok=True)
        return self.copy(path, destination / Path(path).name)

    # ---- what the runner stores ---------------------------------------------------------------

    def policy_artifacts(self) -> list[Artifact]:
        """The saved policies (path, size), one per trial, by trial; where a trial has a file in the
        data format and one in an older pickled format (a migrated run), the data format's
        (:func:`harness.datafile.trial_files`)."""
        from harness.datafile import trial_files
        from harness.learner import POLICY_PREFIX

        files = {a.path: a for a in self.artifacts(layout.POLICIES) if not a.is_dir}
        return [files[path] for path in trial_files(files, POLICY_PREFIX).values()]

    def policies(self) -> list[str]:
        """Artifact paths of the saved policies, one per trial, by trial (:meth:`policy_artifacts`)."""
        return [a.path for a in self.policy_artifacts()]

    def policy(self, trial: int | None = None) -> str:
        """Artifact path of the last saved policy, or of ``trial``'s; a :class:`CheckpointError` saying
        what there is otherwise."""
        files = self.policies()
        if not files:
            raise CheckpointError(f"run {self.run_id} has no saved policy here (no artifacts under '{layout.POLICIES}/'): policies "
                                  "stay on the machine that ran the run unless committed with the store (harness store policies "
                                  "--paths, results/README.md)")
        if trial is None:
            return files[-1]
        wanted = [f for f in files if Path(f).stem == layout.policy_stem(trial)]
        if not wanted:
            raise CheckpointError(f"run {self.run_id} has no policy of trial {trial}; it has {', '.join(Path(f).name for f in files)}")
        return wanted[0]

    def policy_trials(self) -> list[int]:
        """Trials with a saved policy, ascending."""
        return sorted(int(Path(p).stem[len("policy_trial"):]) for p in self.policies())

    def trial_files(self, pattern: str) -> list[str]:
        """Artifact paths of the files matching ``pattern`` (``fnmatch``) in the per-trial folders, by trial."""
        from fnmatch import fnmatch

        found = []
        for entry in self.artifacts():
            if entry.is_dir and layout.trial_of_folder(entry.path) is not None:
                found += [a.path for a in self.artifacts(entry.path) if fnmatch(a.name, pattern)]
        return sorted(found, key=lambda p: Path(p).name)

    def episodes(self) -> list[Episode]:
        """Every interaction episode of the run, in the order they happened (random ones first).

        A run writes its episodes file when it ends; a run still going, or one stopped before that (a
        sweep stopped with SIGUSR1, a crash), gives the episodes of its newest checkpoint that loads.
        A :class:`CheckpointError` saying what is missing where the run has neither."""
        from harness.runner import load_episodes
        from harness.task import Episode

        try:
            return load_episodes(self.file(layout.EPISODES))
        except CheckpointError as missing:
            checkpoint = self.newest_checkpoint()
            if checkpoint is None:
                raise CheckpointError(f"{missing}; nor a checkpoint to read the episodes from") from None
            return [Episode(**ep) for ep in checkpoint.interaction["episodes"]]

    def newest_checkpoint(self) -> Checkpoint | None:
        """The run's checkpoint of the highest trial that loads (one cut short by a crash is skipped), or
        None where it has none."""
        from harness.checkpoint import PREFIX, load_checkpoint
        from harness.datafile import trial_files

        names = trial_files((a.path for a in self.artifacts(layout.CHECKPOINTS) if not a.is_dir), PREFIX)
        for name in reversed(names.values()):
            try:
                return load_checkpoint(self.file(name))
            except CheckpointError:
                continue
        return None
