"""What a learner declares it logs, so that progress lines and reports show it without the harness
knowing its metric or file names.

A learner logs per-trial numbers through ``self.metrics`` and files through ``self.artifacts``
(:class:`harness.learner.Learner`); its class attribute ``logs`` says which of them mean what::

    logs = Logs(
        shown=(("J_after", "J"),),                                    # in each trial's progress line
        timings=(Timing("model_train_seconds", "model_training", "GP training", "GP"),),
        policy_size="policy_parameters",                              # Table 1's policy parameters
        trial_figure=TrialFigure("prediction_trial*.png", "prediction"),
    )
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any


def save_figure(fig: Any, path: Path | str) -> Path:
    """Write a matplotlib figure as an 8-bit palette PNG and return its path.

    A line plot with a legend has few colours: quantised to a 256-colour palette it looks the same as
    matplotlib's RGBA PNG at about 40 % of the bytes (a per-trial prediction plot: 13 kB against 35 kB),
    which is what lets a committed store (:mod:`harness.store.committed`, 30 MB in all) keep every
    trial's plot of its runs. Pillow comes with matplotlib.
    """
    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(path, format="png", optimize=True)
    return Path(path)


@dataclass(frozen=True)
class Timing:
    """A per-trial metric: seconds of one part of a trial's work.

    Attributes:
        metric: the logged name, e.g. ``"policy_opt_seconds"``.
        key: the part's column key in ``walltime_<task>.csv`` (``share_<key>``), e.g. ``"policy_search"``.
        title: its column title in ``walltime_<task>.md``, e.g. ``"policy search"``.
        short: its name in a progress line, e.g. ``"policy"``.
    """

    metric: str
    key: str
    title: str
    short: str


@dataclass(frozen=True)
class TrialFigure:
    """A figure the learner attaches at every hand-over (in the run's ``trialKKK/`` folders).

    Attributes:
        pattern: its file names (``fnmatch``), e.g. ``"prediction_trial*.png"``.
        name: the report's copy of a representative run's last one is ``<name>_<task>_<row>.png``.
    """

    pattern: str
    name: str


@dataclass(frozen=True)
class Logs:
    """What a learner logs besides the runner's records.

    Attributes:
        shown: per-trial metrics shown in progress lines, as ``(metric, label)`` (shown ``label 25.10``)
            or ``(metric, label, format spec)`` (``("planning_horizon", "H", ".0f")``: ``H 40``), in order.
        timings: per-trial seconds of the learner's own work (:class:`Timing`); the report splits the
            wall time into them, the evaluation's and the rest.
        policy_size: the metric holding the policy's number of parameters (Table 1), if logged.
        trial_figure: a figure attached at every hand-over (:class:`TrialFigure`), if any.
    """

    shown: tuple[tuple[str, ...], ...] = ()
    timings: tuple[Timing, ...] = ()
    policy_size: str | None = None
    trial_figure: TrialFigure | None = None


#: the harness's own timing: the evaluation episodes of each hand-over (logged by the runner)
EVALUATION = Timing("eval_seconds", "evaluation", "evaluation", "eval")


def declared_logs(learner: str) -> Logs:
    """The :class:`Logs` of the installed learner ``learner``; empty for one not installed here."""
    from harness.discovery import load_learner
    from harness.errors import HarnessError

    try:
        return load_learner(learner).logs
    except HarnessError:
        return Logs()
