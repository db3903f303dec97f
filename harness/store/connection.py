"""Opening a tracking store: its URI, the MLflow client (imported lazily: ``import mlflow`` costs
~2.5 s), experiments, and where a local store keeps its artifacts.

Default store, no server needed: a SQLite database ``mlflow.db`` in the working directory with
artifacts in ``./mlruns`` beside it. Override with ``--tracking-uri`` or ``MLFLOW_TRACKING_URI``
(e.g. ``http://127.0.0.1:5000`` for a shared ``mlflow server``).

A local store keeps every artifact under ``<folder of mlflow.db>/mlruns/<experiment>/<run id>/artifacts``.
MLflow records that location as an absolute path; a store copied elsewhere (a clone) is read from its
own folder (:func:`local_artifact_root`) and made writable again by ``harness store relocate``.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from urllib.parse import unquote, urlparse

from harness.errors import TrackingError

#: the folder of a local store's artifacts, beside its database
ARTIFACTS_FOLDER = "mlruns"


def default_tracking_uri(directory: Path | None = None) -> str:
    """``sqlite:///<abs dir>/mlflow.db`` (``directory`` defaults to the working directory)."""
    path = (directory or Path.cwd()).resolve() / "mlflow.db"
    return f"sqlite:///{path}"


def resolve_tracking_uri(uri: str | None) -> str:
    """Explicit ``uri`` > ``MLFLOW_TRACKING_URI`` > the local SQLite default."""
    return uri or os.environ.get("MLFLOW_TRACKING_URI") or default_tracking_uri()


def browse_command(tracking_uri: str) -> str:
    """How to look at the store: a server's own address (it is the UI), else ``mlflow ui`` on the store."""
    return tracking_uri if tracking_uri.startswith(("http://", "https://")) else f"mlflow ui --backend-store-uri {tracking_uri}"


def sqlite_path(tracking_uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI, else ``None``."""
    return Path(tracking_uri[len("sqlite:///"):]) if tracking_uri.startswith("sqlite:///") else None


def store_folder(tracking_uri: str) -> Path | None:
    """The folder of a local SQLite store (its artifacts are in ``<folder>/mlruns``), else ``None``."""
    db = sqlite_path(tracking_uri)
    return None if db is None else db.resolve().parent


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
    db = sqlite_path(tracking_uri)
    if db is None:
        yield
        return
    import fcntl

    with open(str(db) + ".lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _check_server_listens(tracking_uri: str, timeout: float = 10) -> None:
    """A :class:`TrackingError` at once if nothing listens at a server URI's address (MLflow's client
    would retry for minutes before it says so)."""
    parsed = urlparse(tracking_uri)
    if parsed.scheme not in ("http", "https") or not parsed.hostname:
        return
    import socket

    try:
        socket.create_connection((parsed.hostname, parsed.port or (443 if parsed.scheme == "https" else 80)), timeout=timeout).close()
    except OSError as exc:
        raise TrackingError(
            f"the tracking server {tracking_uri} does not answer ({exc.strerror or type(exc).__name__}); start it "
            "(`harness store serve --dir DIR` prints its URI) or pass the right --tracking-uri"
        ) from None


def open_client(tracking_uri: str):
    """An ``MlflowClient`` for ``tracking_uri``; a :class:`TrackingError` with the fix if it fails."""
    quiet_mlflow_logging()
    db = sqlite_path(tracking_uri)
    if db is not None and (not db.parent.exists() or not os.access(db.parent, os.W_OK)):
        raise TrackingError(
            f"tracking store directory {db.parent} does not exist or is not writable; "
            "pass --tracking-uri sqlite:////a/writable/path/mlflow.db"
        )
    _check_server_listens(tracking_uri)
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
        raise TrackingError(f"no run {run_id!r} in {tracking_uri}; check the id (`{browse_command(tracking_uri)}` lists runs)") from exc


def artifact_location_for(tracking_uri: str, experiment: str) -> str | None:
    """For a local SQLite store: ``<db dir>/mlruns/<experiment>`` (not the current directory)."""
    folder = store_folder(tracking_uri)
    return None if folder is None else (folder / ARTIFACTS_FOLDER / experiment).as_uri()


def uri_path(uri: str) -> Path | None:
    """The local path of a ``file:`` URI or of a plain path; ``None`` for any other scheme."""
    parsed = urlparse(uri)
    if parsed.scheme == "file":
        return Path(unquote(parsed.path))
    return Path(uri) if parsed.scheme == "" else None


def relative_artifact_path(uri: str) -> str | None:
    """What follows ``/mlruns/`` in a local artifact location (``cartpole/<run>/artifacts``), else ``None``."""
    path = uri_path(uri)
    if path is None:
        return None
    parts = path.parts
    if ARTIFACTS_FOLDER not in parts:
        return None
    index = len(parts) - 1 - parts[::-1].index(ARTIFACTS_FOLDER)
    return "/".join(parts[index + 1:])


def local_artifact_root(tracking_uri: str, artifact_uri: str) -> Path | None:
    """Where a run's (or an experiment's) artifacts are on this machine: the same place under this
    store's own ``mlruns`` folder (a store copied or cloned from another path records the old one) if
    it is there, else the recorded path; ``None`` for a store that serves its artifacts (a server)."""
    recorded = uri_path(artifact_uri)
    if recorded is None:
        return None
    folder, relative = store_folder(tracking_uri), relative_artifact_path(artifact_uri)
    if folder is not None and relative is not None and (folder / ARTIFACTS_FOLDER / relative).exists():
        return folder / ARTIFACTS_FOLDER / relative
    return recorded


def check_located(tracking_uri: str, artifact_location: str, what: str) -> None:
    """A :class:`TrackingError` if a local store's ``what`` (an experiment) keeps its artifacts
    outside the store's folder: the store was copied from another path and new artifacts would be
    written there; ``harness store relocate`` rewrites the locations."""
    folder = store_folder(tracking_uri)
    path = uri_path(artifact_location)
    if folder is None or path is None:
        return
    if not path.resolve().is_relative_to(folder / ARTIFACTS_FOLDER):
        raise TrackingError(
            f"{what} of the store {tracking_uri} keeps its artifacts at {path}, outside the store's folder "
            f"(the store was copied from another path); run `harness store relocate --tracking-uri {tracking_uri}` first"
        )


def ensure_experiment(client, name: str, tracking_uri: str) -> str:
    """The id of experiment ``name``, created if missing (idempotent under a creation race); a
    :class:`TrackingError` if it writes its artifacts outside a local store's folder (:func:`check_located`)."""
    found = client.get_experiment_by_name(name)
    if found is None:
        try:
            return client.create_experiment(name, artifact_location=artifact_location_for(tracking_uri, name))
        except Exception:
            found = client.get_experiment_by_name(name)  # another process created it first
            if found is None:
                raise
    check_located(tracking_uri, found.artifact_location, f"experiment {name!r}")
    return found.experiment_id
