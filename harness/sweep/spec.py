"""What a sweep runs: learners x tasks x seeds with options and limits (:class:`SweepSpec`), its id,
and the check of every plugin and option before anything starts."""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from harness.errors import OptionError


def parse_names(text: str, what: str) -> tuple[str, ...]:
    """``"pilco, sac"`` -> ``("pilco", "sac")`` (order kept, duplicates dropped)."""
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    if not names:
        raise OptionError(f"--{what} expects a comma-separated list, got {text!r}")
    return names


def parse_seeds(text: str) -> tuple[int, ...]:
    """``"0-4,10"`` -> ``(0, 1, 2, 3, 4, 10)``; ranges are inclusive."""
    seeds: list[int] = []
    for part in (p.strip() for p in str(text).split(",")):
        match = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not match:
            raise OptionError(f"--seeds expects numbers and ranges like 0-9 or 0,3,5-7; got {text!r}")
        lo = int(match.group(1))
        hi = int(match.group(2)) if match.group(2) is not None else lo
        if hi < lo:
            raise OptionError(f"--seeds range {part!r} is empty (write low-high)")
        seeds.extend(range(lo, hi + 1))
    return tuple(dict.fromkeys(seeds))


def format_seeds(seeds: Iterable[int]) -> str:
    """``(0, 1, 2, 5)`` -> ``"0-2,5"`` (the inverse of :func:`parse_seeds` on sorted seeds)."""
    out: list[str] = []
    ordered = sorted(set(seeds))
    i = 0
    while i < len(ordered):
        j = i
        while j + 1 < len(ordered) and ordered[j + 1] == ordered[j] + 1:
            j += 1
        out.append(str(ordered[i]) if i == j else f"{ordered[i]}-{ordered[j]}")
        i = j + 1
    return ",".join(out)


@dataclass(frozen=True)
class Cell:
    """One (learner, task, seed) of a sweep."""

    learner: str
    task: str
    seed: int

    @property
    def label(self) -> str:
        return f"{self.learner}-{self.task}-s{self.seed}"


@dataclass(frozen=True)
class SweepSpec:
    """What a sweep runs. ``assignments`` are the raw ``--set`` pairs, applied to every cell.

    A key ``NAME:key`` (``NAME`` a learner or task of the sweep) applies only to the cells of
    that learner or task, e.g. ``sac:learning_rate=1e-3``.
    """

    learners: tuple[str, ...]
    tasks: tuple[str, ...]
    seeds: tuple[int, ...]
    assignments: tuple[tuple[str, str], ...] = ()
    max_trials: int | None = None
    budget_seconds: float | None = None
    eval_episodes: int = 10

    def cells(self) -> list[Cell]:
        """Task-major, then learner, then seed (the order cells are started in)."""
        return [Cell(l, t, s) for t in self.tasks for l in self.learners for s in self.seeds]

    def canonical(self) -> dict[str, Any]:
        """The spec as plain data, independent of the order names and seeds were given in."""
        return {
            "learners": sorted(self.learners),
            "tasks": sorted(self.tasks),
            "seeds": sorted(self.seeds),
            "set": sorted(dict(self.assignments).items()),
            "max_trials": self.max_trials,
            "budget_seconds": self.budget_seconds,
            "eval_episodes": self.eval_episodes,
        }

    @property
    def sweep_id(self) -> str:
        """12 hex digits of the SHA-256 of :meth:`canonical`: same spec, same id."""
        blob = json.dumps(self.canonical(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode()).hexdigest()[:12]

    def command(self) -> str:
        """The ``harness sweep`` command line that reproduces this spec."""
        parts = ["harness sweep", f"--learners {','.join(self.learners)}", f"--tasks {','.join(self.tasks)}",
                 f"--seeds {format_seeds(self.seeds)}"]
        if self.max_trials is not None:
            parts.append(f"--max-trials {self.max_trials}")
        if self.budget_seconds is not None:
            parts.append(f"--budget-seconds {self.budget_seconds:g}")
        if self.eval_episodes != 10:
            parts.append(f"--eval-episodes {self.eval_episodes}")
        parts += [f"--set {k}={v}" for k, v in dict(self.assignments).items()]
        return " ".join(parts)

    def assignments_for(self, learner: str, task: str) -> list[tuple[str, str]]:
        """The ``--set`` pairs that apply to the cells of ``learner`` on ``task``, scope removed."""
        out = []
        for key, value in self.assignments:
            if ":" in key:
                scope, key = key.split(":", 1)
                if scope not in self.learners and scope not in self.tasks:
                    raise OptionError(
                        f"--set {scope}:{key}=...: '{scope}' is none of this sweep's learners "
                        f"({', '.join(self.learners)}) or tasks ({', '.join(self.tasks)})"
                    )
                if scope not in (learner, task):
                    continue
            out.append((key, value))
        return out


def validate(spec: SweepSpec) -> dict[tuple[str, str], dict[str, Any]]:
    """Load every plugin, route and check every option for every (learner, task) pair.

    Returns, per pair, ``learner_options``, ``task_options`` (raw strings, as the runner takes
    them) and ``extra_params`` (the sweep command, logged with every child run). Raises a one-line
    :class:`~harness.errors.HarnessError` on the first problem.
    """
    from harness.discovery import load_learner, load_task
    from harness.runner import RunConfig, prepare, route_options

    if not spec.seeds:
        raise OptionError("--seeds is empty")
    setups: dict[tuple[str, str], dict[str, Any]] = {}
    for task in spec.tasks:
        load_task(task)  # unknown or broken plugins fail here, before any option is looked at
        for learner in spec.learners:
            load_learner(learner)
            pairs = spec.assignments_for(learner, task)
            try:
                to_learner, to_task = route_options(learner, task, pairs)
                prepare(RunConfig(learner, task, 0, to_learner, to_task, spec.max_trials, spec.budget_seconds, spec.eval_episodes))
            except OptionError as exc:
                raise OptionError(f"{exc} (in the sweep cell {learner} on {task}; scope a --set to one learner or task with NAME:key=value)") from None
            setups[(learner, task)] = {
                "learner_options": to_learner,
                "task_options": to_task,
                "extra_params": {"sweep.command": spec.command()},  # task sizes: every run logs them (runner.run_params)
            }
    return setups
