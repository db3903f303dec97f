"""Experiment tracking: MLflow (imported lazily: ``import mlflow`` costs ~2.5 s) or in memory.

Default store, no server needed: a SQLite database ``mlflow.db`` in the working directory with
artifacts in ``./mlruns`` beside it. Override with ``--tracking-uri`` or ``MLFLOW_TRACKING_URI``
(e.g. ``http://127.0.0.1:5000`` for a shared ``mlflow server``). One experiment per task, one
run per (learner, task, seed). Browse with::

    mlflow ui --backend-store-uri sqlite:///mlflow.db
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, Protocol

from harness.errors import TrackingError
from harness.provenance import PROCESS_TAG, process_token

RunStatus = Literal["FINISHED", "FAILED", "KILLED"]


def default_tracking_uri(directory: Path | None = None) -> str:
    """``sqlite:///<abs dir>/mlflow.db`` (``directory`` defaults to the working directory)."""
    path = (directory or Path.cwd()).resolve() / "mlflow.db"
    return f"sqlite:///{path}"


def resolve_tracking_uri(uri: str | None) -> str:
    """Explicit ``uri`` > ``MLFLOW_TRACKING_URI`` > the local SQLite default."""
    return uri or os.environ.get("MLFLOW_TRACKING_URI") or default_tracking_uri()


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
        get_run(self.client, run_id, self.tracking_uri)
        self.run_id = run_id
        self.client.update_run(run_id, status="RUNNING")
        self.set_tags({PROCESS_TAG: process_token()})

    def list_artifacts(self, artifact_path: str) -> list[str]:
        """Names of the run's artifacts under ``artifact_path``."""
        return sorted(a.path for a in self.client.list_artifacts(self.run_id, artifact_path))

    def fetch_artifact(self, name: str, destination: Path) -> Path:
        """Download one artifact of the run into ``destination``."""
        destination.mkdir(parents=True, exist_ok=True)
        return Path(self.client.download_artifacts(self.run_id, name, str(destination)))

    def logged_steps(self, key: str) -> set[int]:
        """The steps at which metric ``key`` of the run is in the store."""
        return {m.step for m in self.client.get_metric_history(self.run_id, key)}

    def find_resumable(self, experiment: str, learner: str, seed: int) -> str | None:
        """The newest unfinished (RUNNING, FAILED or KILLED) run of ``learner`` with ``seed``."""
        found = self.client.get_experiment_by_name(experiment)
        if found is None:
            return None
        runs = self.client.search_runs(
            [found.experiment_id],
            filter_string=f"params.learner = '{learner}' AND params.seed = '{seed}' AND attributes.status != 'FINISHED'",
            order_by=["attributes.start_time DESC"],
            max_results=1,
        )
        return runs[0].info.run_id if runs else None


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


def quiet_mlflow_logging() -> None:
    """Silence MLflow/alembic INFO chatter ("Creating initial MLflow database tables...") and MLflow's
    download bar per artifact (a resumed run's checkpoint, each plot a report or script copies);
    ``MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR=true`` in the environment brings the bars back."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    for name in ("alembic", "alembic.runtime.migration", "mlflow"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # it logs each refused write with its traceback (twice, with its retry) before raising it; the
    # harness reports the error once, as a TrackingError (the traceback with --debug)
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)


@contextlib.contextmanager
def _store_lock(tracking_uri: str):
    """Serialise the opening of a local SQLite store across processes.

    Two processes creating a fresh ``mlflow.db`` at once race in MLflow's schema migration
    ("table alembic_version already exists"); an exclusive ``flock`` on ``<db>.lock`` while the
    store is opened (and, if new, created) makes the second wait for the first.
    """
    if not tracking_uri.startswith("sqlite:///"):
        yield
        return
    import fcntl

    lock_path = Path(tracking_uri[len("sqlite:///"):] + ".lock")
    with open(lock_path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def open_client(tracking_uri: str):
    """An ``MlflowClient`` for ``tracking_uri``; a :class:`TrackingError` with the fix if it fails."""
    quiet_mlflow_logging()
    if tracking_uri.startswith("sqlite:///"):
        db = Path(tracking_uri[len("sqlite:///"):])
        if not db.parent.exists() or not os.access(db.parent, os.W_OK):
            raise TrackingError(
                f"tracking store directory {db.parent} does not exist or is not writable; "
                "pass --tracking-uri sqlite:////a/writable/path/mlflow.db"
            )
    try:
        import warnings

        with warnings.catch_warnings(), _store_lock(tracking_uri):
            warnings.simplefilter("ignore")
            from mlflow.tracking import MlflowClient

            client = MlflowClient(tracking_uri=tracking_uri)
            client.search_experiments(max_results=1)  # opens (and if new, creates) the store
    except TrackingError:
        raise
    except Exception as exc:
        raise TrackingError(
            f"cannot open the tracking store {tracking_uri} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); "
            "check the URI, that the server is running, or pass --tracking-uri"
        ) from exc
    return client


def get_run(client, run_id: str, tracking_uri: str):
    """The MLflow run ``run_id`` of ``client``'s store; a :class:`TrackingError` naming the id and
    the store if there is no such run."""
    try:
        return client.get_run(run_id)
    except Exception as exc:
        raise TrackingError(f"no run {run_id!r} in {tracking_uri}; check the id (`mlflow ui --backend-store-uri {tracking_uri}` lists runs)") from exc


def artifact_location_for(tracking_uri: str, experiment: str) -> str | None:
    """For a local SQLite store: ``<db dir>/mlruns/<experiment>`` (not the current directory)."""
    if tracking_uri.startswith("sqlite:///"):
        db = Path(tracking_uri[len("sqlite:///"):])
        return (db.parent / "mlruns" / experiment).resolve().as_uri()
    return None


def ensure_experiment(client, name: str, tracking_uri: str) -> str:
    """The id of experiment ``name``, created if missing (idempotent under a creation race)."""
    found = client.get_experiment_by_name(name)
    if found is not None:
        return found.experiment_id
    try:
        return client.create_experiment(name, artifact_location=artifact_location_for(tracking_uri, name))
    except Exception:
        found = client.get_experiment_by_name(name)  # another process created it first
        if found is None:
            raise
        return found.experiment_id
