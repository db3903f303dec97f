"""The tracking store: the one place that knows how the harness's records sit in MLflow.

* :mod:`~harness.store.layout`: experiments, run names, roles, tags, metric names, artifact paths;
* :mod:`~harness.store.connection`: opening a store, its experiments, where its artifacts are;
* :mod:`~harness.store.client`: :class:`Store`, runs found by what they are, and the writes beside
  a run's own records (a run's own: :class:`harness.tracking.MlflowTracker`);
* :mod:`~harness.store.reader`: :class:`RunReader`, one run read back (settings, metrics, files);
* :mod:`~harness.store.relocate`: a store copied to another path made whole again.

Nothing else in the harness calls MLflow's client. Importing this package imports no MLflow.
"""

from harness.store.client import Store
from harness.store.reader import Artifact, RunReader

__all__ = ["Artifact", "RunReader", "Store"]
