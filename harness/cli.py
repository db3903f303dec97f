"""The ``harness`` command line.

    harness list [--options]
    harness bench --learner L --task T [--seed S] [--max-trials N | --budget-seconds X] [--set k=v ...]
    harness sweep --learners L1,L2 --tasks T1,T2 --seeds 0-9 [--executor local|ray] [--workers N] [--set k=v ...]
    harness report [--sweep ID] [--out results/]
    harness store migrate RUN_ID... | --all [--yes]
    harness store serve [--dir DIR] [--port 5000] [--db-port 5432]
    harness --version

Errors caused by input (unknown plugin or option, bad value, unwritable store, ...) print one
line naming the problem and the fix and exit with status 2; ``--debug`` shows the traceback.
Heavy modules (mlflow, torch) are imported only by the commands that need them.
"""

from __future__ import annotations

import difflib
import os
import sys
from typing import Any

import click

from harness import __version__
from harness.errors import HarnessError, PluginNotFoundError, TrackingError


class _Context:
    debug: bool = False


def _fail(message: str, code: int) -> None:
    click.echo(f"error: {message}", err=True)
    sys.exit(code)


def _guarded(fn):
    """Turn exceptions into one-line errors (tracebacks only with --debug)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any):
        try:
            return fn(*args, **kwargs)
        except HarnessError as exc:
            if _Context.debug:
                raise
            _fail(str(exc), exc.exit_code)
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            sys.exit(130)
        except BrokenPipeError:
            # the reader of the output went away (`harness ... | head`): stop quietly, as Unix tools do
            # (stdout pointed at /dev/null so that the interpreter's final flush does not fail again)
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            sys.exit(141)
        except click.exceptions.Exit:
            raise
        except click.ClickException:
            raise
        except Exception as exc:
            if _Context.debug:
                raise
            _fail(f"unexpected {type(exc).__name__}: {exc} (run with --debug for the traceback)", 1)

    return wrapper


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="harness")
@click.option("--debug", is_flag=True, help="Show full tracebacks on errors.")
def main(debug: bool) -> None:
    """Benchmark data-efficient RL learners (PILCO, SAC, PPO, ...) on control tasks.

    Learners and tasks are plugins found through the entry-point groups ``harness.learners`` and
    ``harness.tasks``. Results go to MLflow (default: ./mlflow.db, no server needed).
    """
    _Context.debug = debug

    from harness.interrupts import terminate_as_interrupt

    terminate_as_interrupt()  # `kill PID` / a scheduler's SIGTERM: the Ctrl-C path (run KILLED, resume hint)


@main.command("list")
@click.argument("names", nargs=-1, metavar="[NAME]...")
@click.option("--options", "show_options", is_flag=True, help="Also list every plugin's options.")
@_guarded
def list_command(names: tuple[str, ...], show_options: bool) -> None:
    """List learners and tasks, with broken or unavailable plugins and why.

    With NAMEs (learners or tasks, e.g. `harness list mc-pilco unicycle`): only those, with their options.
    """
    from harness.discovery import LEARNER_GROUP, TASK_GROUP, list_plugins

    groups = [(title, list_plugins(group)) for title, group in (("Learners", LEARNER_GROUP), ("Tasks", TASK_GROUP))]
    if names:
        known = sorted({p.name for _, plugins in groups for p in plugins})
        for name in names:
            if name not in known:
                close = difflib.get_close_matches(name, known, n=1)
                hint = f" Did you mean '{close[0]}'?" if close else ""
                raise PluginNotFoundError(f"no learner or task named '{name}'.{hint} Installed: {', '.join(known) or '(none)'}")
        groups = [(title, [p for p in plugins if p.name in names]) for title, plugins in groups]
        groups = [(title, plugins) for title, plugins in groups if plugins]
        show_options = True
    for title, plugins in groups:
        click.echo(f"{title}:")
        if not plugins:
            click.echo("  (none installed)")
        width = max((len(p.name) for p in plugins), default=0)
        for p in plugins:
            if p.status == "ok":
                click.echo(f"  {p.name:<{width}}  {p.description}")
            else:
                click.echo(f"  {p.name:<{width}}  [{p.status.upper()}] {p.error}  ({p.distribution})")
            if show_options and p.cls is not None:
                for opt in p.cls.option_set():
                    click.echo(f"  {'':<{width}}    --set {opt.describe()}")
        click.echo("")


def _parse_budget(value: str | None) -> float | None:
    if value is None:
        return None
    try:
        budget = float(value)
    except ValueError:
        raise HarnessError(f"--budget-seconds expects a number of seconds, got {value!r}") from None
    return budget


@main.command("bench")
@click.option("--learner", "-l", required=True, help="Learner name (see `harness list`).")
@click.option("--task", "-t", required=True, help="Task name (see `harness list`).")
@click.option("--seed", default=0, show_default=True, type=int, help="Run seed (>= 0).")
@click.option("--max-trials", type=int, default=None, help="Stop after this many policy hand-overs.")
@click.option("--budget-seconds", default=None, help="Stop when this much interaction (system seconds) is used.")
@click.option("--set", "assignments", multiple=True, metavar="KEY=VALUE", help="Learner or task option (repeatable; prefix learner./task. if ambiguous).")
@click.option("--eval-episodes", default=10, show_default=True, type=int, help="Evaluation episodes per hand-over.")
@click.option("--tracking-uri", default=None, help="MLflow store (default: $MLFLOW_TRACKING_URI or sqlite:///./mlflow.db).")
@click.option("--no-tracking", is_flag=True, help="Do not log to MLflow (results are printed only).")
@click.option("--quiet", "-q", is_flag=True, help="No progress output.")
@click.option("--resume", "resume", is_flag=False, flag_value="latest", default=None, metavar="[RUN_ID]",
              help="Continue a run from its last checkpoint (no id: the newest unfinished run of this learner/task/seed).")
@_guarded
def bench_command(
    learner: str,
    task: str,
    seed: int,
    max_trials: int | None,
    budget_seconds: str | None,
    assignments: tuple[str, ...],
    eval_episodes: int,
    tracking_uri: str | None,
    no_tracking: bool,
    quiet: bool,
    resume: str | None,
) -> None:
    """Run one learner on one task and report its interaction time to success.

    Ctrl-C or `kill PID` stops the run at once, `kill -USR1 PID` after the trial in progress;
    either way it is marked KILLED and continues with the same command plus --resume.
    """
    from harness.options import parse_assignments
    from harness.progress import RichProgress, SilentProgress
    from harness.runner import RunConfig, prepare, route_options, run
    from harness.tracking import MemoryTracker, MlflowTracker

    to_learner, to_task = route_options(learner, task, parse_assignments(assignments))
    config = RunConfig(learner, task, seed, to_learner, to_task, max_trials, _parse_budget(budget_seconds), eval_episodes)
    prepare(config)  # validate everything before the store is touched
    if resume is not None and no_tracking:
        raise HarnessError("--resume needs the tracking store (drop --no-tracking)")
    tracker = MemoryTracker() if no_tracking else MlflowTracker(tracking_uri)
    if resume == "latest":
        resume = tracker.find_resumable(task, learner, seed)
        if resume is None:
            raise HarnessError(f"no unfinished run of {learner} on {task} with seed {seed} in {tracker.tracking_uri} to resume")
    from harness.interrupts import STOP_AFTER_TRIAL, StopRequested, catch_stop_requests_early

    catch_stop_requests_early()  # a kill -USR1 before the run listens (loading a checkpoint) is kept, not fatal
    if not quiet and STOP_AFTER_TRIAL is not None:
        click.echo(f"to stop (resumable): Ctrl-C or kill {os.getpid()} now; kill -{STOP_AFTER_TRIAL.name[3:]} {os.getpid()} "
                   "after the trial in progress", err=True)
    from harness.discovery import load_learner

    progress = SilentProgress() if quiet else RichProgress(logs=load_learner(learner).logs)
    try:
        result = run(config, tracker=tracker, progress=progress, resume_run_id=resume)
    except KeyboardInterrupt as stopped:
        what = str(stopped) if isinstance(stopped, StopRequested) else "interrupted"
        click.echo(f"{what}: run {tracker.run_id} marked KILLED; continue it with the same command plus --resume {tracker.run_id}", err=True)
        sys.exit(130)
    if quiet:
        click.echo(result.summary())
    if isinstance(tracker, MlflowTracker):
        from harness.configuration import bench_group_of
        from harness.store import Store

        _, group = bench_group_of(Store(tracker.tracking_uri, tracker.client).run(result.run_id).params)
        click.echo(f"MLflow run {result.run_id} in experiment '{task}' at {tracker.tracking_uri}")
        from harness.store.connection import browse_command

        click.echo(f"  browse: {browse_command(tracker.tracking_uri)}")
        click.echo(f"  report: harness report --tracking-uri {tracker.tracking_uri} --sweep {group}"
                   "  (the runs of this configuration, all seeds)")


@main.command("eval")
@click.argument("run_id")
@click.option("--episodes", default=1000, show_default=True, type=click.IntRange(min=1), help="Test episodes.")
@click.option("--seed", default=12345, show_default=True, type=click.IntRange(min=0), help="Seed of the test episodes' initial states.")
@click.option("--trial", default=None, type=click.IntRange(min=1), help="Test this trial's policy (default: the last saved).")
@click.option("--out", "out_dir", default=None, type=click.Path(file_okay=False), help="Folder for the histogram and summary.")
@click.option("--tracking-uri", default=None, help="MLflow store (default: $MLFLOW_TRACKING_URI or sqlite:///./mlflow.db).")
@_guarded
def eval_command(run_id: str, episodes: int, seed: int, trial: int | None, out_dir: str | None, tracking_uri: str | None) -> None:
    """Test a finished run's saved policy on many episodes (success rate, final-distance histogram)."""
    from pathlib import Path

    from harness.testrun import evaluate_saved_policy

    report = evaluate_saved_policy(run_id, episodes, seed, tracking_uri, Path(out_dir) if out_dir else None, trial)
    from harness.statistics import rate_interval

    low, high = rate_interval(report.success_rate, report.episodes)
    click.echo(
        f"{report.task}: {report.policy_artifact} succeeded in {100 * report.success_rate:.1f}% of {report.episodes} "
        f"test episodes (95 % interval {100 * low:.1f}-{100 * high:.1f}%; mean cost {report.mean_cost:.2f})"
    )
    if report.histogram is not None:
        click.echo(f"  histogram of final distances: {report.histogram}")
    click.echo(f"  summary: {report.summary_path} (also logged to the run under test/)")


@main.group("store")
def store_group() -> None:
    """Maintain a tracking store: convert runs of older harness versions (migrate); a local store copied
    to another path (a clone): relocate it, check it, describe its runs' files; list the checkpoints a clone
    needs to resume the runs stopped before their limit, and the policies it needs to test the runs."""


@store_group.command("migrate")
@click.argument("run_ids", nargs=-1, metavar="[RUN_ID]...")
@click.option("--all", "all_runs", is_flag=True, help="Every run of the store with a checkpoint or policy in the old format.")
@click.option("--tracking-uri", default=None, help="MLflow store (default: $MLFLOW_TRACKING_URI or sqlite:///./mlflow.db).")
@click.option("--yes", is_flag=True, help="Do not ask before reading the old files (they are pickles: reading runs code).")
@_guarded
def migrate_command(run_ids: tuple[str, ...], all_runs: bool, tracking_uri: str | None, yes: bool) -> None:
    """Convert runs' checkpoints and policies from the old pickled format to the data-only one, once.

    Older harness versions pickled checkpoints and policies; reading a pickle runs code stored in it,
    so the harness now refuses them. This reads each old file of the given runs once, on your request,
    and writes its data-only equivalent to the run (old files stay, unused). Only for stores you trust.
    """
    from harness.migration import WARNING, migrate_run, runs_with_legacy_files
    from harness.store import Store

    if bool(run_ids) == all_runs:
        raise HarnessError("give the RUN_IDs to convert or --all (not both)")
    store = Store(tracking_uri)
    uri = store.uri
    for run_id in run_ids:
        store.run(run_id)  # an unknown id fails before anything is read
    targets = list(run_ids) or runs_with_legacy_files(store)
    if not targets:
        click.echo(f"no run in {uri} has files in the old format")
        return
    click.echo(f"warning: {WARNING}", err=True)
    if not yes:
        click.confirm(f"convert the old files of {len(targets)} run(s) in {uri}?", abort=True, err=True)
    for run_id in targets:
        if not migrate_run(store, run_id, say=click.echo):
            click.echo(f"run {run_id}: nothing to convert")


@main.command("sweep")
@click.option("--learners", required=True, help="Comma-separated learner names, e.g. pilco,sac.")
@click.option("--tasks", required=True, help="Comma-separated task names, e.g. cartpole,double-pendulum.")
@click.option("--seeds", default="0", show_default=True, help="Seeds: numbers and inclusive ranges, e.g. 0-9 or 0,3,5-7.")
@click.option("--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True,
              help="local: a process pool on this machine; ray: Ray (embedded, or --address of a cluster; pip install 'pilco-harness[ray]').")
@click.option("--workers", type=int, default=None, help="Cells at a time (default: CPU cores - 1, at least 1; Ray cluster: its CPUs).")
@click.option("--address", default=None, help="Ray cluster address (e.g. ray://head:10001 or auto); default: embedded Ray.")
@click.option("--max-trials", type=int, default=None, help="Stop every run after this many policy hand-overs.")
@click.option("--budget-seconds", default=None, help="Stop every run when this much interaction (system seconds) is used.")
@click.option("--set", "assignments", multiple=True, metavar="KEY=VALUE",
              help="Option for every cell (repeatable); NAME:key=value applies it only to learner or task NAME.")
@click.option("--eval-episodes", default=10, show_default=True, type=int, help="Evaluation episodes per hand-over.")
@click.option("--tracking-uri", default=None, help="MLflow store (default: $MLFLOW_TRACKING_URI or sqlite:///./mlflow.db).")
@click.option("--quiet", "-q", is_flag=True, help="No progress view; one line per cell at the end.")
@_guarded
def sweep_command(
    learners: str,
    tasks: str,
    seeds: str,
    executor: str,
    workers: int | None,
    address: str | None,
    max_trials: int | None,
    budget_seconds: str | None,
    assignments: tuple[str, ...],
    eval_episodes: int,
    tracking_uri: str | None,
    quiet: bool,
) -> None:
    """Run learners x tasks x seeds as child runs of one MLflow sweep run.

    Re-running the same command resumes the sweep: finished cells are skipped, interrupted ones
    continue from their last checkpoint, failed ones run again. Exits with status 1 if any cell
    failed. `kill -USR1 PID` drains the sweep: no more cells start, running local cells stop
    after their trial in progress (exit status 130).
    """
    from harness.options import parse_assignments
    from harness.sweep import SweepSpec, parse_names, parse_seeds, run_sweep
    from harness.sweep.progress import RichSweepProgress, SilentSweepProgress

    spec = SweepSpec(
        learners=parse_names(learners, "learners"),
        tasks=parse_names(tasks, "tasks"),
        seeds=parse_seeds(seeds),
        assignments=tuple(parse_assignments(assignments)),
        max_trials=max_trials,
        budget_seconds=_parse_budget(budget_seconds),
        eval_episodes=eval_episodes,
    )
    from harness.tracking import resolve_tracking_uri

    if address and resolve_tracking_uri(tracking_uri).startswith("sqlite:"):
        click.echo(f"note: Ray workers on other machines must reach {resolve_tracking_uri(tracking_uri)} (a shared filesystem); "
                   "otherwise run `mlflow server` and pass --tracking-uri http://HOST:5000", err=True)
    from harness.interrupts import STOP_AFTER_TRIAL, catch_stop_requests_early

    catch_stop_requests_early()  # a kill -USR1 before the driver listens (opening the store) is kept, not fatal
    if STOP_AFTER_TRIAL is not None:  # also with -q: a sweep in the background is stopped by its pid
        click.echo(f"to stop (resumable): kill -{STOP_AFTER_TRIAL.name[3:]} {os.getpid()} (no new cells; the running ones "
                   f"stop after their trial in progress), kill {os.getpid()} at once", err=True)
    progress = SilentSweepProgress() if quiet else RichSweepProgress()
    result = run_sweep(spec, tracking_uri=tracking_uri, executor=executor, workers=workers, address=address, progress=progress)
    if quiet:
        for retry in result.retries:
            click.echo(retry.line())
        for outcome in result.outcomes:
            click.echo(outcome.line())
    counts = {s: len(result.with_status(s)) for s in ("finished", "skipped", "failed", "stopped")}
    stopped = f", {counts['stopped']} stopped as asked, {result.not_started} not started" if result.stopped_early else ""
    click.echo(
        f"sweep {result.sweep_id}: {counts['finished']} finished, {counts['skipped']} skipped (finished before), "
        f"{counts['failed']} failed{stopped}; parent runs ({'; '.join(result.parent_lines())}) at {result.tracking_uri}"
    )
    click.echo(f"  report: harness report --sweep {result.sweep_id} --tracking-uri {result.tracking_uri}")
    if result.stopped_early:
        click.echo("stopped as asked (SIGUSR1); re-run the same command to continue: stopped cells resume from their "
                   "checkpoints, unstarted ones start", err=True)
        sys.exit(130)
    if counts["failed"]:
        click.echo(f"error: {counts['failed']} cell(s) failed (see above); re-run the same command to retry them", err=True)
        sys.exit(1)


@main.command("report")
@click.option("--tracking-uri", default=None, help="MLflow store (default: $MLFLOW_TRACKING_URI or sqlite:///./mlflow.db).")
@click.option("--sweep", "sweeps", multiple=True, metavar="ID", help="Sweep id (repeatable); default: every sweep in the store.")
@click.option("--out", default="results", show_default=True, type=click.Path(file_okay=False), help="Directory for tables and figures.")
@click.option("--table1-learner", default="pilco", show_default=True, help="Learner whose runs fill Table 1.")
@click.option("--fig5-task", "fig5_tasks", multiple=True, metavar="TASK",
              help="A task of Fig. 5, a panel each (repeatable); default: cartpole, dmc-cartpole, double-pendulum, unicycle.")
@click.option("--literature", default=None, type=click.Path(dir_okay=False), help="Sourced literature values for Fig. 5 (default: OUT/literature_fig5.csv if present).")
@click.option("--include-bench", is_flag=True, help="Also report `harness bench` runs, grouped by configuration as pseudo-sweeps bench-<hash>.")
@click.option("--publish/--no-publish", default=None,
              help="Write each task's comparison into the store (runs 'comparison · TASK'); default: when --sweep is given.")
@_guarded
def report_command(tracking_uri: str | None, sweeps: tuple[str, ...], out: str, table1_learner: str, fig5_tasks: tuple[str, ...],
                   literature: str | None, include_bench: bool, publish: bool | None) -> None:
    """Comparison tables, Table 1, Fig. 5 and learning curves from MLflow alone (nothing is re-run)."""
    from pathlib import Path

    import warnings

    from harness.errors import MissingArtifactsWarning
    from harness.report import make_report
    from harness.report.fig5 import FIG5_TASKS
    from harness.store import Store
    from harness.store.connection import browse_command

    store = Store(tracking_uri)
    publish = bool(sweeps) if publish is None else publish
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MissingArtifactsWarning)
        written = make_report(store, Path(out), list(sweeps) or None, table1_learner, fig5_tasks or FIG5_TASKS,
                              Path(literature) if literature else None, include_bench, publish)
    for warning in caught:
        if issubclass(warning.category, MissingArtifactsWarning):
            click.echo(f"warning: {warning.message}", err=True)
        else:
            warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)
    for path in written:
        click.echo(str(path))
    if publish:
        click.echo(f"comparisons written into the store: the runs 'comparison · TASK' in each task's experiment "
                   f"(browse: {browse_command(store.uri)})")


#: the store a `harness store` command works on
_store_uri = click.option("--tracking-uri", default=None, help="The SQLite store (default: $MLFLOW_TRACKING_URI or sqlite:///./mlflow.db).")


@store_group.command("relocate")
@_store_uri
@_guarded
def store_relocate_command(tracking_uri: str | None) -> None:
    """Point every artifact location of the store at its own folder (after a copy or a clone elsewhere)."""
    from harness.store.connection import resolve_tracking_uri
    from harness.store.relocate import relocate

    uri = resolve_tracking_uri(tracking_uri)
    done = relocate(uri)
    if not done.total:
        click.echo(f"{uri}: every artifact location is already in the store's folder")
        return
    counts = ", ".join(f"{n} {table}" for table, n in done.rewritten.items())
    click.echo(f"{uri}: {counts} now keep their artifacts in the store's folder (before: {', '.join(done.previous_roots)})")


@store_group.command("check")
@_store_uri
@_guarded
def store_check_command(tracking_uri: str | None) -> None:
    """Say, per run, where MLflow (and `mlflow ui`) finds its files; exit 1 if the store needs relocating."""
    from harness.store import Store
    from harness.store.relocate import check

    store = Store(tracking_uri)
    runs = check(store)
    moved = [r for r in runs if not r.located]
    empty = [r for r in runs if r.located and not r.files]
    click.echo(f"{store.uri}: {len(runs)} runs, {sum(r.files for r in runs)} files; {len(runs) - len(moved)} located in the store's folder, "
               f"{len(empty)} of them without any file here")
    for r in empty:
        click.echo(f"  no files: {r.run_id} {r.name} ({r.status})")
    if moved:
        for r in moved[:20]:
            click.echo(f"  recorded elsewhere: {r.run_id} {r.name}" + (" (its files are in this store's folder)" if r.moved else ""))
        _fail(f"{len(moved)} runs record artifact locations outside the store's folder; "
              f"run `harness store relocate --tracking-uri {store.uri}`", 1)


@store_group.command("serve")
@click.option("--dir", "directory", default="mlflow-server", show_default=True, type=click.Path(file_okay=False),
              help="The store's folder: PostgreSQL cluster (created if absent), artifacts, logs.")
@click.option("--port", default=5000, show_default=True, type=click.IntRange(1, 65535), help="Port of the MLflow server.")
@click.option("--db-port", default=5432, show_default=True, type=click.IntRange(1, 65535), help="Port of PostgreSQL (127.0.0.1 only).")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address the MLflow server listens on (0.0.0.0: every machine that reaches this one).")
@click.option("--workers", default=2, show_default=True, type=click.IntRange(min=1), help="MLflow server worker processes.")
@_guarded
def store_serve_command(directory: str, port: int, db_port: int, host: str, workers: int) -> None:
    """Serve a store to many writers: MLflow on PostgreSQL, artifacts through the server; Ctrl-C or `kill PID` stops both."""
    import time
    from pathlib import Path

    from harness.store.server import StoreServer

    server = StoreServer(Path(directory), port=port, db_port=db_port, host=host, workers=workers)
    click.echo(f"starting the store {server.paths.directory} (PostgreSQL on 127.0.0.1:{db_port}, MLflow on {host}:{port}) ...", err=True)
    try:
        server.start()
        shown = server.uri if host not in ("0.0.0.0", "::") else f"http://{os.uname().nodename}:{port}"
        click.echo(f"tracking URI: {shown}")
        click.echo(f"  sweep against it: harness sweep --learners pilco --tasks cartpole --seeds 0-9 --executor ray --tracking-uri {shown}")
        click.echo("  stop: Ctrl-C", err=True)
        while (problem := server.problem()) is None:
            time.sleep(1)
        raise TrackingError(problem)
    except KeyboardInterrupt:
        click.echo("stopping the MLflow server and PostgreSQL ...", err=True)
    finally:
        server.stop()
    click.echo(f"stopped; the store is kept in {server.paths.directory}", err=True)


@store_group.command("describe")
@_store_uri
@_guarded
def store_describe_command(tracking_uri: str | None) -> None:
    """Write into each run's description which of its files a committed store keeps and which it leaves out."""
    from harness.store import Store, layout
    from harness.store.committed import BUDGET_BYTES, committed, describe_files

    store = Store(tracking_uri)
    kept = 0
    runs = store.search(None)
    for run in runs:
        store.set_tags(run.run_id, {layout.NOTE_TAG: describe_files(run)})
        kept += sum(a.size for a in run.all_artifacts() if committed(a.path))
    click.echo(f"{store.uri}: {len(runs)} run descriptions say what is committed; the committed kinds of files come to "
               f"{kept / 1e6:.1f} MB here (budget {BUDGET_BYTES / 1e6:.0f} MB, results/README.md)")


@store_group.command("policies")
@_store_uri
@click.option("--paths", is_flag=True, help="Print only the local files to commit, one per line (for `git add -f`).")
@_guarded
def store_policies_command(tracking_uri: str | None, paths: bool) -> None:
    """List each run's last saved policy (what `harness eval RUN` tests): the files a clone needs to test the runs."""
    from harness.store import Store
    from harness.store.committed import MAX_POLICY_BYTES, last_policies

    store = Store(tracking_uri)
    found = last_policies(store.search(None))
    keep = [p for p in found if p.fits and p.file is not None]
    if paths:
        for p in keep:
            click.echo(os.path.relpath(p.file))
        return
    for p in found:
        size = f"{p.size / 1e3:.1f} kB" if p.fits else f"{p.size / 1e3:.0f} kB, over the {MAX_POLICY_BYTES / 1e3:.0f} kB a committed policy may have: stays on this machine"
        click.echo(f"{p.run_id[:8]} {p.status:8} {p.name}: {p.policy} ({size})")
    uri = f" --tracking-uri {tracking_uri}" if tracking_uri else ""
    click.echo(f"{store.uri}: {len(found)} runs have a saved policy here, {len(keep)} small enough to commit "
               f"({sum(p.size for p in keep) / 1e3:.0f} kB). Commit them with the store, no run writing: "
               f"git add -f $(harness store policies --paths{uri})")


@store_group.command("checkpoints")
@_store_uri
@click.option("--paths", is_flag=True, help="Print only the local files to commit, one per line (for `git add -f`).")
@_guarded
def store_checkpoints_command(tracking_uri: str | None, paths: bool) -> None:
    """List the runs stopped before their limit and the newest checkpoint of each: the files a clone needs to resume them."""
    from harness.store import Store
    from harness.store.committed import BUDGET_BYTES, MAX_FILE_BYTES, stopped_runs

    store = Store(tracking_uri)
    stopped = stopped_runs(store.search(None))
    keep = [r for r in stopped if r.fits and r.file is not None]
    if paths:
        for r in keep:
            click.echo(os.path.relpath(r.file))
        return
    for r in stopped:
        if r.checkpoint is not None:
            size = (f"{r.size / 1e3:.0f} kB" if r.fits else
                    f"{r.size / 1e6:.1f} MB, over the {MAX_FILE_BYTES / 1e6:.0f} MB a committed file may have: stays on this machine")
            click.echo(f"{r.run_id[:8]} {r.status:8} {r.name}: {r.checkpoint} ({size})")
    without = sum(r.checkpoint is None for r in stopped)
    uri = f" --tracking-uri {tracking_uri}" if tracking_uri else ""
    click.echo(f"{store.uri}: {len(stopped)} runs stopped before their limit (or still running); {len(keep)} have a checkpoint "
               f"a committed store can keep ({sum(r.size for r in keep) / 1e6:.1f} MB), {without} none here (not resumable "
               f"from this store). Commit them with the store, no run writing: git add -f $(harness store checkpoints --paths{uri}); "
               f"the repository's committed files stay under {BUDGET_BYTES / 1e6:.0f} MB (tests/harness/test_store_travels.py)")
