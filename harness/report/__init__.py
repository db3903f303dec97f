"""``harness report``: tables and figures from the MLflow store alone (nothing is re-run).

Reads the sweeps' child runs and `harness bench` runs (see :mod:`harness.store.layout`) and writes into ``out``:

* ``comparison_<task>.md`` / ``.csv``: learner x {solved seeds, median and IQM of interaction
  time to success with 95 % stratified-bootstrap CIs, trials to success, wall time, and the bounds
  of the median with the row's stopped runs} (:mod:`~harness.report.comparison`);
* ``table1.md`` / ``.csv``: the paper's Table 1 (state dimension, trials, experience, policy
  parameters) measured, median [range], beside the paper's values (:mod:`~harness.report.paper`), and
  beside SAC and PPO with how many times less interaction PILCO needed (:mod:`~harness.report.baselines`);
* ``fig5.png`` / ``fig5.csv``: interaction time to success, a panel per task, log axis, every seed
  a point (unsolved: ``>`` at the interaction consumed), the median marked, the paper's and the
  literature's values in grey (``literature_fig5.csv``, each with its source; :mod:`~harness.report.fig5`);
* ``runs_<task>.md`` / ``.csv``: one row per counted run (seed, solved, time to success or the
  interaction at which it stopped unsolved, trials, wall time, stop reason, run id), then the
  runs stopped before their limit, marked as such (in no statistic but the median's bounds;
  :mod:`~harness.report.runs_table`);
* ``curves_<task>.png`` / ``.csv``: evaluation success rate and cost vs interaction seconds
  (mean with band, and every run as a thin line); runs stopped before their limit get a row
  ``<label> (stopped)`` of their own, dashed, ending where they stopped;
* ``<figure>_<task>_<row>.png``: for learners that declare a per-trial figure (PILCO's prediction
  plot, ``prediction_<task>_<row>.png``), the last one of a representative run: the solved run with
  the median time to success (lower median), else the run with the most hand-overs; and
  ``test_<task>.md``, ``fig4b_<task>_<row>.png`` for runs tested with ``harness eval`` (:mod:`~harness.report.from_runs`);
* ``walltime_<task>.md`` / ``.csv``: where the wall time goes, per row: wall per trial (median,
  range, last trial) and the shares of the parts the learners time, the evaluation and the rest
  (:mod:`~harness.report.walltime`);
* ``sweeps.md``: which sweeps (ids, commands, store) the files were made from (:mod:`~harness.report.notes`).

Rows are named by learner. Where a learner ran on a task in several sweeps, each sweep's row is
named by the settings its runs differ in (``pilco [horizon=30]`` beside ``pilco [horizon=40]``),
with ``@<sweep id>`` added where settings do not tell sweeps apart; files named after a row use
the same name as a slug (``prediction_cartpole_pilco_horizon-30.png``; :mod:`~harness.report.labels`).

With ``include_bench``, `harness bench` runs outside sweeps are reported too, grouped by
configuration (learner, task, limits, resolved options) into pseudo-sweeps ``bench-<hash>``
(options at their current default are left out of the hash: an option added later does not split
a group; :mod:`harness.configuration`).

Which run counts for a cell: the newest FINISHED child of the cell, else the newest child. A cell
whose counted run FAILED (the learner raised) counts as unsolved and is listed under "errors";
a cell still RUNNING or KILLED is not counted and is listed as incomplete (a RUNNING run whose
process, tag ``harness.process``, is gone from this machine is said to be stale); a cell of the sweep's
spec without any run is listed as missing. Nothing is dropped without being named (:mod:`~harness.report.loading`).

When sweep ids are given, each task's comparison is also written into the store: a run
``comparison · <task>`` with the whole table and the files, a child run per row with its statistics
as metrics, and every reported run tagged with its row (:mod:`~harness.report.publish`).
"""

from harness.report.loading import load
from harness.report.make import make_report

__all__ = ["load", "make_report"]
