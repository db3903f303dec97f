"""Writing a run's records: to MLflow (imported lazily: ``import mlflow`` costs ~2.5 s) or in memory.

The runner hands a :class:`Tracker` its params, per-trial metrics, files and end; where they go in
the store (experiment per task, names, tags) is :mod:`harness.store.layout`. Browse with::

    mlflow ui --backend-store-uri sqlite:///mlflow.db
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, Protocol

from harness.errors import TrackingError
from harness.provenance import PROCESS_TAG, process_token
from harness.store.connection import default_tracking_uri, ensure_experiment, get_run, open_client, resolve_tracking_uri

__all__ = ["MemoryTracker", "MlflowTracker", "Tracker", "default_tracking_uri", "ensure_experiment", "get_run", "open_client",
           "refused_write_message", "resolve_tracking_uri"]

RunStatus = Literal["FINISHED", "FAILED", "KILLED"]


class Tracker(Protocol):
    """What the runner needs from a tracking backend."""

    run_id: str | None

    def start(self, experiment: str, run_name: str, params: Mapping[str, Any], tags: Mapping[str, str]) -> str: ...

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None: ...

    def set_tags(self, tags: Mapping[str, Any]) -> None: ...

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None: ...

    def finish(self, status: RunStatus) -> None: ...

    def resume(self, run_id: str) -> None: ...

    def list_artifacts(self, artifact_path: str) -> list[str]: ...

    def delete_artifact(self, name: str) -> None: ...

    def fetch_artifact(self, name: str, destination: Path) -> Path: ...

    def logged_steps(self, key: str) -> set[int]: ...


def _finite(metrics: Mapping[str, float]) -> dict[str, float]:
    """Drop non-finite values (MLflow rejects NaN in some stores; a missing metric is honest)."""
    out = {}
    for key, value in metrics.items():
        if value is None:
            continue
        value = float(value)
        if math.isfinite(value):
            out[key] = value
    return out


class MemoryTracker:
    """Keeps everything in memory (artifacts: copies in a private temporary folder); for library
    use and tests. ``resume`` continues the same object's run."""

    def __init__(self) -> None:
        import tempfile

        self.root = Path(tempfile.mkdtemp(prefix="harness-memtracker-"))
        self.run_id: str | None = None
        self.experiment: str | None = None
        self.params: dict[str, str] = {}
        self.tags: dict[str, str] = {}
        self.metrics: dict[str, list[tuple[int, float]]] = {}
        self.artifacts: list[tuple[Path, str | None]] = []
        self.status: str | None = None

    def start(self, experiment: str, run_name: str, params: Mapping[str, Any], tags: Mapping[str, str]) -> str:
        self.experiment = experiment
        self.run_id = run_name
        self.params = {k: str(v) for k, v in params.items()}
        self.tags = {k: str(v) for k, v in tags.items()}
        self.status = "RUNNING"
        return self.run_id

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        for key, value in _finite(metrics).items():
            self.metrics.setdefault(key, []).append((step, value))

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        self.tags.update({k: str(v) for k, v in tags.items()})

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        import shutil

        folder = self.root / (artifact_path or "")
        folder.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, folder / Path(path).name)
        self.artifacts.append((Path(path), artifact_path))

    def finish(self, status: RunStatus) -> None:
        self.status = status

    def resume(self, run_id: str) -> None:
        if run_id != self.run_id:
            raise TrackingError(f"no run {run_id!r} in this in-memory tracker")
        self.status = "RUNNING"

    def list_artifacts(self, artifact_path: str) -> list[str]:
        source = self.root / artifact_path
        return [f"{artifact_path}/{f.name}" for f in sorted(source.glob("*"))] if source.exists() else []

    def delete_artifact(self, name: str) -> None:
        (self.root / name).unlink(missing_ok=True)

    def fetch_artifact(self, name: str, destination: Path) -> Path:
        import shutil

        destination.mkdir(parents=True, exist_ok=True)
        return Path(shutil.copy2(self.root / name, destination / Path(name).name))

    def logged_steps(self, key: str) -> set[int]:
        return {step for step, _ in self.metrics.get(key, [])}


class MlflowTracker:
    """Logs to an MLflow tracking store.

    Args:
        tracking_uri: store URI; see :func:`resolve_tracking_uri`.
        parent_run_id: makes the run a child of this run (sweeps).
        experiment_id: use this experiment instead of looking it up by name (sweeps create it
            once in the driver, so that concurrent workers never race on creation).
    """

    def __init__(self, tracking_uri: str | None = None, parent_run_id: str | None = None, experiment_id: str | None = None) -> None:
        self.tracking_uri = resolve_tracking_uri(tracking_uri)
        self.parent_run_id = parent_run_id
        self.experiment_id = experiment_id
        self.run_id: str | None = None
        self._client = None

    @property
    def client(self):
        if self._client is None:
            self._client = open_client(self.tracking_uri)
        return self._client

    def start(self, experiment: str, run_name: str, params: Mapping[str, Any], tags: Mapping[str, str]) -> str:
        try:
            experiment_id = self.experiment_id or ensure_experiment(self.client, experiment, self.tracking_uri)
            all_tags = dict(tags)
            if self.parent_run_id:
                all_tags["mlflow.parentRunId"] = self.parent_run_id
            all_tags["mlflow.runName"] = run_name
            all_tags[PROCESS_TAG] = process_token()
            run = self.client.create_run(experiment_id, run_name=run_name, tags=all_tags)
            self.run_id = run.info.run_id
            self._log_params(params)
        except TrackingError:
            raise
        except Exception as exc:
            raise TrackingError(
                f"cannot write to the tracking store {self.tracking_uri} ({type(exc).__name__}: {exc}); "
                "check the path is writable or the server is running, or pass --tracking-uri"
            ) from exc
        return self.run_id

    def _log_params(self, params: Mapping[str, Any]) -> None:
        from mlflow.entities import Param

        items = [Param(str(k), str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self.client.log_batch(self.run_id, params=items[i : i + 100])

    @contextlib.contextmanager
    def _writing(self, what: str):
        """A write the store refuses mid-run becomes a :class:`TrackingError` that says what to do."""
        try:
            yield
        except TrackingError:
            raise
        except Exception as exc:
            raise TrackingError(refused_write_message(self.tracking_uri, self.run_id, what, exc)) from exc

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        batch = [Metric(k, v, now, int(step)) for k, v in _finite(metrics).items()]
        if batch:
            with self._writing(f"log the metrics of step {step}"):
                self.client.log_batch(self.run_id, metrics=batch)

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        from mlflow.entities import RunTag

        with self._writing("set tags"):
            self.client.log_batch(self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        with self._writing(f"store {Path(path).name}"):
            self.client.log_artifact(self.run_id, str(path), artifact_path)

    def finish(self, status: RunStatus) -> None:
        if self.run_id is not None:
            with self._writing(f"mark the run {status}"):
                self.client.set_terminated(self.run_id, status)

    def resume(self, run_id: str) -> None:
        """Continue logging into the existing run ``run_id`` (marked RUNNING again)."""
        from harness.store.connection import check_located

        run = get_run(self.client, run_id, self.tracking_uri)
        check_located(self.tracking_uri, run.info.artifact_uri, f"run {run_id}")
        self.run_id = run_id
        self.client.update_run(run_id, status="RUNNING")
        self.set_tags({PROCESS_TAG: process_token()})

    def list_artifacts(self, artifact_path: str) -> list[str]:
        """Names of the run's artifacts under ``artifact_path``."""
        return sorted(a.path for a in self.client.list_artifacts(self.run_id, artifact_path))

    def delete_artifact(self, name: str) -> None:
        """Remove one artifact file of the run (``checkpoints/ckpt_trial003.ckpt``); absent: nothing."""
        from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

        with self._writing(f"delete {name}"):
            run = get_run(self.client, self.run_id, self.tracking_uri)
            get_artifact_repository(run.info.artifact_uri).delete_artifacts(name)

    def fetch_artifact(self, name: str, destination: Path) -> Path:
        """Download one artifact of the run into ``destination``."""
        destination.mkdir(parents=True, exist_ok=True)
        return Path(self.client.download_artifacts(self.run_id, name, str(destination)))

    def logged_steps(self, key: str) -> set[int]:
        """The steps at which metric ``key`` of the run is in the store."""
        return {m.step for m in self.client.get_metric_history(self.run_id, key)}

    def find_resumable(self, task: str, learner: str, seed: int) -> str | None:
        """The newest unfinished (RUNNING, FAILED or KILLED) `harness bench` run of ``learner`` on ``task`` with ``seed``."""
        from harness.store import Store

        return Store(self.tracking_uri, self.client).unfinished_bench_run(task, learner, seed)


def refused_write_message(tracking_uri: str, run_id: str | None, what: str, exc: Exception) -> str:
    """What a write the store refused means, and the way back (the run's checkpoints are files
    beside the store: the resume continues after the last trial whose checkpoint was stored)."""
    lines = str(exc).splitlines()
    readonly = [line for line in lines if "readonly database" in line]
    cause = "; ".join(readonly) or (lines[0] if lines else "")
    hint = ""
    if readonly:
        hint = (" The SQLite file was replaced or deleted while this process had it open (for example by "
                "`git stash` or `git checkout` of a committed store); leave the file alone while runs write to it.")
    return (f"the tracking store {tracking_uri} refused to {what} for run {run_id} ({type(exc).__name__}: {cause}).{hint} "
            f"Once the store takes writes again, continue with the same command plus --resume {run_id} "
            "(a sweep: re-run it); trials whose checkpoints were stored are not run again.")
