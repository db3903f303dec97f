"""A local store copied to another path (a clone, a moved folder) made whole again, and checked.

MLflow records each experiment's and each run's artifact location as an absolute path. A copy of
``results/runs`` (``mlflow.db`` and ``mlruns/``) elsewhere is read by the harness from its own folder
(:func:`~harness.store.connection.local_artifact_root`), but ``mlflow ui`` follows the recorded paths,
and new files would be written there. :func:`relocate` rewrites every recorded location to the same
place under the store's own folder (``<folder>/mlruns/<experiment>/<run>/artifacts``); :func:`check`
says, per run, whether the recorded location holds its files.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from harness.errors import TrackingError
from harness.store.connection import ARTIFACTS_FOLDER, relative_artifact_path, sqlite_path, store_folder, uri_path

#: (table, key column, location column) of every artifact location MLflow records
LOCATIONS = (("experiments", "experiment_id", "artifact_location"), ("runs", "run_uuid", "artifact_uri"),
             ("logged_models", "model_id", "artifact_location"))


def _database(tracking_uri: str) -> Path:
    db = sqlite_path(tracking_uri)
    if db is None or not db.exists():
        raise TrackingError(f"{tracking_uri} is not a local SQLite store (sqlite:////path/to/mlflow.db) that exists; "
                            "a server's store keeps its artifacts itself and needs no relocating")
    return db


def _locations(connection: sqlite3.Connection) -> Iterator[tuple[str, str, str, str, str]]:
    """``(table, key column, location column, key, location)`` of every recorded artifact location."""
    tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    for table, key, column in LOCATIONS:
        if table in tables:
            for row_key, location in connection.execute(f"SELECT {key}, {column} FROM {table}"):  # noqa: S608 - fixed names
                yield table, key, column, row_key, location


@dataclass(frozen=True)
class Relocation:
    """What :func:`relocate` rewrote: how many locations per table, and the folders they pointed into before."""

    rewritten: dict[str, int]
    previous_roots: tuple[str, ...]

    @property
    def total(self) -> int:
        return sum(self.rewritten.values())


def relocate(tracking_uri: str) -> Relocation:
    """Rewrite every local artifact location of the SQLite store to the same place under its own folder
    (what follows ``/mlruns/`` kept); idempotent. Runs must not be writing to the store meanwhile."""
    db = _database(tracking_uri)
    folder = store_folder(tracking_uri) / ARTIFACTS_FOLDER
    rewritten: dict[str, int] = {}
    previous: set[str] = set()
    with sqlite3.connect(db) as connection:
        for table, key, column, row_key, location in list(_locations(connection)):
            relative = relative_artifact_path(location or "")
            if relative is None:
                continue
            target = (folder / relative).as_uri() if relative else folder.as_uri()
            if target != location:
                connection.execute(f"UPDATE {table} SET {column} = ? WHERE {key} = ?", (target, row_key))  # noqa: S608
                rewritten[table] = rewritten.get(table, 0) + 1
                previous.add(str(uri_path(location)).removesuffix(relative).rstrip("/"))
    return Relocation(rewritten, tuple(sorted(previous)))


@dataclass(frozen=True)
class RunFiles:
    """One run's artifact location as the store records it: whether it is inside the store's folder and
    how many files are there (``moved``: recorded elsewhere, but the files are in the store's own folder)."""

    run_id: str
    name: str
    status: str
    located: bool
    moved: bool
    files: int


def check(store) -> list[RunFiles]:
    """Every active run of ``store`` (a :class:`~harness.store.Store` on a local SQLite store): where MLflow
    (and so ``mlflow ui``) looks for its files, and what it finds there."""
    folder = store_folder(store.uri) / ARTIFACTS_FOLDER
    out = []
    for run in store.search(None):
        recorded = uri_path(run.artifact_uri)
        located = recorded is not None and recorded.resolve().is_relative_to(folder)
        here = run.local_root
        files = sum(1 for p in here.rglob("*") if p.is_file()) if here is not None and here.is_dir() else 0
        out.append(RunFiles(run.run_id, run.name, run.status, located, not located and here is not None and here != recorded and here.is_dir(), files))
    return out
