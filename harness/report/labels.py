"""Row labels: a learner's name, or where it ran in several sweeps on a task, the settings that tell them apart."""

from __future__ import annotations

import re
from collections import defaultdict
from collections.abc import Sequence

from harness.configuration import option_defaults
from harness.report.records import RunRecord

#: at most this many differing settings in a row label; more, and the label is ``learner@<sweep id>``
LABEL_SETTINGS = 5


def label_runs(records: Sequence[RunRecord]) -> None:
    """Row label = learner. Where a learner-task pair is in several sweeps, each sweep's row is the
    learner with the settings its runs differ in, e.g. ``pilco [horizon=30]`` beside
    ``pilco [horizon=40]``, with ``@<sweep id>`` added where settings do not tell sweeps apart. A
    setting a sweep did not record (an option added after it ran) counts at the installed default."""
    by_pair: dict[tuple[str, str], dict[str, list[RunRecord]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        by_pair[(r.learner, r.task)][r.sweep_id].append(r)
    for (learner, task), by_sweep in by_pair.items():
        if len(by_sweep) == 1:
            names = dict.fromkeys(by_sweep, learner)
        else:
            defaults = option_defaults(learner, task)
            configs = {sweep: {**defaults, **_shared_config(rs)} for sweep, rs in by_sweep.items()}
            names = variant_labels(learner, configs)
        for sweep, rs in by_sweep.items():
            for r in rs:
                r.label = names[sweep]


def _shared_config(records: Sequence[RunRecord]) -> dict[str, str]:
    """The settings every one of ``records`` was run with."""
    shared = dict(records[0].config)
    for r in records[1:]:
        shared = {k: v for k, v in shared.items() if r.config.get(k) == v}
    return shared


def variant_labels(learner: str, configs: dict[str, dict[str, str]]) -> dict[str, str]:
    """``sweep id -> label`` for several sweeps of one learner on one task, from each sweep's shared
    settings (``configs``): the settings recorded in every sweep whose values differ, by their option
    name (``task.horizon`` -> ``horizon``). Settings missing from a sweep (an option added after it
    ran) are not compared. Sweeps whose settings do not tell them apart get ``@<sweep id>`` added;
    with more than :data:`LABEL_SETTINGS` differing settings every label is ``learner@<sweep id>``."""
    recorded = set.intersection(*(set(c) for c in configs.values()))
    differing = sorted(k for k in recorded if len({c[k] for c in configs.values()}) > 1)
    if len(differing) > LABEL_SETTINGS:
        return {sweep: f"{learner}@{sweep}" for sweep in configs}
    short = [k.split(".", 1)[-1] for k in differing]
    names = [name if short.count(name) == 1 else key for key, name in zip(differing, short)]
    labels = {sweep: f"{learner} [{', '.join(f'{n}={c[k]}' for n, k in zip(names, differing))}]" if differing else learner
              for sweep, c in configs.items()}
    shared = {label for label in labels.values() if list(labels.values()).count(label) > 1}
    return {sweep: f"{label}@{sweep}" if label in shared else label for sweep, label in labels.items()}


def file_slug(label: str) -> str:
    """``label`` as a file-name part: ``pilco [horizon=30]`` -> ``pilco_horizon-30``."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", label.replace("=", "-")).strip("_")


def groups(runs: Sequence[RunRecord]) -> dict[str, dict[str, list[RunRecord]]]:
    """``task -> label -> runs`` (sorted by seed), tasks and labels in first-seen order."""
    out: dict[str, dict[str, list[RunRecord]]] = {}
    for r in runs:
        out.setdefault(r.task, {}).setdefault(r.label, []).append(r)
    for by_label in out.values():
        for rs in by_label.values():
            rs.sort(key=lambda r: r.seed)
    return out


# ---------------------------------------------------------------------------------------------
# tables
