"""The tracking store as the harness uses it: runs found by what they are, read through
:class:`~harness.store.reader.RunReader`, and the writes that are not a run's own records (sweep
parents, the report's comparison runs, ``harness eval``'s results). A run's own records are written
by :class:`harness.tracking.MlflowTracker`."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from harness.store import layout
from harness.store.connection import check_located, ensure_experiment, get_run, open_client, resolve_tracking_uri
from harness.store.reader import RunReader

RunStatus = Literal["RUNNING", "FINISHED", "FAILED", "KILLED"]


class Store:
    """An MLflow tracking store, opened (a :class:`~harness.errors.TrackingError` with the fix if it cannot be).

    Args:
        tracking_uri: see :func:`~harness.store.connection.resolve_tracking_uri`.
        client: an ``MlflowClient`` already open on ``tracking_uri`` (else one is opened).
    """

    def __init__(self, tracking_uri: str | None = None, client: Any = None) -> None:
        self.uri = resolve_tracking_uri(tracking_uri)
        self.client = client if client is not None else open_client(self.uri)

    # ---- finding runs -------------------------------------------------------------------------

    def run(self, run_id: str) -> RunReader:
        """The run ``run_id``; a :class:`~harness.errors.TrackingError` naming the id and the store if there is none."""
        return RunReader(self, get_run(self.client, run_id, self.uri))

    def experiment_id(self, name: str) -> str | None:
        found = self.client.get_experiment_by_name(name)
        return None if found is None else found.experiment_id

    def ensure_experiment(self, name: str) -> str:
        """The id of experiment ``name``, created if missing (:func:`~harness.store.connection.ensure_experiment`)."""
        return ensure_experiment(self.client, name, self.uri)

    def experiments(self) -> dict[str, str]:
        """``id -> name`` of every active experiment."""
        return {e.experiment_id: e.name for e in self.client.search_experiments()}

    def search(self, experiment_ids: Sequence[str] | None = None, filter_string: str = "",
               order_by: Sequence[str] | None = None, max_results: int | None = None) -> list[RunReader]:
        """The runs matching ``filter_string`` (MLflow's search syntax) in ``experiment_ids`` (default:
        every experiment), all pages, or the first ``max_results``."""
        ids = list(experiment_ids) if experiment_ids is not None else list(self.experiments())
        if not ids:
            return []
        runs, token = [], None
        while True:
            page = self.client.search_runs(ids, filter_string=filter_string, max_results=min(max_results or 1000, 1000),
                                           order_by=list(order_by) if order_by else None, page_token=token)
            runs += [RunReader(self, r) for r in page]
            token = page.token
            if not token or (max_results is not None and len(runs) >= max_results):
                return runs[:max_results] if max_results is not None else runs

    def sweep_parents(self, sweep_id: str | None = None, experiment_id: str | None = None) -> list[RunReader]:
        """Sweep parent runs (of ``sweep_id``, in ``experiment_id``; default: all), oldest first: one
        per task of a sweep in the per-task layout, one per sweep in the legacy ``sweeps`` experiment."""
        where = f"tags.`{layout.ROLE_TAG}` = '{layout.ROLE_SWEEP}'"
        if sweep_id is not None:
            where += f" AND tags.`{layout.SWEEP_TAG}` = '{sweep_id}'"
        runs = self.search(None if experiment_id is None else [experiment_id], where)
        return sorted(runs, key=lambda r: r.start_time)

    def children(self, parent: RunReader | str, experiment_id: str | None = None, filter_string: str = "") -> list[RunReader]:
        """The child runs of ``parent`` (a reader, or a run id with its ``experiment_id``), in its experiment."""
        parent_id = parent if isinstance(parent, str) else parent.run_id
        experiment = experiment_id if isinstance(parent, str) else parent.experiment_id
        where = f"tags.`{layout.PARENT_TAG}` = '{parent_id}'" + (f" AND {filter_string}" if filter_string else "")
        return self.search([experiment], where)

    def bench_runs(self) -> list[RunReader]:
        """Every `harness bench` run: a harness run (learner, task, seed tags) with no role, in any experiment."""
        return [r for r in self.search(None) if not r.role and r.cell is not None]

    def unfinished_bench_run(self, task: str, learner: str, seed: int) -> str | None:
        """The newest unfinished (RUNNING, FAILED or KILLED) `harness bench` run of ``learner`` on ``task`` with ``seed``."""
        experiment = self.experiment_id(layout.task_experiment(task))
        if experiment is None:
            return None
        runs = self.search([experiment], (f"params.learner = '{learner}' AND params.seed = '{seed}' "
                                          "AND attributes.status != 'FINISHED'"), order_by=["attributes.start_time DESC"])
        return next((r.run_id for r in runs if not r.role), None)

    # ---- writing (beside a run's own records) ---------------------------------------------------

    def create_run(self, experiment_id: str, name: str, tags: Mapping[str, str], params: Mapping[str, Any] | None = None) -> str:
        """A new RUNNING run named ``name`` with ``tags`` and ``params`` (values as strings, cut to MLflow's limit)."""
        run = self.client.create_run(experiment_id, run_name=name, tags={**tags, layout.RUN_NAME_TAG: name})
        if params:
            self.log_params(run.info.run_id, params)
        return run.info.run_id

    def log_params(self, run_id: str, params: Mapping[str, Any]) -> None:
        from mlflow.entities import Param

        items = [Param(str(k), str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i : i + 100])

    def set_tags(self, run_id: str, tags: Mapping[str, Any]) -> None:
        from mlflow.entities import RunTag

        if tags:
            self.client.log_batch(run_id, tags=[RunTag(k, str(v)[:5000]) for k, v in tags.items()])

    def log_metrics(self, run_id: str, metrics: Mapping[str, float | None], step: int = 0) -> None:
        """Log the finite ``metrics`` at ``step`` (a missing or infinite value is left out, never logged as a stand-in number)."""
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        batch = [Metric(k, float(v), now, int(step)) for k, v in metrics.items() if v is not None and math.isfinite(v)]
        if batch:
            self.client.log_batch(run_id, metrics=batch)

    def _check_located(self, run_id: str) -> None:
        """A store copied from another path writes no file until relocated (:func:`~harness.store.connection.check_located`)."""
        check_located(self.uri, get_run(self.client, run_id, self.uri).info.artifact_uri, f"run {run_id}")

    def log_artifact(self, run_id: str, path: Path, folder: str | None = None) -> None:
        self._check_located(run_id)
        self.client.log_artifact(run_id, str(path), folder)

    def log_table(self, run_id: str, rows: Sequence[Mapping[str, Any]], artifact_file: str) -> None:
        """``rows`` as an MLflow table (the UI's Evaluation view; non-finite numbers as null)."""
        import pandas as pd

        self._check_located(run_id)
        safe = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()} for r in rows]
        self.client.log_table(run_id, data=pd.DataFrame(safe), artifact_file=artifact_file)

    def rename(self, run_id: str, name: str) -> None:
        """Give the run the name ``name`` (what the UI lists it by)."""
        self.client.update_run(run_id, name=name)

    def set_status(self, run_id: str, status: RunStatus) -> None:
        """Mark the run ``status``: RUNNING again, or ended (FINISHED, FAILED, KILLED)."""
        if status == "RUNNING":
            self.client.update_run(run_id, status="RUNNING")
        else:
            self.client.set_terminated(run_id, status)

    def delete_runs(self, run_ids: Iterable[str]) -> None:
        """Mark the runs deleted (hidden in the UI; kept in the database until ``mlflow gc``)."""
        for run_id in run_ids:
            self.client.delete_run(run_id)
