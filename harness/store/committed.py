"""Which of a run's files a committed store keeps, the size budget, and the description that says,
in the MLflow UI, what was left out.

The repository commits ``results/runs/mlflow.db`` and, of ``results/runs/mlruns/``, the small files:
summaries, settings and tables (``.json``, ``.md``, ``.csv``) and plots (``.png``): every run's
``result.json``, its per-trial settings, its ``harness eval`` summary and histogram, and the report's
files on the comparison runs (:data:`COMMITTED_SUFFIXES`). Per-trial plots (``.png`` in a ``trialNNN/``
folder, e.g. PILCO's ``prediction_trial007.png``, ~50 kB each) are not: at one per trial they filled
the budget; a report copies the last one of each row's representative run into ``results/`` and onto its
comparison run, which are committed. The repository's ``.gitignore`` lets exactly these through.
Policies, checkpoints, trained models and episode data stay on the machine that ran the run, but for two
kinds of file added by hand (``results/README.md``): the newest checkpoint of a run stopped before its limit, so
that it can be resumed (:func:`stopped_runs`), and each run's last policy up to :data:`MAX_POLICY_BYTES`, so that
``harness eval RUN`` works on a clone (:func:`last_policies`). The budget: no committed file over
:data:`MAX_FILE_BYTES`, all of them together under :data:`BUDGET_BYTES` (a test checks the repository).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from harness.store import layout
from harness.store.reader import Artifact, RunReader

#: the artifact files a committed store keeps (the repository's .gitignore lets these through)
COMMITTED_SUFFIXES = (".json", ".md", ".csv", ".png")
#: the largest artifact file a committed store may hold
MAX_FILE_BYTES = 1_000_000
#: all committed artifact files of ``results/runs`` together (checkpoints of stopped runs included)
BUDGET_BYTES = 30_000_000
#: the largest last policy a committed store keeps (PILCO's: 1-15 kB; SB3's networks stay on the machine that ran them)
MAX_POLICY_BYTES = 100_000
#: where a run's description begins to say which of its files a committed store holds
FILES_HEADING = "\n\n---\n**Files**"


def committed(path: str) -> bool:
    """Whether a run's artifact ``path`` (relative to its artifact root, or longer) is of a kind the committed
    store keeps: a :data:`COMMITTED_SUFFIXES` file that is not a per-trial plot."""
    file = Path(path)
    if file.suffix == ".png" and layout.trial_of_folder(file.parent.name) is not None:
        return False
    return file.suffix in COMMITTED_SUFFIXES


def _megabytes(size: float) -> str:
    return f"{size / 1e6:.1f} MB" if size >= 1e5 else f"{size / 1e3:.0f} kB"


def files_note(artifacts: Sequence[Artifact]) -> str:
    """Markdown: how many of the files a committed store keeps, and the others by folder and kind."""
    if not artifacts:
        return (f"{FILES_HEADING}: none in this store (its artifact folder was not kept; the metrics, params and "
                "tags above are all there is).")
    kept = [a for a in artifacts if committed(a.path)]
    left: dict[str, list[Artifact]] = defaultdict(list)
    for a in artifacts:
        if not committed(a.path):
            folder = Path(a.path).parent.name
            left[f"{'trialNNN' if folder.startswith('trial') else folder or '.'}/*{Path(a.path).suffix}"].append(a)
    text = (f"{FILES_HEADING} in the committed store (results/README.md: .json, .md, .csv and .png files, per-trial plots not): {len(kept)} of "
            f"{len(artifacts)} ({_megabytes(sum(a.size for a in kept))} of {_megabytes(sum(a.size for a in artifacts))}).")
    if left:
        groups = ", ".join(f"`{name}` ({len(files)}, {_megabytes(sum(a.size for a in files))})" for name, files in sorted(left.items()))
        text += (f" Not committed, on the machine that ran it: {groups}; the newest checkpoint of a run stopped before "
                 "its limit and a run's last policy are committed by hand.")
    return text


def describe_files(run: RunReader) -> str:
    """The run's description with its :func:`files_note` (replacing an earlier one; the rest kept)."""
    note = run.tags.get(layout.NOTE_TAG, "")
    return note.split(FILES_HEADING)[0] + files_note(run.all_artifacts())


@dataclass(frozen=True)
class StoppedRun:
    """A run stopped before its limit (status not ``FINISHED``) and its newest checkpoint on this machine.

    Attributes:
        run_id, name, status: the run's.
        checkpoint: artifact path of its newest checkpoint (``checkpoints/ckpt_trialNNN.ckpt``), ``None``
            if this machine holds none (the run cannot be resumed from here).
        file: that checkpoint's local file (``None`` without one, or on a served store).
        size: its size in bytes (0 without one).
    """

    run_id: str
    name: str
    status: str
    checkpoint: str | None
    file: Path | None
    size: int

    @property
    def fits(self) -> bool:
        """Whether the checkpoint is small enough for the committed store (:data:`MAX_FILE_BYTES`)."""
        return self.checkpoint is not None and self.size <= MAX_FILE_BYTES


def stopped_runs(runs: Sequence[RunReader]) -> list[StoppedRun]:
    """The harness runs of ``runs`` (bench runs and sweep cells) that ended before their limit or are still
    open (``KILLED``, ``FAILED``, ``RUNNING``), each with its newest checkpoint: the one file a clone of
    the repository needs to resume it (the store's other checkpoints are older)."""
    from harness.checkpoint import PREFIX
    from harness.datafile import trial_files

    out = []
    for run in runs:
        if run.status == "FINISHED" or run.cell is None:
            continue
        files = {a.path: a for a in run.artifacts(layout.CHECKPOINTS) if not a.is_dir}
        path = next(reversed(trial_files(files, PREFIX).values()), None)  # the newest trial's
        local = run.local_root / path if path is not None and run.local_root is not None else None
        out.append(StoppedRun(run.run_id, run.name, run.status, path, local, files[path].size if path is not None else 0))
    return out


@dataclass(frozen=True)
class LastPolicy:
    """A harness run's last saved policy (the one ``harness eval RUN`` tests) on this machine.

    Attributes:
        run_id, name, status: the run's.
        policy: its artifact path (``policies/policy_trialNNN.policy``).
        file: its local file (``None`` on a served store).
        size: its size in bytes.
    """

    run_id: str
    name: str
    status: str
    policy: str
    file: Path | None
    size: int

    @property
    def fits(self) -> bool:
        """Whether a committed store keeps it (at most :data:`MAX_POLICY_BYTES`)."""
        return self.size <= MAX_POLICY_BYTES


def last_policies(runs: Sequence[RunReader]) -> list[LastPolicy]:
    """The harness runs of ``runs`` (bench runs and sweep cells) that saved a policy, each with its last one:
    the file a clone of the repository needs to test the run's learned controller (the earlier ones are
    the trials' on the way)."""
    out = []
    for run in runs:
        if run.cell is None:
            continue
        saved = run.policy_artifacts()
        if not saved:
            continue
        last = saved[-1]
        local = run.local_root / last.path if run.local_root is not None else None
        out.append(LastPolicy(run.run_id, run.name, run.status, last.path, local, last.size))
    return out
