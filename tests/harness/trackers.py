"""Trackers that step in when a given trial's records are logged (for interruption tests): in memory, and
one on an MLflow store."""

from __future__ import annotations

from harness.errors import TrackingError
from harness.tracking import MemoryTracker, MlflowTracker


class AtTrial(MemoryTracker):
    """Calls :meth:`at_trial` instead of logging, once, when trial ``step``'s metrics arrive (after
    its evaluation, its artifacts and its checkpoint: the metrics are the trial's last record)."""

    def __init__(self, step: int) -> None:
        super().__init__()
        self.step = step

    def log_metrics(self, metrics, step):
        if step == self.step and "eval_success_rate" in metrics:
            self.step = -1
            self.at_trial(metrics, step)
            return
        super().log_metrics(metrics, step)

    def at_trial(self, metrics, step) -> None:
        raise NotImplementedError


class InterruptAt(AtTrial):
    """Raises KeyboardInterrupt when trial ``step`` is logged."""

    def at_trial(self, metrics, step) -> None:
        raise KeyboardInterrupt


class DiesAfterLogging(AtTrial):
    """Logs trial ``step``'s metrics, then dies (KeyboardInterrupt): the store holds a trial that no
    checkpoint does when ``step`` has none (the last trial)."""

    def at_trial(self, metrics, step) -> None:
        MemoryTracker.log_metrics(self, metrics, step)
        raise KeyboardInterrupt


class RefusesAt(AtTrial):
    """A store that refuses trial ``step``'s metrics (a server down, a database file replaced) and
    every write after them until it is :meth:`mended` (the run's end included)."""

    def at_trial(self, metrics, step) -> None:
        self.broken = True
        raise TrackingError(f"refused the metrics of step {step}")

    def log_metrics(self, metrics, step):
        if getattr(self, "broken", False):
            raise TrackingError("still refusing")
        super().log_metrics(metrics, step)

    def finish(self, status):
        if getattr(self, "broken", False):
            raise TrackingError("still refusing to end the run")
        super().finish(status)

    def mended(self) -> RefusesAt:
        self.broken = False
        return self


class InterruptedMlflow(MlflowTracker):
    """An MLflow run interrupted (Ctrl-C) when trial ``step``'s metrics arrive: its policy and checkpoint
    are stored, the run ends KILLED."""

    def __init__(self, uri: str, step: int) -> None:
        super().__init__(uri)
        self.step = step

    def log_metrics(self, metrics, step):
        if step == self.step and "eval_success_rate" in metrics:
            self.step = -1
            raise KeyboardInterrupt
        super().log_metrics(metrics, step)
