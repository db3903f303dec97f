"""In-memory trackers that step in when a given trial's records are logged (for interruption tests)."""

from __future__ import annotations

from harness.tracking import MemoryTracker


class AtTrial(MemoryTracker):
    """Calls :meth:`at_trial` instead of logging, once, when trial ``step``'s metrics arrive (after
    its evaluation, before its checkpoint)."""

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
