"""Stop requests (Ctrl-C, SIGTERM) never cut a store write or checkpoint in half."""

from __future__ import annotations

import os
import signal

import pytest

from harness.interrupts import (STOP_AFTER_TRIAL, StopRequested, catch_stop_requests_early, held_interrupts, stop_requests,
                                terminate_as_interrupt)
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


class AskedToStopWhileWriting(AtTrial):
    """Gets SIGUSR1 (stop after the trial in progress) while trial ``step``'s metrics are logged."""

    def at_trial(self, metrics, step) -> None:
        os.kill(os.getpid(), STOP_AFTER_TRIAL)
        MemoryTracker.log_metrics(self, metrics, step)


@pytest.mark.skipif(STOP_AFTER_TRIAL is None, reason="no SIGUSR1 on this platform")
def test_sigusr1_stops_the_run_once_its_trial_is_stored_and_the_resume_loses_nothing():
    config = RunConfig("random", "cartpole", seed=6, max_trials=5, eval_episodes=1)
    reference = run(config)
    before = signal.getsignal(STOP_AFTER_TRIAL)
    tracker = AskedToStopWhileWriting(2)
    with pytest.raises(StopRequested, match="stopped after trial 2 as asked"):
        run(config, tracker=tracker)
    assert signal.getsignal(STOP_AFTER_TRIAL) is before  # the run's handler is gone with it
    assert tracker.status == "KILLED" and [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2]
    assert any(name.endswith("ckpt_trial002.ckpt") for name in tracker.list_artifacts("checkpoints"))
    # the store tells a stopped, resumable run from a failed one: a tag, and the description says how to continue
    assert tracker.tags["harness.resumable"] == "true" and tracker.tags["stop_reason"] == "killed"
    assert tracker.tags["mlflow.note.content"].startswith("**Stopped before its limit** after 8 s of interaction, 2 trials")
    assert f"plus `--resume {tracker.run_id}`" in tracker.tags["mlflow.note.content"]
    resumed = run(config, tracker=tracker, resume_run_id=tracker.run_id)
    assert tracker.status == "FINISHED" and [s for s, _ in tracker.metrics["eval_cost"]] == [1, 2, 3, 4, 5]
    assert tracker.tags["harness.resumable"] == "false" and tracker.tags["mlflow.note.content"].startswith("**Not solved** (max trials)")
    assert [r["eval_cost"] for r in resumed.history] == [r["eval_cost"] for r in reference.history]
    assert resumed.interaction_seconds == reference.interaction_seconds


@pytest.mark.skipif(STOP_AFTER_TRIAL is None, reason="no SIGUSR1 on this platform")
def test_stop_requests_only_record_the_signal_inside_the_block():
    with stop_requests() as requested:
        assert not requested.is_set()
        os.kill(os.getpid(), STOP_AFTER_TRIAL)
        assert requested.is_set()  # and the process is still here: the default action would have ended it
    with stop_requests() as again:
        assert not again.is_set()


@pytest.mark.skipif(STOP_AFTER_TRIAL is None, reason="no SIGUSR1 on this platform")
def test_a_request_before_the_block_is_honoured_once_when_caught_early():
    """A sweep's cell process may be asked to stop while it is still importing."""
    before = signal.getsignal(STOP_AFTER_TRIAL)
    try:
        catch_stop_requests_early()
        os.kill(os.getpid(), STOP_AFTER_TRIAL)  # recorded; the signal's default action would end the process
        with stop_requests() as requested:
            assert requested.is_set()
        with stop_requests() as again:
            assert not again.is_set()
    finally:
        signal.signal(STOP_AFTER_TRIAL, before)
