"""The names the harness gives things in MLflow: experiments, run names, roles, tags, metrics, artifact paths.

Every other module refers to these constants and helpers; none spells a tag, metric or artifact path
of its own (but a learner's own metrics and files, which it declares: :class:`harness.learner_logs.Logs`).

**Experiments.** One per task, named after it: `harness bench` runs, sweep cells (children of their
sweep's parent run in that task) and the report's comparison runs all live there. Sweeps made before
this layout have their parent and children in one experiment, :data:`LEGACY_SWEEP_EXPERIMENT`; they are
read and continued there.

**Runs** (``harness.role`` tag):

* a run (`harness bench`; no role) or a sweep cell (role ``cell``, tag ``harness.sweep_id``), named
  ``pilco · cartpole [horizon=30] · s3`` (:func:`run_name`);
* a sweep parent (role ``sweep``) per task of a sweep, named ``sweep 4d745437f024 · cartpole``;
* the report's comparison run per task (role ``comparison``), named ``comparison · cartpole``, and a
  run per row of its table (role ``comparison-row``, tag ``harness.comparison_run``), named after the row.
"""

from __future__ import annotations

from harness.provenance import PROCESS_TAG

#: the experiment that held every sweep (parents and children, all tasks) before the per-task layout
LEGACY_SWEEP_EXPERIMENT = "sweeps"


def task_experiment(task: str) -> str:
    """The experiment of ``task``'s runs, sweep cells and comparison (its name: the task's)."""
    return task


# ---- roles -------------------------------------------------------------------------------------

ROLE_TAG = "harness.role"
ROLE_SWEEP = "sweep"
ROLE_CELL = "cell"
ROLE_COMPARISON = "comparison"
ROLE_ROW = "comparison-row"

# ---- tags --------------------------------------------------------------------------------------

LEARNER_TAG, TASK_TAG, SEED_TAG = "learner", "task", "seed"
SWEEP_TAG = "harness.sweep_id"
ERROR_TAG = "harness.error"
#: ``bench-<hash>`` of the run's configuration (:func:`harness.configuration.config_hash`; the report's group id)
CONFIG_HASH_TAG = "harness.config_hash"
#: the learner and the settings away from the installed defaults, ``pilco [horizon=30]``
CONFIG_LABEL_TAG = "harness.config_label"
#: a comparison row's comparison run (the run id)
COMPARISON_TAG = "harness.comparison_run"
#: the comparison row the last report counted the run in (its label in ``comparison_<task>.md``)
ROW_TAG = "harness.report_row"
#: ``true`` on a run stopped before its limit (KILLED) that continues from its checkpoint, ``false`` on
#: one that cannot; absent on runs that ended (FINISHED, FAILED)
RESUMABLE_TAG = "harness.resumable"
STOP_REASON_TAG = "stop_reason"
SOLVED_TAG = "solved"
#: the process that last wrote to the run (host, pid, start time; :mod:`harness.provenance`)
PROCESS_TAG = PROCESS_TAG
PARENT_TAG = "mlflow.parentRunId"
RUN_NAME_TAG = "mlflow.runName"
#: the run's description in the MLflow UI (markdown)
NOTE_TAG = "mlflow.note.content"
#: sweep parents: cells of the sweep in the parent's task, and how they ended (also logged as metrics)
CELL_COUNT_TAGS = ("harness.cells_total", "harness.cells_finished", "harness.cells_failed", "harness.cells_stopped")
EXECUTOR_TAG = "harness.last_executor"
#: sweep cells run by Ray: the Ray node that last ran the cell (set when its run starts or resumes)
NODE_TAG = "harness.ray_node"
#: sweep parents: cells whose worker was lost (its process or node died) and that ran again, resuming
#: their run (also logged as a metric), and one line per such retry (cell, node, error, run)
RETRIED_TAG = "harness.cells_retried"
RETRIES_TAG = "harness.cell_retries"
#: sweep parents: ``<prefix><cell label>`` holds the token of the one worker allowed to write the
#: cell's run (:mod:`harness.sweep.lease`)
LEASE_TAG_PREFIX = "harness.lease."

# ---- metrics (the runner's; a learner's own are declared by the learner) -------------------------

INTERACTION_SECONDS = "interaction_seconds"
INTERACTION_EPISODES = "interaction_episodes"
WALL_SECONDS = "wall_seconds"
EVAL_SECONDS = "eval_seconds"
EVAL_SUCCESS_RATE = "eval_success_rate"
EVAL_COST = "eval_cost"
#: logged once, at the end of a run (segment)
SOLVED = "solved"
TIME_TO_SUCCESS = "interaction_time_to_success_seconds"
#: the name of :data:`TIME_TO_SUCCESS` (metric and tag) in runs made before the unit was in it
LEGACY_TIME_TO_SUCCESS = "interaction_time_to_success"
TRIALS_TO_SUCCESS = "trials_to_success"
TOTAL_SUFFIX = "_total"
TEST_SUCCESS_RATE = "test_success_rate"
TEST_EPISODES = "test_episodes"

# ---- params ------------------------------------------------------------------------------------

#: the run's limits among its params (with ``learner.*`` and ``task.*``: its configuration)
LIMIT_PARAMS = ("max_trials", "budget_seconds", "eval_episodes")
#: prefix of the value an option had in use where it was left to the learner or task (``None``:
#: "the preset's"), e.g. ``used.learner.planning_horizon`` = 40 beside ``learner.planning_horizon`` = None
USED_PREFIX = "used."

# ---- artifacts ---------------------------------------------------------------------------------

POLICIES = "policies"
CHECKPOINTS = "checkpoints"
EPISODES = "episodes/interaction_episodes.npz"
RESULT = "result.json"
TEST = "test"
TEST_HISTOGRAM = "test_final_distance.png"
ERROR_TRACE = "error.txt"
#: the report's files on its comparison runs
REPORT = "report"
COMPARISON_TABLE = "comparison.json"


def trial_folder(trial: int) -> str:
    """The folder of the files a learner attaches at hand-over ``trial``: ``trial007``."""
    return f"trial{trial:03d}"


def trial_of_folder(name: str) -> int | None:
    """``trial007`` -> 7; ``None`` for any other name."""
    return int(name[len("trial"):]) if name.startswith("trial") and name[len("trial"):].isdigit() else None


def policy_stem(trial: int) -> str:
    """File name (without suffix) of the policy handed over at ``trial``: ``policy_trial007``."""
    return f"policy_trial{trial:03d}"


# ---- names -------------------------------------------------------------------------------------


def run_name(learner: str, task: str, seed: int, settings: str = "") -> str:
    """``pilco · cartpole [horizon=30] · s3`` (``settings``: ``horizon=30``, the options away from their defaults)."""
    return f"{learner} · {task}{f' [{settings}]' if settings else ''} · s{seed}"


def sweep_parent_name(sweep_id: str, task: str) -> str:
    return f"sweep {sweep_id} · {task}"


def comparison_name(task: str) -> str:
    return f"comparison · {task}"


def row_name(label: str, task: str) -> str:
    return f"{label} · {task}"
