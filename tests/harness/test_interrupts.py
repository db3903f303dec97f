"""Stop requests (Ctrl-C, SIGTERM) never cut a store write or checkpoint in half."""

from __future__ import annotations

import os
import signal

import pytest

from harness.interrupts import held_interrupts, terminate_as_interrupt
from harness.runner import RunConfig, run
from harness.tracking import MemoryTracker
from tests.harness.trackers import AtTrial


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_inside_the_block_is_delivered_after_it(signum):
    terminate_as_interrupt()  # SIGTERM -> KeyboardInterrupt, as in the CLI
    # SIGINT: Python's default handler, also when the tests run as a background job (which inherits SIG_IGN)
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        before = signal.getsignal(signum)
        finished = []
        with pytest.raises(KeyboardInterrupt):
            with held_interrupts():
                os.kill(os.getpid(), signum)
                finished.append("after the signal")  # not reached if the signal cut the block short
        assert finished == ["after the signal"]
        assert signal.getsignal(signum) is before
    finally:
        signal.signal(signal.SIGINT, inherited)


def test_an_ignored_sigint_stays_ignored_inside_the_block():
    inherited = signal.signal(signal.SIGINT, signal.SIG_IGN)  # e.g. a background job started by a shell
    try:
        finished = []
        with held_interrupts():
            os.kill(os.getpid(), signal.SIGINT)
            finished.append("after the signal")
        assert finished == ["after the signal"] and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, inherited)


def test_without_a_signal_the_block_leaves_the_handlers_as_they_were():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with held_interrupts():
        pass
    assert {s: signal.getsignal(s) for s in before} == before


class SignalledWhileWriting(AtTrial):
    """Gets SIGTERM in the middle of logging trial ``step``'s metrics (between two halves of the batch)."""

    def at_trial(self, metrics, step) -> None:
        items = list(metrics.items())
        MemoryTracker.log_metrics(self, dict(items[: len(items) // 2]), step)
        os.kill(os.getpid(), signal.SIGTERM)
        MemoryTracker.log_metrics(self, dict(items[len(items) // 2:]), step)


def test_sigterm_during_a_trial_write_stops_the_run_after_the_write():
    terminate_as_interrupt()
    tracker = SignalledWhileWriting(2)
    with pytest.raises(KeyboardInterrupt):
        run(RunConfig("random", "cartpole", seed=3, max_trials=5, eval_episodes=1), tracker=tracker)
    assert tracker.status == "KILLED"
    trial_2 = {key for key, points in tracker.metrics.items() if any(step == 2 for step, _ in points)}
    assert {"eval_cost", "eval_success_rate", "interaction_seconds", "wall_seconds"} <= trial_2  # both halves
    assert [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2]  # and nothing after it


def test_sigterm_handler_kept_puts_the_application_handler_back():
    from harness.interrupts import sigterm_handler_kept

    def application(signum, frame):
        pass

    signal.signal(signal.SIGTERM, application)
    with sigterm_handler_kept():
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # what ray.init does to it
    assert signal.getsignal(signal.SIGTERM) is application
