"""Sweeps: the cross product learners x tasks x seeds, run by a local process pool or by Ray.

    harness sweep --learners pilco,sac --tasks cartpole --seeds 0-9 [--executor local|ray] [--workers N]

* :mod:`~harness.sweep.spec`: what a sweep runs (:class:`SweepSpec`), its id, the check of every option;
* :mod:`~harness.sweep.cell`: the worker side, one cell as a child run (:func:`run_cell`);
* :mod:`~harness.sweep.pools`: the executors (a local pool of spawned processes, Ray);
* :mod:`~harness.sweep.progress`: the bar, the line per cell, the running cells' trials;
* :mod:`~harness.sweep.driver`: :func:`run_sweep`, parents, feeding, stopping.

**MLflow layout** (:mod:`harness.store.layout`). A sweep has a parent run in each of its tasks'
experiments, ``sweep <id> · <task>`` (tags ``harness.sweep_id``, ``harness.role=sweep``; params: the
spec), and each cell is a child of its task's parent, ``pilco · cartpole [horizon=30] · s3`` (tags
``harness.sweep_id``, ``harness.role=cell``, learner, task, seed, the configuration's hash and label;
params: the runner's and ``sweep.command``), beside the `harness bench` runs of that task. A sweep
begun before this layout (one parent in the experiment ``sweeps``) is continued there.

**Identity and resuming.** The sweep id is a hash of the spec (learners, tasks, seeds as sets;
the ``--set`` pairs; the limits). Running the same spec again finds the same parent runs and
skips the cells that have a FINISHED child. A cell whose newest child was interrupted (KILLED,
or RUNNING left by a driver that died) continues in that child from its last per-trial
checkpoint (:mod:`harness.checkpoint`) if its learner supports resuming and a checkpoint exists;
every other unfinished cell (FAILED, or nothing to resume from) runs again as a new child. Old
children stay; the report uses the newest FINISHED child of each cell. A failed cell is reported
and never stops the others.

**Creation order.** With a fresh SQLite store, concurrent workers race on schema creation
(harness-reference §3.4): the driver opens the store, creates the experiments and the parent runs,
and hands the tracking URI, experiment id and parent run id to the workers, which only create
their own runs.

**Workers.** Every cell runs in a fresh, single-threaded process (local: one process started
with the spawn method per cell; Ray: ``max_calls=1``), so its result never depends on what ran
before it (global RNGs, torch state). A learner that raises fails its own cell only. A cell whose
*process* dies (crash, out of memory, killed) is reported failed with its run marked KILLED, and
the next invocation continues it from its checkpoint; the cells beside it go on. The driver keeps at most
``workers`` cells in flight; that bounded feeding is the only scheduling done here.

**Stopping.** Ctrl-C or SIGTERM to the driver stops the running cells at once (each run KILLED,
resumable). ``kill -USR1 DRIVER_PID`` drains instead: no more cells start, and each running
local cell stops once its trial in progress is stored (Ray tasks cannot be signalled: they run to
their end). Either way the same command continues the sweep.
"""

from harness.sweep.driver import SweepResult, run_sweep
from harness.sweep.spec import Cell, SweepSpec, format_seeds, parse_names, parse_seeds

__all__ = ["Cell", "SweepResult", "SweepSpec", "format_seeds", "parse_names", "parse_seeds", "run_sweep"]
