"""Plugin discovery through Python entry points.

Learners are announced in the entry-point group ``harness.learners`` and tasks in
``harness.tasks``; the harness's own plugins are registered exactly like a third party's::

    [project.entry-points."harness.learners"]
    my-learner = "my_package.module:MyLearner"

A plugin whose import fails is reported as *broken* with its error, and one whose optional
dependencies are missing as *unavailable* with the ``pip install`` that enables it; neither
breaks the listing or the other plugins.
"""

from __future__ import annotations

import difflib
import importlib.util
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Literal

from harness.errors import PluginLoadError, PluginNotFoundError, PluginUnavailableError
from harness.learner import Learner
from harness.task import Task

LEARNER_GROUP = "harness.learners"
TASK_GROUP = "harness.tasks"
_KIND = {LEARNER_GROUP: "learner", TASK_GROUP: "task"}
_BASE = {LEARNER_GROUP: Learner, TASK_GROUP: Task}

Status = Literal["ok", "broken", "unavailable"]


@dataclass
class PluginInfo:
    """What discovery knows about one entry point.

    Attributes:
        name: entry-point name (what users type).
        group: entry-point group.
        value: ``module:attr`` reference.
        distribution: ``name version`` of the package that announces it.
        status: ``ok``, ``broken`` (import failed / not a plugin) or ``unavailable``
            (optional dependencies missing).
        description: the plugin's one-line description (if it loaded).
        error: why it is broken or unavailable, with the fix.
        cls: the loaded class (``None`` unless ``ok`` or ``unavailable``).
    """

    name: str
    group: str
    value: str
    distribution: str
    status: Status
    description: str = ""
    error: str = ""
    cls: type | None = None


def _distribution(ep: EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return f"{dist.name} {dist.version}" if dist is not None else "?"


def _install_hint(cls: type, dist: str) -> str:
    extra = getattr(cls, "extra", None)
    package = dist.split(" ")[0] if dist != "?" else "pilco-harness"
    return f"pip install '{package}[{extra}]'" if extra else f"pip install {' '.join(cls.requires)}"


def _inspect(ep: EntryPoint) -> PluginInfo:
    kind = _KIND[ep.group]
    info = PluginInfo(ep.name, ep.group, ep.value, _distribution(ep), "broken")
    try:
        cls = ep.load()
    except Exception as exc:  # any import-time failure of a third-party module
        info.error = f"cannot import {ep.value} ({type(exc).__name__}: {exc})"
        return info
    base = _BASE[ep.group]
    if not (isinstance(cls, type) and issubclass(cls, base)):
        info.error = f"{ep.value} is not a subclass of harness.{kind}.{base.__name__}"
        return info
    info.cls = cls
    info.description = cls.description
    missing = [mod for mod in cls.requires if importlib.util.find_spec(mod) is None]
    if missing:
        info.status = "unavailable"
        info.error = f"needs {', '.join(missing)}: {_install_hint(cls, info.distribution)}"
        return info
    info.status = "ok"
    return info


def _entry_points(group: str) -> list[EntryPoint]:
    seen: dict[str, EntryPoint] = {}
    for ep in entry_points(group=group):
        seen.setdefault(ep.name, ep)  # first distribution wins on a name clash
    return sorted(seen.values(), key=lambda ep: ep.name)


def list_plugins(group: str) -> list[PluginInfo]:
    """All plugins of ``group`` with their status; never raises for a bad plugin."""
    return [_inspect(ep) for ep in _entry_points(group)]


def _load(group: str, name: str) -> type:
    kind = _KIND[group]
    eps = {ep.name: ep for ep in _entry_points(group)}
    if name not in eps:
        valid = sorted(eps)
        close = difflib.get_close_matches(name, valid, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        raise PluginNotFoundError(f"unknown {kind} '{name}'.{hint} Available {kind}s: {', '.join(valid) or '(none)'}")
    info = _inspect(eps[name])
    if info.status == "broken":
        raise PluginLoadError(f"{kind} plugin '{name}' from {info.distribution} is broken: {info.error}")
    if info.status == "unavailable":
        raise PluginUnavailableError(f"{kind} '{name}' is not installed completely; {info.error}")
    assert info.cls is not None
    return info.cls


def load_learner(name: str) -> type[Learner]:
    """The learner class registered as ``name``; a typed, one-line error otherwise."""
    return _load(LEARNER_GROUP, name)


def load_task(name: str) -> type[Task]:
    """The task class registered as ``name``; a typed, one-line error otherwise."""
    return _load(TASK_GROUP, name)
