"""A run's configuration: what it ran with besides learner, task and seed, its hash and its label.

The configuration is the run's limits and resolved options as logged params (``max_trials``,
``budget_seconds``, ``eval_episodes``, ``learner.<k>``, ``task.<k>``), without the execution options
(threads, kernel: :attr:`harness.options.Option.execution`). Runs of one configuration differ only in
their seeds. Its hash (``bench-<8 hex>``) leaves out the options at their current default, so a run
made before an option existed and one made after, with the option at its default, share it; its label
names the learner and the settings away from the defaults (``pilco [horizon=30]``).

The runner tags every run with both (:data:`~harness.store.layout.CONFIG_HASH_TAG`,
:data:`~harness.store.layout.CONFIG_LABEL_TAG`); ``harness report`` groups `harness bench` runs by the
hash and names the groups' rows by the settings that tell them apart.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Mapping

from harness.errors import HarnessError
from harness.store.layout import LIMIT_PARAMS


def run_config(params: Mapping[str, str]) -> dict[str, str]:
    """The limits and resolved options among a run's params, without the execution options
    (threads, kernel: :attr:`harness.options.Option.execution`) of the installed plugins."""
    skip = execution_keys(params.get("learner", ""), params.get("task", ""))
    return {k: v for k, v in params.items() if (k in LIMIT_PARAMS or k.startswith(("learner.", "task."))) and k not in skip}


@functools.lru_cache(maxsize=None)
def execution_keys(learner: str, task: str) -> frozenset[str]:
    """``learner.<k>``/``task.<k>`` of the execution options of the installed plugins (none for one
    that is not installed here)."""
    from harness.discovery import load_learner, load_task

    keys: set[str] = set()
    for prefix, loader, name in (("learner", load_learner, learner), ("task", load_task, task)):
        try:
            keys |= {f"{prefix}.{k}" for k in loader(name).option_set().execution_names()}
        except HarnessError:
            continue
    return frozenset(keys)


@functools.lru_cache(maxsize=None)
def option_defaults(learner: str, task: str) -> dict[str, str]:
    """The installed plugins' option defaults as logged params (``learner.<k>``, ``task.<k>``);
    empty for a plugin that is not installed here."""
    from harness.discovery import load_learner, load_task

    defaults: dict[str, str] = {}
    for prefix, loader, name in (("learner", load_learner, learner), ("task", load_task, task)):
        try:
            option_set = loader(name).option_set()
        except HarnessError:
            continue
        defaults.update({f"{prefix}.{k}": str(v) for k, v in option_set.defaults().items()})
    return defaults


def bench_group_id(config: Mapping[str, str], defaults: Mapping[str, str]) -> str:
    """``bench-<hash>`` of a run's configuration without the options at their current default
    (``defaults``, params as strings): a run made before an option existed and one made after,
    with the option at its default, did the same and share a group."""
    blob = json.dumps(sorted((k, v) for k, v in config.items() if defaults.get(k) != v))
    return "bench-" + hashlib.sha256(blob.encode()).hexdigest()[:8]


def bench_group_of(params: Mapping[str, str]) -> tuple[dict[str, str], str]:
    """A run's configuration (learner, task, limits, resolved options) from its logged params, and
    the ``bench-<hash>`` that `harness report --sweep` knows its group of `harness bench` runs by."""
    config = {k: v for k, v in params.items() if k in ("learner", "task")} | run_config(params)
    return config, bench_group_id(config, option_defaults(config.get("learner", ""), config.get("task", "")))


def settings_label(config: Mapping[str, str], defaults: Mapping[str, str]) -> str:
    """The options of ``config`` away from ``defaults``, by option name (``task.horizon`` ->
    ``horizon``; the full key where a learner and a task option share a name): ``horizon=30, num_centres=10``."""
    away = sorted(k for k, v in config.items() if k.startswith(("learner.", "task.")) and defaults.get(k) != v)
    short = [k.split(".", 1)[1] for k in away]
    return ", ".join(f"{name if short.count(name) == 1 else key}={config[key]}" for key, name in zip(away, short))


def settings_of(params: Mapping[str, str]) -> str:
    """``horizon=30``: the options a run ran with away from the installed defaults (:func:`settings_label`)."""
    return settings_label(run_config(params), option_defaults(params.get("learner", ""), params.get("task", "")))


def config_label(params: Mapping[str, str]) -> str:
    """``pilco [horizon=30]``: the learner and the options it ran with away from the installed defaults."""
    settings = settings_of(params)
    return f"{params.get('learner', '?')} [{settings}]" if settings else params.get("learner", "?")


def bench_command(config: Mapping[str, str], defaults: Mapping[str, str], seeds: str) -> str:
    """The `harness bench` command behind a bench group: its limits and one ``--set`` per option
    that differs from the installed default (``defaults``, params as strings; an option of a
    plugin not installed here is written out whatever its value), for the seeds ``seeds``."""
    limits = "".join(f" --{k.replace('_', '-')} {config[k]}" for k in ("max_trials", "budget_seconds")
                     if config.get(k) not in (None, "None"))
    sets = "".join(f" --set {k}={v}" for k, v in sorted(config.items())
                   if k.startswith(("learner.", "task.")) and defaults.get(k) != v)
    return (f"harness bench --learner {config.get('learner')} --task {config.get('task')} --seed S{limits}"
            f" --eval-episodes {config.get('eval_episodes')}{sets}  (S = {seeds})")
