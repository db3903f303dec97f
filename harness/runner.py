"""One benchmark run: a learner on a task with a seed, until solved or out of trials / budget.

The loop (one *trial* = one policy hand-over)::

    for policy in learner.learn(interaction):        # the learner acts only via `interaction`
        result = evaluator(policy)                    # separate env, never counted
        log trial metrics (interaction_seconds, eval_success_rate, eval_cost, wall_seconds, ...)
        if result.solved: interaction_time_to_success = interaction.seconds; stop
        if trial == max_trials: stop
    # BudgetExhaustedError from the interaction ends the run as unsolved ("budget")

*Interaction time to success* is the interaction consumed before the first solved evaluation,
i.e. the data the successful policy was learned from. An unsolved run has none (``None``),
never a number. *Trials to success* is the number of interaction episodes (the initial random
ones included) in that data.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.checkpoint import PREFIX as CHECKPOINT_PREFIX
from harness.checkpoint import Checkpoint, checkpoint_name, global_rng_state, identity_mismatch, load_checkpoint, save_checkpoint, set_global_rng_state
from harness.datafile import LegacyFormatError, is_legacy, legacy_message, trial_files
from harness.discovery import load_learner, load_task
from harness.errors import BudgetExhaustedError, CheckpointError, HarnessError, OptionError, TrackingError
from harness.evaluation import Evaluator
from harness.interaction import Interaction
from harness.interrupts import STOP_AFTER_TRIAL, StopRequested, StopRequests, held_interrupts
from harness.learner import POLICY_PREFIX, Learner
from harness.progress import ProgressReporter, SilentProgress
from harness.provenance import git_sha, package_versions
from harness.seeding import derive_seeds, seed_everything
from harness.store import layout
from harness.task import Episode, Task
from harness.tracking import MemoryTracker, Tracker


@dataclass
class RunConfig:
    """What to run. ``learner_options``/``task_options`` are raw values (strings from the CLI are fine)."""

    learner: str
    task: str
    seed: int = 0
    learner_options: dict[str, Any] = field(default_factory=dict)
    task_options: dict[str, Any] = field(default_factory=dict)
    max_trials: int | None = None
    budget_seconds: float | None = None
    eval_episodes: int = 10

    def validate(self) -> None:
        if self.max_trials is not None and self.max_trials < 1:
            raise OptionError(f"--max-trials must be >= 1, got {self.max_trials}")
        if self.budget_seconds is not None and not (self.budget_seconds > 0 and np.isfinite(self.budget_seconds)):
            raise OptionError(f"--budget-seconds must be a positive number of seconds, got {self.budget_seconds}")
        if self.eval_episodes < 1:
            raise OptionError(f"--eval-episodes must be >= 1, got {self.eval_episodes}")
        if self.seed < 0:
            raise OptionError(f"--seed must be >= 0, got {self.seed}")


@dataclass
class RunResult:
    """Outcome of a run (also logged to the tracker)."""

    run_id: str | None
    learner: str
    task: str
    seed: int
    solved: bool
    interaction_time_to_success: float | None
    trials_to_success: int | None
    trials: int
    interaction_seconds: float
    interaction_episodes: int
    wall_seconds: float
    stop_reason: str
    history: list[dict[str, float]] = field(default_factory=list)

    def summary(self) -> str:
        head = f"{self.learner} on {self.task} (seed {self.seed})"
        if self.solved:
            return (
                f"{head}: SOLVED after {self.interaction_time_to_success:.1f} s of interaction "
                f"({self.trials_to_success} episodes, {self.trials} trials), wall {self.wall_seconds:.0f} s"
            )
        return (
            f"{head}: not solved ({self.stop_reason}) after {self.interaction_seconds:.1f} s of interaction "
            f"({self.interaction_episodes} episodes, {self.trials} trials), wall {self.wall_seconds:.0f} s"
        )


@dataclass
class Prepared:
    """A learner and a task built and validated, ready to run."""

    config: RunConfig
    task: Task
    learner_cls: type[Learner]
    learner_options: dict[str, Any]
    max_trials: int | None
    budget_seconds: float | None


def prepare(config: RunConfig) -> Prepared:
    """Load the plugins and validate every option before anything runs or is logged."""
    config.validate()
    learner_cls = load_learner(config.learner)
    task_cls = load_task(config.task)
    task = task_cls(**config.task_options)
    learner_options = learner_cls.option_set().resolve(config.learner_options)
    max_trials, budget = config.max_trials, config.budget_seconds
    if max_trials is None and budget is None:
        max_trials, budget = learner_cls.default_limits(task.spec)
    return Prepared(config, task, learner_cls, learner_options, max_trials, budget)


def new_learner(prep: Prepared) -> Learner:
    """The run's learner, as :func:`run` builds it (seeded from the run's seed by :func:`~harness.seeding.derive_seeds`)."""
    return prep.learner_cls(prep.task.spec, prep.learner_options, seed=derive_seeds(prep.config.seed)["learner"])


def config_from_identity(identity: Mapping[str, Any]) -> RunConfig:
    """The :class:`RunConfig` that :func:`run_identity` describes (a checkpoint's ``identity``); options
    left unset there (``None``) are left out. For tools that read a run back from its checkpoint."""
    def options(prefix: str) -> dict[str, Any]:
        return {k[len(prefix):]: v for k, v in identity.items() if k.startswith(prefix) and v is not None}

    return RunConfig(identity["learner"], identity["task"], identity["seed"], learner_options=options("learner."),
                     task_options=options("task."), max_trials=identity.get("max_trials"),
                     budget_seconds=identity.get("budget_seconds"), eval_episodes=identity.get("eval_episodes", 10))


def run_params(prep: Prepared) -> dict[str, Any]:
    """Everything that defines the run, flat, for the tracker's params."""
    cfg = prep.config
    params: dict[str, Any] = {
        "learner": cfg.learner,
        "task": cfg.task,
        "seed": cfg.seed,
        "max_trials": prep.max_trials,
        "budget_seconds": prep.budget_seconds,
        "eval_episodes": cfg.eval_episodes,
        "git_sha": git_sha(),
    }
    spec = prep.task.spec
    params.update({"spec.state_dim": spec.state_dim, "spec.action_dim": spec.action_dim, "spec.dt": spec.dt, "spec.horizon": spec.horizon})
    params.update({f"task.{k}": v for k, v in prep.task.options.items()})
    params.update({f"learner.{k}": v for k, v in prep.learner_options.items()})
    params.update({f"version.{k}": v for k, v in package_versions().items()})
    return params


def used_option_params(learner: Learner) -> dict[str, Any]:
    """``used.learner.<k>``: the value the learner uses for each option whose logged value is not it
    (left unset, ``None``: "the task preset's"), so that the store shows what ran."""
    return {f"{layout.USED_PREFIX}learner.{k}": v for k, v in learner.options_used().items() if learner.options.get(k) != v}


def run_tags(config: RunConfig, params: Mapping[str, Any]) -> dict[str, str]:
    """The run's tags at its start: learner, task, seed, its configuration's hash and label (the
    report's, :mod:`harness.configuration`)."""
    from harness.configuration import bench_group_of, config_label

    logged = {k: str(v) for k, v in params.items()}
    return {layout.LEARNER_TAG: config.learner, layout.TASK_TAG: config.task, layout.SEED_TAG: str(config.seed),
            layout.CONFIG_HASH_TAG: bench_group_of(logged)[1], layout.CONFIG_LABEL_TAG: config_label(logged)}


def save_episodes(episodes: tuple[Episode, ...] | list[Episode], path: Path) -> Path:
    """All episodes in one ``.npz``: arrays ``ep{i}_observations/states/actions/costs``."""
    arrays: dict[str, np.ndarray] = {}
    for i, ep in enumerate(episodes):
        arrays[f"ep{i}_observations"] = ep.observations
        arrays[f"ep{i}_states"] = ep.states
        arrays[f"ep{i}_actions"] = ep.actions
        arrays[f"ep{i}_costs"] = ep.costs
        arrays[f"ep{i}_terminated"] = np.asarray(ep.terminated)
    np.savez_compressed(path, **arrays)
    return path


def load_episodes(path: Path) -> list[Episode]:
    """The episodes of a :func:`save_episodes` file, in order (``clipped_actions``/``extra`` are not stored)."""
    try:
        data = np.load(path, allow_pickle=False)
    except OSError as exc:
        raise FileNotFoundError(f"cannot read episodes file {path}: {exc}") from exc
    with data:
        count = sum(1 for key in data.files if key.endswith("_observations"))
        return [
            Episode(observations=data[f"ep{i}_observations"], states=data[f"ep{i}_states"], actions=data[f"ep{i}_actions"],
                    costs=data[f"ep{i}_costs"], terminated=bool(data[f"ep{i}_terminated"]))
            for i in range(count)
        ]


def run_identity(prep: Prepared) -> dict[str, Any]:
    """What must be equal for a checkpoint to be resumed: learner, task, seed, options (but the
    execution options, :attr:`~harness.options.Option.execution`), limits."""
    cfg = prep.config
    identity: dict[str, Any] = {
        "learner": cfg.learner, "task": cfg.task, "seed": cfg.seed, "eval_episodes": cfg.eval_episodes,
        "max_trials": prep.max_trials, "budget_seconds": prep.budget_seconds,
    }
    skip = execution_keys(prep)
    identity.update({f"task.{k}": v for k, v in prep.task.options.items() if f"task.{k}" not in skip})
    identity.update({f"learner.{k}": v for k, v in prep.learner_options.items() if f"learner.{k}" not in skip})
    return identity


def execution_keys(prep: Prepared) -> set[str]:
    """The execution options' :func:`run_identity` keys (a checkpoint may hold them: ignored)."""
    return ({f"task.{k}" for k in type(prep.task).option_set().execution_names()}
            | {f"learner.{k}" for k in prep.learner_cls.option_set().execution_names()})


def option_defaults(prep: Prepared) -> dict[str, Any]:
    """The task's and the learner's option defaults under their :func:`run_identity` keys."""
    task_defaults = type(prep.task).option_set().defaults()
    learner_defaults = prep.learner_cls.option_set().defaults()
    return {**{f"task.{k}": v for k, v in task_defaults.items()}, **{f"learner.{k}": v for k, v in learner_defaults.items()}}


def _latest_valid_checkpoint(tracker: Tracker, destination: Path) -> Checkpoint:
    """The checkpoint of the highest trial that loads (a file cut by a crash is skipped); only
    the files needed are downloaded, newest first."""
    errors = []
    for name in reversed(trial_files(tracker.list_artifacts("checkpoints"), CHECKPOINT_PREFIX).values()):
        if is_legacy(name):  # an older harness's pickle: converted on request, never skipped for an older checkpoint
            raise LegacyFormatError(legacy_message(Path(name).name, "checkpoint", tracker.run_id))
        try:
            return load_checkpoint(tracker.fetch_artifact(name, destination))
        except CheckpointError as exc:
            errors.append(str(exc))
    detail = f" ({errors[0]})" if errors else ""
    raise CheckpointError(f"no usable checkpoint in the run{detail}; start a new run without --resume")


def run(
    config: RunConfig,
    tracker: Tracker | None = None,
    progress: ProgressReporter | None = None,
    workdir: Path | None = None,
    resume_run_id: str | None = None,
) -> RunResult:
    """Run ``config`` to the end and return its :class:`RunResult`.

    The tracker receives params at the start, metrics after every trial, the policy and the
    interaction episodes as artifacts, and the final status: FINISHED (solved or limits
    reached), FAILED (an exception; what was logged is kept) or KILLED (Ctrl-C).

    With ``resume_run_id`` the run continues in that tracked run from its last checkpoint (see
    :mod:`harness.checkpoint`); the continuation is identical to an uninterrupted run.
    """
    prep = prepare(config)
    tracker = tracker or MemoryTracker()
    progress = progress or SilentProgress()
    seeds = derive_seeds(config.seed)
    seed_everything(config.seed)
    spec = prep.task.spec
    identity = run_identity(prep)
    own_workdir = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="harness-run-")) if workdir is None else Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)

    learner = new_learner(prep)
    checkpoint: Checkpoint | None = None
    if resume_run_id is not None:
        if not prep.learner_cls.supports_resume:
            raise CheckpointError(f"learner '{config.learner}' cannot resume runs; start a new run without --resume")
        tracker.resume(resume_run_id)
        try:
            checkpoint = _latest_valid_checkpoint(tracker, workdir / "resume")
        except LegacyFormatError:
            tracker.finish("KILLED")  # not RUNNING: resumable once its checkpoints are converted
            raise
        mismatch = identity_mismatch(checkpoint.identity, identity, option_defaults(prep), ignore=execution_keys(prep))
        if mismatch:
            tracker.finish("FAILED")
            raise CheckpointError(f"run {resume_run_id} was made with other settings ({mismatch}); resume it with the same command")
    else:
        from harness.configuration import settings_of

        params = run_params(prep) | used_option_params(learner)
        tracker.start(
            experiment=layout.task_experiment(config.task),
            run_name=layout.run_name(config.learner, config.task, config.seed, settings_of({k: str(v) for k, v in params.items()})),
            params=params,
            tags=run_tags(config, params),
        )

    interaction = Interaction(prep.task.make_env(), spec, budget_seconds=prep.budget_seconds, seed=seeds["interaction"])
    evaluator = Evaluator(prep.task, n_episodes=config.eval_episodes, seed=seeds["evaluation"])
    history: list[dict[str, float]] = []
    first_trial, wall_offset = 1, 0.0
    held_before: set[int] = set()  # trials after the checkpoint whose records the store already holds
    if checkpoint is not None:
        interaction.load_state_dict(checkpoint.interaction)
        learner.load_state_dict(checkpoint.learner)
        set_global_rng_state(checkpoint.rng)
        history = [dict(h) for h in checkpoint.history]
        first_trial = checkpoint.trial + 1
        wall_offset = history[-1]["wall_seconds"] if history else 0.0
        # params are immutable: the code that ran the trials from here on is a tag of its own
        tracker.set_tags({f"git_sha.resumed_at_trial_{first_trial}": git_sha()})
        logged = tracker.logged_steps("interaction_seconds")
        _log_missing_trials(tracker, history, logged)
        # a trial logged after the newest checkpoint (the last one, which has none, or one between the
        # checkpoints of a learner that writes them every so often) before the run died: the resume repeats
        # it exactly, and its records are not logged a second time
        held_before = {step for step in logged if step > checkpoint.trial}

    total, unit = (prep.max_trials, "trials") if prep.max_trials else (prep.budget_seconds, "s")
    progress.start(f"{config.learner} on {config.task}", total, unit)
    start = time.perf_counter() - wall_offset
    solved_at: tuple[float, int] | None = None
    stop_reason = "learner finished"
    status = "FAILED"
    failure: BaseException | None = None
    learner.status_sink = progress.status  # what the learner is doing within a trial, shown live
    generator = learner.learn(interaction)
    stop = StopRequests.listen()  # kill -USR1: stop once the trial in progress is stored
    checkpointed_at = time.perf_counter()

    def store_checkpoint(trial: int) -> None:
        nonlocal checkpointed_at
        _save_checkpoint(tracker, workdir, Checkpoint(
            identity, trial, history, interaction.state_dict(), learner.state_dict(), global_rng_state()),
            learner.keep_checkpoints)
        checkpointed_at = time.perf_counter()

    try:
        try:
            for trial, policy in enumerate(generator, start=first_trial):
                progress.status(f"evaluating the policy of trial {trial} ({config.eval_episodes} episodes)")
                eval_start = time.perf_counter()
                result = evaluator(policy)
                eval_seconds = time.perf_counter() - eval_start
                record: dict[str, Any] = {
                    "trial": trial,
                    "interaction_seconds": interaction.seconds,
                    "interaction_episodes": len(interaction.episodes),
                    "eval_success_rate": result.success_rate,
                    "eval_cost": result.mean_cost,
                    "wall_seconds": time.perf_counter() - start,
                    "eval_seconds": eval_seconds,
                }
                record.update({f"eval_{k}": v for k, v in result.mean_extra.items()})
                record.update(learner.metrics)
                learner.metrics = {}
                history.append({k: float(v) for k, v in record.items()})
                last = result.solved or (prep.max_trials is not None and trial >= prep.max_trials)
                # a stop request waits for the trial to be stored whole; the checkpoint (files) goes before
                # the metrics (the store's database), so a store that refuses them loses no trial: the
                # resume logs what the checkpoint holds and the store lacks (_log_missing_trials)
                can_checkpoint = learner.supports_resume and not last and interaction.can_checkpoint
                every = learner.checkpoint_every_seconds
                checkpointed = False
                with held_interrupts():
                    _log_trial_artifacts(tracker, learner, policy, interaction, workdir, trial)
                    if can_checkpoint and (every is None or stop.is_set() or time.perf_counter() - checkpointed_at >= every):
                        store_checkpoint(trial)
                        checkpointed = True
                    if trial not in held_before:
                        tracker.log_metrics(_trial_metrics(record), step=trial)
                progress.update({**record, "max_trials": prep.max_trials, "budget_seconds": prep.budget_seconds},
                                completed=trial if prep.max_trials else interaction.seconds)
                if result.solved:
                    solved_at = (interaction.seconds, len(interaction.episodes))
                    stop_reason = "solved"
                    break
                if last:
                    stop_reason = "max trials"
                    break
                if stop.is_set():
                    if can_checkpoint and not checkpointed:  # asked after the checkpoint was passed over: nothing has moved since
                        with held_interrupts():
                            store_checkpoint(trial)
                    raise StopRequested(f"stopped after trial {trial} as asked ({STOP_AFTER_TRIAL.name})")
        except BudgetExhaustedError:
            stop_reason = "budget"
        finally:
            generator.close()
        status = "FINISHED"
    except BaseException as exc:
        failure = exc
        if isinstance(exc, KeyboardInterrupt):
            status = "KILLED"
        raise
    finally:
        stop.restore()
        wall = time.perf_counter() - start
        run_result = RunResult(
            run_id=tracker.run_id,
            learner=config.learner,
            task=config.task,
            seed=config.seed,
            solved=solved_at is not None,
            interaction_time_to_success=None if solved_at is None else solved_at[0],
            trials_to_success=None if solved_at is None else solved_at[1],
            trials=len(history),
            interaction_seconds=interaction.seconds,
            interaction_episodes=len(interaction.episodes),
            wall_seconds=wall,
            stop_reason=stop_reason if status == "FINISHED" else status.lower(),
            history=history,
        )
        try:
            with held_interrupts():  # a second Ctrl-C must not cut the run's final records short
                _finish(tracker, run_result, interaction, workdir, status, prep.learner_cls.supports_resume, failure)
        except TrackingError:
            if failure is None:
                raise  # else the run's own error is the one to see (a store that refuses the end refused the trial first)
        interaction.close()
        evaluator.close()
        if own_workdir:
            import shutil

            shutil.rmtree(workdir, ignore_errors=True)
    progress.finish(run_result.summary())
    return run_result


def _trial_metrics(record: Mapping[str, float]) -> dict[str, float]:
    """A trial's record as logged: every entry but the trial number (the metrics' step)."""
    return {k: v for k, v in record.items() if k != "trial"}


def _log_missing_trials(tracker: Tracker, history: Sequence[Mapping[str, float]], logged: set[int]) -> None:
    """Log the trials of a resumed checkpoint that the store lacks (``logged``: the trials it holds): the
    store refused their metrics (a server down, a database file replaced) after their checkpoint was written."""
    for record in history:
        if int(record["trial"]) not in logged:
            tracker.log_metrics(_trial_metrics(record), step=int(record["trial"]))


def _save_checkpoint(tracker: Tracker, workdir: Path, checkpoint: Checkpoint, keep: int | None = None) -> None:
    """Store ``checkpoint``; with ``keep``, remove the store's checkpoints older than the newest ``keep``."""
    folder = workdir / "checkpoints"
    folder.mkdir(exist_ok=True)
    path = save_checkpoint(checkpoint, folder / checkpoint_name(checkpoint.trial))
    tracker.log_artifact(path, "checkpoints")
    for old in folder.glob(f"{CHECKPOINT_PREFIX}*"):
        if old != path:
            old.unlink(missing_ok=True)  # the tracker keeps its copy; the local one is no longer needed
    if keep is not None:
        stored = trial_files(tracker.list_artifacts("checkpoints"), CHECKPOINT_PREFIX)
        for name in list(stored.values())[:-keep]:
            tracker.delete_artifact(name)


def _log_trial_artifacts(tracker: Tracker, learner: Learner, policy: Any, interaction: Interaction, workdir: Path, trial: int) -> None:
    policy_dir = workdir / "policies"
    policy_dir.mkdir(exist_ok=True)
    try:
        path = learner.save_policy(policy, policy_dir / f"{POLICY_PREFIX}{trial:03d}")
    except Exception as exc:  # a policy that cannot be saved must not kill the run; say so in the run
        tracker.set_tags({f"policy_save_error_trial{trial}": f"{type(exc).__name__}: {exc}"})
    else:
        tracker.log_artifact(path, "policies")
    for extra in learner.artifacts:
        tracker.log_artifact(Path(extra), f"trial{trial:03d}")
    learner.artifacts = []


def _finish(tracker: Tracker, result: RunResult, interaction: Interaction, workdir: Path, status: str,
            resumable: bool = False, failure: BaseException | None = None) -> None:
    """Final metrics, tags, episode data and status; best effort so nothing logged is lost. A run
    stopped before its limit (KILLED) is tagged resumable (its learner checkpoints and it stored a
    trial) or not, and a stopped or failed run says so, and what to do, in its description."""
    try:
        total = layout.TOTAL_SUFFIX
        final = {
            layout.SOLVED: float(result.solved),
            layout.INTERACTION_SECONDS + total: result.interaction_seconds,
            layout.INTERACTION_EPISODES + total: float(result.interaction_episodes),
            layout.WALL_SECONDS + total: result.wall_seconds,
        }
        if result.solved:
            final[layout.TIME_TO_SUCCESS] = result.interaction_time_to_success
            final[layout.TRIALS_TO_SUCCESS] = float(result.trials_to_success)
        tracker.log_metrics(final, step=result.trials)
        tags = {
            layout.SOLVED_TAG: str(result.solved).lower(),
            layout.STOP_REASON_TAG: result.stop_reason,
            layout.TIME_TO_SUCCESS: "" if not result.solved else f"{result.interaction_time_to_success:.6g}",
            layout.TRIALS_TO_SUCCESS: "" if not result.solved else str(result.trials_to_success),
        }
        can_resume = status == "KILLED" and resumable and result.trials > 0
        tags[layout.RESUMABLE_TAG] = str(can_resume).lower()
        tags[layout.NOTE_TAG] = end_note(result, status, can_resume, failure)
        tracker.set_tags(tags)
        if interaction.episodes:
            episodes = Path(layout.EPISODES)
            tracker.log_artifact(save_episodes(interaction.episodes, workdir / episodes.name), str(episodes.parent))
        summary = workdir / layout.RESULT
        summary.write_text(json.dumps({k: v for k, v in asdict(result).items() if k != "history"}, indent=2))
        tracker.log_artifact(summary)
    finally:
        tracker.finish(status)  # type: ignore[arg-type]


def end_note(result: RunResult, status: str, resumable: bool, failure: BaseException | None = None) -> str:
    """How the run (segment) ended, for its description in the MLflow UI (markdown): solved or not, or
    stopped before its limit and whether it is resumable, or failed and why."""
    reached = f"{result.interaction_seconds:g} s of interaction, {result.trials} trials"
    if status == "FINISHED":
        if result.solved:
            return f"**Solved** after {result.interaction_time_to_success:g} s of interaction ({result.trials_to_success} episodes, {result.trials} trials)."
        return f"**Not solved** ({result.stop_reason}) after {reached}: counted as unsolved (+inf) by the report."
    if status == "KILLED":
        then = (f"**Resumable**: the same command plus `--resume {result.run_id}` (a sweep cell: the same sweep command) "
                "continues it from its last checkpoint." if resumable else "Not resumable (no checkpoint): the same command starts it again.")
        return f"**Stopped before its limit** after {reached}, unsolved so far: in no statistic of the report. {then}"
    error = f"{type(failure).__name__}: {failure}".splitlines()[0][:500] if failure is not None else "an error"
    return (f"**Failed** after {reached}: {error}. Counted as unsolved by the report; the same command runs it again "
            "(a sweep: the same sweep command).")


def route_options(learner: str, task: str, pairs: list[tuple[str, Any]]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``key=value`` pairs split into the learner's and the task's options (see ``split_assignments``)."""
    from harness.options import split_assignments

    return split_assignments(pairs, load_learner(learner).option_set(), load_task(task).option_set())


def run_from_names(learner: str, task: str, seed: int = 0, options: Mapping[str, Any] | None = None, **kwargs: Any) -> RunResult:
    """Library shortcut: ``run_from_names("random", "cartpole", max_trials=3)`` (in-memory tracking)."""
    to_learner, to_task = route_options(learner, task, list((options or {}).items()))
    return run(RunConfig(learner, task, seed, to_learner, to_task, **kwargs))


__all__ = ["RunConfig", "RunResult", "prepare", "run", "run_from_names", "HarnessError"]
