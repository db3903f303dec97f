"""Declared, typed, validated options for learners and tasks.

A plugin declares its options as a tuple of :class:`Option`; the harness parses the
``--set key=value`` strings of the CLI against them, rejects unknown keys (listing the valid
ones), wrong types and out-of-range values, and records the resolved values with every run.

Example::

    OPTIONS = (
        Option("n_centres", int, 50, "RBF controller centres", low=1),
        Option("controller", str, "rbf", "controller type", choices=("rbf", "linear")),
    )
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from harness.errors import OptionError

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


@dataclass(frozen=True)
class Option:
    """One declared option.

    Attributes:
        name: key used in ``--set name=value``; letters, digits and ``_``.
        type: one of ``int``, ``float``, ``bool``, ``str``.
        default: value used when the option is not set; ``None`` means "no value"
            (allowed only where the plugin handles it, e.g. "use the preset").
        help: one line shown by ``harness list --options``.
        choices: allowed values, if the option is an enumeration.
        low, high: inclusive bounds for numbers.
        execution: how a run is executed (threads, which of two equivalent kernels), not what it
            computes: logged with the run like every option, but not part of its identity (a
            resume may change it) nor of its configuration (report groups and labels).
    """

    name: str
    type: type
    default: Any
    help: str
    choices: tuple[Any, ...] | None = None
    low: float | None = None
    high: float | None = None
    execution: bool = False

    def parse(self, raw: Any, owner: str) -> Any:
        """Convert ``raw`` (a CLI string or a Python value) to this option's type and check it."""
        where = f"option '{self.name}' of {owner}"
        if raw is None:
            if self.default is None:
                return None
            raise OptionError(f"{where} needs a value ({self._expected()})")
        value: Any
        if self.type is bool:
            if isinstance(raw, bool):
                value = raw
            elif str(raw).strip().lower() in _TRUE:
                value = True
            elif str(raw).strip().lower() in _FALSE:
                value = False
            else:
                raise OptionError(f"{where} expects true/false, got {raw!r}")
        elif self.type is int:
            if isinstance(raw, bool):
                raise OptionError(f"{where} expects an integer, got {raw!r}")
            try:
                as_float = float(str(raw).strip())
            except ValueError:
                raise OptionError(f"{where} expects an integer, got {raw!r}") from None
            if not math.isfinite(as_float) or as_float != int(as_float):
                raise OptionError(f"{where} expects an integer, got {raw!r}")
            value = int(as_float)
        elif self.type is float:
            if isinstance(raw, bool):
                raise OptionError(f"{where} expects a number, got {raw!r}")
            try:
                value = float(str(raw).strip())
            except ValueError:
                raise OptionError(f"{where} expects a number, got {raw!r}") from None
            if not math.isfinite(value):
                raise OptionError(f"{where} expects a finite number, got {raw!r}")
        elif self.type is str:
            value = str(raw).strip()
        else:  # pragma: no cover - guarded by OptionSet
            raise OptionError(f"{where} has unsupported type {self.type!r}")
        if self.choices is not None and value not in self.choices:
            raise OptionError(
                f"{where} must be one of {', '.join(map(str, self.choices))}; got {value!r}"
            )
        if self.low is not None and value < self.low:
            raise OptionError(f"{where} must be >= {self.low}; got {value!r}")
        if self.high is not None and value > self.high:
            raise OptionError(f"{where} must be <= {self.high}; got {value!r}")
        return value

    def _expected(self) -> str:
        if self.choices:
            return "one of " + ", ".join(map(str, self.choices))
        return self.type.__name__

    def describe(self) -> str:
        """One line: ``name (type, default) help``."""
        rng = ""
        if self.choices:
            rng = f", one of {'/'.join(map(str, self.choices))}"
        elif self.low is not None or self.high is not None:
            lo = "" if self.low is None else f"{self.low} <= "
            hi = "" if self.high is None else f" <= {self.high}"
            rng = f", {lo}x{hi}"
        return f"{self.name} ({self.type.__name__}, default {self.default!r}{rng}): {self.help}"


class OptionSet:
    """An ordered, named collection of :class:`Option` with resolution of user values."""

    def __init__(self, options: Iterable[Option], owner: str) -> None:
        self.owner = owner
        self._options: dict[str, Option] = {}
        for opt in options:
            if opt.type not in (int, float, bool, str):
                raise TypeError(f"{owner}: option {opt.name} has unsupported type {opt.type}")
            if opt.name in self._options:
                raise TypeError(f"{owner}: option {opt.name} declared twice")
            self._options[opt.name] = opt

    def __contains__(self, name: object) -> bool:
        return name in self._options

    def __iter__(self):
        return iter(self._options.values())

    def __len__(self) -> int:
        return len(self._options)

    @property
    def names(self) -> list[str]:
        return list(self._options)

    def defaults(self) -> dict[str, Any]:
        return {name: opt.default for name, opt in self._options.items()}

    def execution_names(self) -> set[str]:
        """The options that say how a run executes, not what it is (:attr:`Option.execution`)."""
        return {name for name, opt in self._options.items() if opt.execution}

    def resolve(self, values: Mapping[str, Any] | None) -> dict[str, Any]:
        """Defaults overridden by ``values``; every key checked, every value parsed."""
        resolved = self.defaults()
        for key, raw in (values or {}).items():
            if key not in self._options:
                raise OptionError(unknown_key_message(key, self.names, self.owner))
            resolved[key] = self._options[key].parse(raw, self.owner)
        return resolved


def unknown_key_message(key: str, valid: list[str], owner: str) -> str:
    """One line: the unknown key, a close match if any, and the valid keys."""
    close = difflib.get_close_matches(key, valid, n=1)
    hint = f" Did you mean '{close[0]}'?" if close else ""
    listing = ", ".join(valid) if valid else "(none)"
    return f"unknown option '{key}' for {owner}.{hint} Valid options: {listing}"


def parse_assignments(pairs: Iterable[str]) -> list[tuple[str, str]]:
    """Split ``key=value`` strings; a string without ``=`` or with an empty key is an error."""
    out: list[tuple[str, str]] = []
    for pair in pairs:
        if "=" not in pair:
            raise OptionError(f"--set expects key=value, got {pair!r} (example: --set horizon=30)")
        key, value = pair.split("=", 1)
        key = key.strip()
        if not key:
            raise OptionError(f"--set expects key=value, got {pair!r} (the key is empty)")
        out.append((key, value))
    return out


def split_assignments(
    pairs: Iterable[tuple[str, str]], learner: OptionSet, task: OptionSet
) -> tuple[dict[str, str], dict[str, str]]:
    """Route ``key=value`` pairs to the learner's or the task's options.

    A key may be prefixed ``learner.`` or ``task.``; an unprefixed key goes to whichever of the
    two declares it, and is an error if both or neither do.
    """
    to_learner: dict[str, str] = {}
    to_task: dict[str, str] = {}
    for key, value in pairs:
        if key.startswith("learner."):
            to_learner[key[len("learner."):]] = value
        elif key.startswith("task."):
            to_task[key[len("task."):]] = value
        elif key in learner and key in task:
            raise OptionError(
                f"option '{key}' exists for both {learner.owner} and {task.owner}; "
                f"write learner.{key}=... or task.{key}=..."
            )
        elif key in learner:
            to_learner[key] = value
        elif key in task:
            to_task[key] = value
        else:
            valid = [f"{n}" for n in learner.names] + [f"{n}" for n in task.names]
            raise OptionError(unknown_key_message(key, valid, f"{learner.owner} / {task.owner}"))
    return to_learner, to_task
