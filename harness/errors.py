"""Typed exception hierarchy of the harness.

Every error a user can cause derives from :class:`HarnessError`. Its message is one line
that names the problem and, where there is one, the fix. The CLI prints that line and exits
non-zero; it never shows a traceback for a ``HarnessError`` (use ``--debug`` for one).
"""

from __future__ import annotations

import sys
from collections.abc import Callable


class HarnessError(Exception):
    """Base class of all errors the harness raises on purpose."""

    exit_code: int = 2


class PluginNotFoundError(HarnessError):
    """A learner or task name that no installed plugin provides."""


class PluginLoadError(HarnessError):
    """A plugin whose entry point exists but cannot be imported or is not a valid plugin."""


class PluginUnavailableError(PluginLoadError):
    """A plugin whose optional dependencies (a pip extra) are not installed."""


class OptionError(HarnessError):
    """An unknown option, a value of the wrong type, or a value out of range."""


class BudgetExhaustedError(HarnessError):
    """A learner asked for more interaction than the run's budget allows.

    The runner treats this as the normal end of an unsolved run, not as a crash.
    """


class InvalidActionError(HarnessError):
    """An action with the wrong shape or a non-finite entry (NaN, inf)."""


class InteractionError(HarnessError):
    """Interaction used out of order (e.g. ``step`` before ``reset``)."""


class TrackingError(HarnessError):
    """The tracking store cannot be opened or written."""


class CheckpointError(HarnessError):
    """A checkpoint that is missing, corrupt, or from a different configuration."""


class NumericalError(HarnessError):
    """A linear-algebra failure that jitter and retries could not cure."""


def exit_on_error(main: Callable[[], object]) -> None:
    """Run a script's ``main()``; a :class:`HarnessError` ends the script with its one-line message
    on stderr and its exit code, as the CLI does, instead of a traceback.

    For the scripts in ``benchmarks/``: ``if __name__ == "__main__": exit_on_error(main)``.
    """
    try:
        main()
    except HarnessError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)


class MissingArtifactsWarning(UserWarning):
    """A run's artifacts are not in the store (e.g. its artifact folder was not copied with the
    database): whatever needed them (a plot, a test histogram) was not written."""
