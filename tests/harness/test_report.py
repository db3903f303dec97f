"""`harness report`: statistics (inf for unsolved, seeded bootstrap), and tables/figures from MLflow alone."""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import stats

from harness.cli import main
from harness.errors import HarnessError, MissingArtifactsWarning
from harness.report.comparison import comparison_markdown, comparison_row
from harness.report.from_runs import copy_test_histogram, copy_trial_figure, representative_run
from harness.report.labels import file_slug, label_runs, variant_labels
from harness.report.fig5 import fig5_data, fig5_figure, plot_fig5
from harness.report.paper import TABLE1_FIELDS, flat_table1, read_literature, table1_markdown, table1_rows
from harness.report.records import RunRecord, record_from_run
from harness.report.runs_table import run_rows, runs_markdown
from harness.statistics import bootstrap_ci, iqm, median, median_bounds, stratified_bootstrap, times_with_failures
from harness.store import RunReader, Store
from harness.sweep import SweepSpec, pools, run_sweep
from tests.harness import sweep_site

# ---- statistics ---------------------------------------------------------------------------------


def test_iqm_is_scipy_trim_mean_and_inf_survives_only_if_untrimmed():
    rng = np.random.default_rng(1)
    for n in (1, 3, 4, 7, 10, 11):
        x = rng.exponential(10.0, size=(5, n))
        np.testing.assert_allclose(iqm(x), stats.trim_mean(x, 0.25, axis=1), rtol=1e-12)
    # n = 10 trims 2 at each end: 2 unsolved runs are trimmed away, 3 are not
    assert math.isfinite(iqm(np.r_[np.arange(8.0), np.inf, np.inf]))
    assert iqm(np.r_[np.arange(7.0), np.inf, np.inf, np.inf]) == np.inf
    assert median(np.array([4.0, 8.0, np.inf])) == 8.0 and median(np.array([4.0, np.inf, np.inf])) == np.inf
    assert median(np.array([1.0, 3.0, np.inf, np.inf])) == np.inf and median(np.array([1.0, 3.0, 5.0, np.inf])) == 4.0


def test_unsolved_runs_are_inf_never_dropped():
    times = times_with_failures([True, False, True, False], [4.0, None, 8.0, 12.0])
    np.testing.assert_array_equal(times, [4.0, np.inf, 8.0, np.inf])  # an unsolved run's number is ignored


def test_bootstrap_is_seeded_and_contains_the_point_estimate():
    rng = np.random.default_rng(0)
    for n_unsolved in (0, 1, 4):
        x = np.r_[rng.exponential(20.0, size=10 - n_unsolved), np.full(n_unsolved, np.inf)]
        for statistic in (median, iqm):
            low, high = bootstrap_ci(x, statistic, reps=4000, seed=7)
            assert (low, high) == bootstrap_ci(x, statistic, reps=4000, seed=7)
            assert low <= statistic(x) <= high
            replicates = stratified_bootstrap([x], statistic, reps=4000, seed=7)
            np.testing.assert_array_equal(replicates, stratified_bootstrap([x], statistic, reps=4000, seed=7))
            assert not np.array_equal(replicates, stratified_bootstrap([x], statistic, reps=4000, seed=8))


def test_bootstrap_bounds_match_the_exact_bootstrap_distribution():
    """n = 5: all 5^5 resamples enumerated; the Monte Carlo bounds sit between the exact
    2 % / 3 % (and 97 % / 98 %) quantiles of the exact bootstrap distribution of the IQM."""
    x = np.array([3.0, 5.0, 6.0, 11.0, 20.0])
    exact = np.sort(iqm(x[np.array(list(itertools.product(range(5), repeat=5)))]))
    low, high = bootstrap_ci(x, iqm, reps=20_000, seed=3)
    assert np.quantile(exact, 0.015) <= low <= np.quantile(exact, 0.035)
    assert np.quantile(exact, 0.965) <= high <= np.quantile(exact, 0.985)


def test_stratified_bootstrap_keeps_each_task_size():
    small, large = np.array([1.0, 2.0, 3.0]), np.array([100.0, 200.0])
    count_small = lambda v: np.sum(v < 50, axis=-1)  # noqa: E731
    reps = stratified_bootstrap([small, large], count_small, reps=500, seed=0)
    assert np.all(reps == 3)  # never a task's runs drawn in place of another's
    pooled = stratified_bootstrap([np.r_[small, large]], count_small, reps=500, seed=0)
    assert pooled.min() < 3 < pooled.max()


def _record(seed, solved, time=None, trials=None, interaction=8.0, status="FINISHED", task="cartpole", params=305.0):
    return RunRecord(f"run{seed}", "abc", "pilco", task, seed, status, seed, solved, "solved" if solved else "max trials",
                     time, trials, interaction, 10.0 + seed, params, 4, label="pilco")


def test_comparison_row_counts_unsolved_and_errors():
    runs = [_record(0, True, 15.0, 4.0), _record(1, True, 20.0, 5.0), _record(2, False, interaction=40.0),
            _record(3, False, interaction=3.0, status="FAILED")]
    row = comparison_row("cartpole", "pilco", runs, reps=2000)
    assert (row["runs"], row["solved"], row["errors"]) == (4, 2, 1)
    assert row["median_time_to_success_s"] == np.inf  # [15, 20, inf, inf]: only half solved
    assert row["iqm_time_to_success_s"] == np.inf and row["median_ci_high_s"] == np.inf
    assert (row["trials_to_success_median"], row["trials_to_success_min"], row["trials_to_success_max"]) == (4.5, 4.0, 5.0)
    assert (row["unsolved_interaction_min_s"], row["unsolved_interaction_max_s"]) == (3.0, 40.0)


def test_median_bounds_enumerate_what_the_stopped_runs_could_still_do():
    """Independent check: every stopped run either solves at some time >= where it stopped or never; the
    bounds are the smallest and largest median over a grid of such completions, and both are attained."""
    finished, stopped_at = [90.0, 111.0, np.inf], [36.0, 18.0]
    low, high = median_bounds(finished, stopped_at)
    grid = [18.0, 36.0, 50.0, 90.0, 100.0, 111.0, 500.0, np.inf]
    medians = [float(np.median(finished + [a, b])) for a in grid if a >= 36.0 for b in grid if b >= 18.0]
    assert (low, high) == (min(medians), max(medians)) == (90.0, np.inf)
    assert median_bounds([15.0, 20.0, 30.0], []) == (20.0, 20.0)
    assert median_bounds([90.0, 111.0], [60.0, 63.0]) == (76.5, np.inf)  # >= 76.5: a 60 s target is missed already
    assert median_bounds([10.0, 12.0, 14.0], [5.0]) == (11.0, 13.0)
    assert all(math.isnan(v) for v in median_bounds([], []))


def test_comparison_row_bounds_the_median_with_its_stopped_runs():
    runs = [_record(0, True, 90.0, 30.0), _record(1, True, 111.0, 37.0)]
    stopped = [_record(2, False, interaction=36.0, status="KILLED"), _record(3, False, interaction=18.0, status="KILLED")]
    row = comparison_row("double-pendulum", "pilco", runs, reps=200, stopped=stopped)
    assert row["median_time_to_success_s"] == 100.5 and row["runs"] == 2  # the statistics stay over finished runs
    assert (row["stopped"], row["median_with_stopped_low_s"], row["median_with_stopped_high_s"]) == (2, 63.0, np.inf)
    md = comparison_markdown("double-pendulum", [row, comparison_row("double-pendulum", "other", runs, reps=200)])
    assert md.splitlines()[-2].endswith("| ≥ 63.0 (2 stopped of 4) |")
    assert md.splitlines()[-1].endswith("| 0 | – |")


def test_a_configuration_whose_runs_are_all_stopped_has_a_row_with_only_its_bounds():
    stopped = [_record(0, False, interaction=66.0, status="KILLED"), _record(1, False, interaction=60.0, status="KILLED")]
    row = comparison_row("double-pendulum", "pilco", [], reps=200, stopped=stopped)
    assert (row["runs"], row["solved"], row["stopped"]) == (0, 0, 2)
    assert all(math.isnan(row[k]) for k in ("median_time_to_success_s", "median_ci_low_s", "iqm_time_to_success_s",
                                             "wall_seconds_median", "trials_to_success_median"))
    assert (row["median_with_stopped_low_s"], row["median_with_stopped_high_s"]) == (63.0, np.inf)
    assert comparison_markdown("double-pendulum", [row]).splitlines()[-1] == (
        "| pilco | 0/0 | – | – | – | – | – | 0 | ≥ 63.0 (2 stopped of 2) |")


def test_run_rows_give_unsolved_runs_a_lower_bound_not_a_value():
    runs = [_record(0, True, 15.0, 4.0), _record(1, False, interaction=60.0)]
    rows = run_rows("cartpole", "pilco", runs)
    assert rows[0]["time_to_success_s"] == 15.0 and math.isnan(rows[1]["time_to_success_s"])
    md = runs_markdown("cartpole", rows)
    assert "| pilco | 0 | yes | 15.0 | 4 | 8.0 |" in md
    assert "| pilco | 1 | no | > 60.0 (unsolved) | – | 60.0 |" in md


def test_stopped_runs_are_listed_as_stopped_and_in_no_statistic():
    stopped = _record(2, False, interaction=57.0, status="KILLED")
    stopped.episodes = 19.0
    rows = run_rows("cartpole", "pilco", [_record(0, True, 15.0, 4.0)]) + run_rows("cartpole", "pilco", [stopped], counted=False)
    assert [r["counted"] for r in rows] == [True, False] and rows[1]["learner"] == "pilco (stopped)"
    md = runs_markdown("cartpole", rows)
    assert "| pilco (stopped) | 2 | no | > 57.0 (*stopped*, unsolved so far) | – (19 so far) | 57.0 |" in md
    assert "stopped before its limit (KILLED)" in md


def _fake_run(metrics=None, tags=None, root: Path | None = None, run_id="r", status="KILLED"):
    """A stored run as the store returns it (an MLflow ``Run``'s fields), its files in ``root``."""
    from types import SimpleNamespace

    info = SimpleNamespace(run_id=run_id, experiment_id="1", status=status, start_time=0,
                           artifact_uri=(root or Path("/nonexistent")).as_uri())
    data = SimpleNamespace(tags={"learner": "pilco", "task": "cartpole", "seed": "0", **(tags or {})}, metrics=metrics or {}, params={})
    return SimpleNamespace(info=info, data=data)


def _reader(run) -> RunReader:
    from types import SimpleNamespace

    return RunReader(SimpleNamespace(uri="sqlite:////nonexistent/mlflow.db"), run)


def test_a_stale_total_of_an_earlier_run_segment_does_not_hide_later_trials():
    fake_run = lambda metrics: _reader(_fake_run(metrics))  # noqa: E731

    # killed at 60 s (totals logged), resumed, then lost at 114 s without logging totals
    stale = fake_run({"interaction_seconds_total": 60.0, "interaction_seconds": 114.0, "wall_seconds_total": 4312.0,
                      "wall_seconds": 14826.0})
    record = record_from_run(stale, "s")
    assert (record.interaction_seconds, record.wall_seconds) == (114.0, 14826.0)
    # a finished run's totals include what came after its last hand-over
    finished = record_from_run(fake_run({"interaction_seconds_total": 44.0, "interaction_seconds": 40.0}), "s")
    assert finished.interaction_seconds == 44.0
    # episodes count the same way as seconds: a stopped run's last rollout is in its total, not in its last hand-over's
    stopped = record_from_run(fake_run({"interaction_seconds_total": 69.0, "interaction_seconds": 66.0,
                                        "interaction_episodes_total": 23.0, "interaction_episodes": 22.0}), "s")
    assert (stopped.interaction_seconds, stopped.episodes) == (69.0, 23.0)


def test_a_run_made_before_the_unit_was_in_the_metric_name_reads_the_same():
    old = _reader(_fake_run({"interaction_time_to_success": 12.0, "trials_to_success": 3.0}, {"solved": "true"}, status="FINISHED"))
    new = _reader(_fake_run({"interaction_time_to_success_seconds": 12.0, "trials_to_success": 3.0}, {"solved": "true"}, status="FINISHED"))
    assert record_from_run(old, "s").time_to_success == record_from_run(new, "s").time_to_success == 12.0
    # what the learner declares it logs: PILCO's policy size fills Table 1, a learner that declares none has none
    sized = _reader(_fake_run({"policy_parameters": 305.0}))
    assert record_from_run(sized, "s").policy_parameters == 305.0
    sized.tags["learner"] = "random"
    assert record_from_run(sized, "s").policy_parameters is None


def test_wall_time_is_split_per_trial_into_the_logged_parts_and_the_rest():
    from harness.report.walltime import wall_breakdown, wall_parts, walltime_markdown

    # run A: trials of 10, 20, 30 s (cumulative 10, 30, 60); run B: one trial of 40 s, no evaluation timing
    a = {"wall_seconds": {1: 10.0, 2: 30.0, 3: 60.0}, "model_train_seconds": {1: 1.0, 2: 2.0, 3: 3.0},
         "policy_opt_seconds": {1: 5.0, 2: 10.0, 3: 20.0}, "eval_seconds": {1: 1.0, 2: 1.0, 3: 1.0}}
    b = {"wall_seconds": {1: 40.0}, "model_train_seconds": {1: 4.0}, "policy_opt_seconds": {1: 30.0}}
    parts = wall_parts(["pilco", "random", "sac"])  # PILCO declares GP training and policy search; the harness times evaluation
    assert [p.key for p in parts] == ["model_training", "policy_search", "evaluation"] and [p.key for p in wall_parts(["sac"])] == ["evaluation"]
    row = wall_breakdown([a, b], parts)
    assert row["policies"] == 4 and row["total_wall_s"] == 100.0
    assert (row["wall_per_trial_median_s"], row["wall_per_trial_min_s"], row["wall_per_trial_max_s"]) == (25.0, 10.0, 40.0)
    assert row["last_trial_wall_median_s"] == 35.0  # median of 30 (A's last) and 40 (B's only)
    assert (row["share_model_training"], row["share_policy_search"], row["share_evaluation"]) == (0.10, 0.65, 0.03)
    assert row["share_other"] == pytest.approx(0.22)
    none = wall_breakdown([{"wall_seconds": {1: 5.0}}], parts)
    assert math.isnan(none["share_policy_search"]) and none["share_other"] == 1.0
    md = walltime_markdown("cartpole", [{"task": "cartpole", "learner": "pilco", "runs": 2, **row}], parts)
    assert "| GP training | policy search | evaluation | other |" in md
    assert "| pilco | 2 | 4 | 25 [10–40] | 35 | 0.03 | 10 % | 65 % | 3 % | 22 % |" in md


def test_curves_hold_finished_runs_and_end_stopped_runs_where_they_stopped():
    from harness.report.figures import curve_table, hold_on_grid

    grid = np.array([1.0, 2.0, 3.0, 4.0])
    held = hold_on_grid(np.array([1.5, 2.5]), np.array([0.1, 0.9]), grid)
    ended = hold_on_grid(np.array([1.5, 2.5]), np.array([0.1, 0.9]), grid, hold_after=False)
    assert np.allclose(held, [np.nan, 0.1, 0.9, 0.9], equal_nan=True)
    assert np.allclose(ended, [np.nan, 0.1, np.nan, np.nan], equal_nan=True)
    run = lambda x, s: {"interaction_seconds": np.array(x), "eval_success_rate": np.array(s), "eval_cost": np.array(s)}  # noqa: E731
    histories = [run([1.0, 2.0], [0.0, 1.0]), run([1.0, 4.0], [0.0, 0.0])]
    table = curve_table({"pilco": histories, "pilco (stopped)": histories}, points=5, stopped=frozenset({"pilco (stopped)"}))
    last = {r["learner"]: r for r in table if r["interaction_s"] == max(t["interaction_s"] for t in table if t["learner"] == r["learner"])}
    # at 4.4 s (10 % past the last hand-over) both finished runs are held (mean 0.5); the stopped
    # ones ended at 2 s and 4 s, so none is evaluated there, and at ~2.8 s only the second one
    assert last["pilco"]["runs_evaluated"] == 2 and last["pilco"]["success_mean"] == 0.5
    assert last["pilco (stopped)"]["runs_evaluated"] == 0 and math.isnan(last["pilco (stopped)"]["success_mean"])
    at3 = {r["learner"]: r for r in table if 2.0 < r["interaction_s"] < 4.0}
    assert at3["pilco"]["runs_evaluated"] == 2 and at3["pilco (stopped)"]["runs_evaluated"] == 1


def test_representative_run_is_the_lower_median_solved_run_else_the_longest():
    runs = [_record(0, True, 30.0, 7.0), _record(1, True, 10.0, 3.0), _record(2, True, 20.0, 5.0), _record(3, True, 40.0, 9.0),
            _record(4, False, interaction=60.0)]
    assert representative_run(runs).seed == 2  # times 10, 20, 30, 40 -> lower median 20
    assert representative_run([_record(0, False, interaction=20.0), _record(1, False, interaction=60.0)]).seed == 1
    assert representative_run([]) is None


def _stored(tmp_path: Path, record: RunRecord, learner: str = "pilco") -> RunRecord:
    """``record`` with a stored run whose files are in ``tmp_path / run_id``."""
    import dataclasses

    run = _fake_run(root=tmp_path / record.run_id, run_id=record.run_id, status=record.status)
    run.data.tags["learner"] = learner
    return dataclasses.replace(record, learner=learner, reader=_reader(run))


def test_trial_figure_of_the_representative_run_is_copied(tmp_path):
    for run, trials in (("run0", (2, 3)), ("run1", (2, 3, 11))):
        for t in trials:
            (tmp_path / run / f"trial{t:03d}").mkdir(parents=True)
            (tmp_path / run / f"trial{t:03d}" / f"prediction_trial{t - 1:03d}.png").write_bytes(f"{run}-{t}".encode())
        (tmp_path / run / "policies").mkdir()
    out = tmp_path / "out"
    out.mkdir()
    runs = [_stored(tmp_path, _record(0, True, 30.0, 7.0)), _stored(tmp_path, _record(1, True, 10.0, 3.0))]
    path = copy_trial_figure("cartpole", "pilco", runs, out)  # the figure PILCO declares: its prediction plot
    assert path == out / "prediction_cartpole_pilco.png" and path.read_bytes() == b"run1-11"  # lower median; trial 11 > trial 3
    (tmp_path / "run2" / "policies").mkdir(parents=True)  # a run that logs no prediction plots
    assert copy_trial_figure("cartpole", "pilco", [_stored(tmp_path, _record(2, True, 5.0, 2.0))], out) is None
    # a learner that declares no per-trial figure: nothing looked for, nothing said
    assert copy_trial_figure("cartpole", "random", [_stored(tmp_path, _record(1, True, 10.0, 3.0), "random")], out) is None
    (tmp_path / "run3").mkdir()  # a run whose artifacts are missing: said, not silently skipped
    with pytest.warns(MissingArtifactsWarning, match="cartpole / pilco not written: its representative run run3 has no artifacts"):
        assert copy_trial_figure("cartpole", "pilco", [_stored(tmp_path, _record(3, True, 5.0, 2.0))], out) is None


def test_test_histogram_of_the_tested_run_is_copied_and_missing_artifacts_are_said(tmp_path):
    (tmp_path / "run1" / "test").mkdir(parents=True)
    (tmp_path / "run1" / "test" / "test_final_distance.png").write_bytes(b"hist1")
    out = tmp_path / "out"
    out.mkdir()
    runs = [_stored(tmp_path, _record(0, True, 30.0, 7.0)), _stored(tmp_path, _record(1, True, 10.0, 3.0))]
    tested = [{"run_id": "run1"}]
    path = copy_test_histogram("unicycle", "pilco [init=code]", runs, tested, out)
    assert path == out / "fig4b_unicycle_pilco_init-code.png" and path.read_bytes() == b"hist1"
    (tmp_path / "run0").mkdir()  # tested, but its artifacts are missing
    with pytest.warns(MissingArtifactsWarning, match="test histogram of unicycle / pilco not written: its tested run run0 has no artifacts"):
        assert copy_test_histogram("unicycle", "pilco", runs, [{"run_id": "run0"}], out) is None


def test_table1_measured_beside_the_paper():
    runs = [_record(0, True, 15.0, 4.0), _record(1, True, 25.0, 6.0), _record(2, False)]
    rows = table1_rows({"cartpole": {"pilco": runs}}, "pilco")
    (row,) = rows
    assert row["trials"] == (5.0, 4.0, 6.0) and row["experience_s"] == (20.0, 15.0, 25.0)
    assert row["policy_parameters"] == (305.0, 305.0, 305.0) and row["state_dim"] == "4"
    md = table1_markdown(rows, "pilco")
    assert "| cartpole (cart-pole) | 2/3 | R^4 / R^4 | 5 [4–6] / <= 10 | 20.0 [15.0–25.0] / ~ 20 s | R^305 [305–305] / R^305 |" in md
    assert "Stopped before their limit" not in md

    # a run stopped at the end of a session: not counted, shown as a lower bound under the table
    stopped = dataclasses.replace(_record(7, False, interaction=30.0, status="KILLED", task="unicycle", params=22.0), episodes=25.0)
    rows = table1_rows({"cartpole": {"pilco": runs}}, "pilco", [stopped])
    unicycle = rows[-1]
    assert (unicycle["task"], unicycle["runs"], unicycle["solved"], unicycle["stopped"]) == ("unicycle", 0, 0, 1)
    assert math.isnan(unicycle["trials"][0]) and unicycle["policy_parameters"] == (22.0, 22.0, 22.0)
    md = table1_markdown(rows, "pilco")
    assert "| unicycle (unicycle) | 0/0 | R^4 / R^12 | – / ~ 20 | – / ~ 20-30 s | R^22 [22–22] / R^28 |" in md
    assert "- unicycle: 1 run(s) at 25 [25–25] trials, 30.0 [30.0–30.0] s of interaction" in md


def _learner_runs(learner, task, outcomes):
    """Records of ``learner`` on ``task``: per seed ``(solved, time to success or interaction consumed)``."""
    return [dataclasses.replace(_record(seed, solved, time if solved else None, 3.0 if solved else None,
                                        interaction=time, task=task), learner=learner, label=learner)
            for seed, (solved, time) in enumerate(outcomes)]


def _pilco_sac_ppo():
    """Cart-pole: PILCO, SAC and PPO (PPO never solves); double pendulum: PILCO only; unicycle: PILCO
    and a SAC that never solves; dmc-cartpole: no runs."""
    return {
        "cartpole": {"pilco": _learner_runs("pilco", "cartpole", [(True, 10.0), (True, 20.0), (False, 30.0)]),
                     "sac": _learner_runs("sac", "cartpole", [(True, 500.0), (True, 900.0), (False, 2e4)]),
                     "ppo": _learner_runs("ppo", "cartpole", [(False, 2e4), (False, 2e4)])},
        "double-pendulum": {"pilco": _learner_runs("pilco", "double-pendulum", [(True, 84.0)])},
        "unicycle": {"pilco": _learner_runs("pilco", "unicycle", [(True, 30.0)]),
                     "sac": _learner_runs("sac", "unicycle", [(False, 5000.0), (False, 8000.0)])},
    }


def test_table1_sets_pilco_beside_sac_and_ppo():
    by_task = _pilco_sac_ppo()
    rows = {r["task"]: r for r in table1_rows(by_task, "pilco")}
    md = table1_markdown(list(rows.values()), "pilco")
    assert "| PILCO (unsolved = ∞) | SAC | PPO | PILCO vs best model-free |" in md
    # ratio of the medians, unsolved = inf: SAC [500, 900, inf] -> 900 s; PILCO [10, 20, inf] -> 20 s
    ratio = np.median([500.0, 900.0, np.inf]) / np.median([10.0, 20.0, np.inf])
    assert ratio == 45.0 and rows["cartpole"]["vs_model_free"] == f"{ratio:.1f}× less than sac"
    assert "| 2/3, 20.0 s | 2/3, 900.0 s | 0/2, ∞ (≥ 20000.0 s) | 45.0× less than sac |" in md
    assert "| 1/1, 84.0 s | not run | not run | — |" in md  # no baseline ran on the double pendulum
    never = f"baseline never solved within its budget (≥ 5000.0 s); ≥ {5000.0 / 30.0:.1f}× less"
    assert f"| 1/1, 30.0 s | 0/2, ∞ (≥ 5000.0 s) | not run | {never} |" in md
    flat = {r["task"]: r for r in flat_table1(list(rows.values()))}
    assert set(TABLE1_FIELDS) == set(flat["cartpole"])
    assert (flat["cartpole"]["sac_solved"], flat["cartpole"]["sac_median_s"], flat["double-pendulum"]["ppo_runs"]) == (2, 900.0, "")
    assert flat["cartpole"]["pilco_vs_best_model_free"] == "45.0× less than sac"
    # neither PILCO counted nor a baseline run: a dash
    stopped = dataclasses.replace(_record(7, False, interaction=30.0, status="KILLED", task="unicycle"), episodes=25.0)
    (row,) = table1_rows({}, "pilco", [stopped])
    assert row["vs_model_free"] == "—" and "| no counted runs | not run | not run | — |" in table1_markdown([row], "pilco")


def test_fig5_has_a_panel_per_task_with_every_seed(tmp_path):
    rows = fig5_data(_pilco_sac_ppo(), read_literature(Path(__file__).parents[2] / "results" / "literature_fig5.csv"))
    fig = fig5_figure(rows)
    assert [ax.get_title() for ax in fig.axes] == ["cart-pole (cartpole)", "dm_control cart-pole (dmc-cartpole)",
                                                   "double pendulum (double-pendulum)", "unicycle (unicycle)"]
    said = [[t.get_text() for t in ax.texts] for ax in fig.axes]
    assert said == [[], ["no runs"], [], []]
    cartpole = fig.axes[0]
    labels = [t.get_text() for t in cartpole.get_yticklabels()]
    assert "pilco\n2/3 solved, median 20 s" in labels and "ppo\n0/2 solved, median > 20000 s" in labels
    assert any(label.startswith("GP-MPC") for label in labels)  # the literature, in grey
    # every seed drawn: a dot at its time to success, an arrow head at the interaction an unsolved one consumed
    points = [(line.get_marker(), float(np.ravel(line.get_xdata())[0])) for line in cartpole.lines]
    assert [x for m, x in points if m == "o"] == [10.0, 20.0, 500.0, 900.0]
    assert [x for m, x in points if m == ">"] == [30.0, 2e4, 2e4, 2e4]
    assert [x for m, x in points if m == "|"] == [20.0, 900.0]  # the medians reached
    grey = {r["label"]: r for r in rows if r["task"] == "double-pendulum" and r["kind"] == "paper"}
    assert (grey["PILCO (paper, Table 1)"]["solved_min_s"], grey["PILCO (paper, Table 1)"]["solved_max_s"]) == (60.0, 90.0)
    assert {r["task"] for r in rows} == {"cartpole", "double-pendulum", "unicycle"}  # dmc-cartpole: no points, no paper value
    assert plot_fig5(rows, tmp_path / "fig5.png").stat().st_size > 0


def test_sweeps_of_one_learner_are_told_apart_by_the_settings_they_differ_in():
    import dataclasses

    def rec(seed, sweep, config, learner="pilco"):
        return dataclasses.replace(_record(seed, True, 12.0, 3.0), run_id=f"{sweep}{seed}", sweep_id=sweep, learner=learner, config=config)

    base = {"task.horizon": "40", "learner.threads": "1", "max_trials": "15"}
    records = [rec(0, "s40", base), rec(1, "s40", base),
               rec(0, "s30", base | {"task.horizon": "30", "learner.added_later": "x"}),
               rec(0, "m", base, learner="pilco-mean")]
    label_runs(records)
    assert [r.label for r in records] == ["pilco [horizon=40]", "pilco [horizon=40]", "pilco [horizon=30]", "pilco-mean"]
    # the same settings: the sweep id tells them apart; so does a clash of option names, by the full key
    assert variant_labels("pilco", {"a": base, "b": dict(base)}) == {"a": "pilco@a", "b": "pilco@b"}
    three = variant_labels("pilco", {"a": base, "b": dict(base), "c": base | {"task.horizon": "30"}})
    assert three == {"a": "pilco [horizon=40]@a", "b": "pilco [horizon=40]@b", "c": "pilco [horizon=30]"}
    many = {"a": base | {"task.x": "1", "task.y": "1", "task.z": "1"},
            "b": dict.fromkeys(base, "0") | {"task.x": "2", "task.y": "2", "task.z": "2"}}
    assert variant_labels("pilco", many) == {"a": "pilco@a", "b": "pilco@b"}  # 6 settings differ (more than LABEL_SETTINGS)
    five = {k: {key: v for key, v in c.items() if key != "task.z"} for k, c in many.items()}
    assert all("@" not in label and label.count("=") == 5 for label in variant_labels("pilco", five).values())
    both = variant_labels("pilco", {"a": base | {"learner.horizon": "5"}, "b": base | {"task.horizon": "30", "learner.horizon": "9"}})
    assert both == {"a": "pilco [learner.horizon=5, task.horizon=40]", "b": "pilco [learner.horizon=9, task.horizon=30]"}
    # a setting one run of a sweep differs in is not the sweep's: not compared
    mixed = [rec(0, "a", base), rec(1, "a", base | {"task.horizon": "30"}), rec(0, "b", base | {"max_trials": "9"})]
    label_runs(mixed)
    assert [r.label for r in mixed] == ["pilco [max_trials=15]", "pilco [max_trials=15]", "pilco [max_trials=9]"]
    # an option one sweep did not record (added after it ran) counts at its default: a sweep with
    # it set otherwise is told apart by it (pilco's gp_fitc_evals defaults to 100)
    later = [rec(0, "old", base), rec(0, "new", base | {"learner.gp_fitc_evals": "300"}), rec(0, "same", base | {"learner.gp_fitc_evals": "100"})]
    label_runs(later)
    assert [r.label for r in later] == ["pilco [gp_fitc_evals=100]@old", "pilco [gp_fitc_evals=300]", "pilco [gp_fitc_evals=100]@same"]
    assert file_slug("pilco [horizon=30, max_trials=9]") == "pilco_horizon-30_max_trials-9" and file_slug("pilco@ab12") == "pilco_ab12"

    # Table 1 has a row per variant of the learner, the variant named
    rows = table1_rows({"cartpole": {"pilco [horizon=40]": records[:2], "pilco [horizon=30]": records[2:3], "pilco-mean": records[3:]}}, "pilco")
    assert [(r["learner"], r["runs"]) for r in rows] == [("pilco [horizon=40]", 2), ("pilco [horizon=30]", 1)]
    assert "| cartpole (cart-pole), `pilco [horizon=30]` | 1/1 |" in table1_markdown(rows, "pilco")


def test_a_running_run_whose_process_is_gone_is_named_stale():
    import dataclasses
    import subprocess

    from harness.provenance import process_token
    from harness.report.notes import notes_markdown
    from harness.report.records import ReportData

    child = subprocess.Popen(["sleep", "0.01"])
    dead = process_token(child.pid)
    child.wait()
    runs = [dataclasses.replace(_record(0, False, status="RUNNING"), process=dead),
            dataclasses.replace(_record(1, False, status="RUNNING"), run_id="live", process=process_token()),
            dataclasses.replace(_record(2, False, status="KILLED"), run_id="killed", process=dead)]
    md = notes_markdown(ReportData([], [], incomplete=runs))
    host, pid, _ = dead.rsplit(":", 2)
    assert f"(run `run0`): RUNNING in the store, but its process (pid {pid} on {host}) is gone" in md
    assert "(run `live`): RUNNING\n" in md and "(run `killed`): KILLED\n" in md


def test_literature_rows_need_a_source(tmp_path):
    path = tmp_path / "lit.csv"
    path.write_text("# comment\nmethod,year,interaction_seconds,source,note\nX,2001,100,,\n")
    with pytest.raises(HarnessError, match="'X' has no source"):
        read_literature(path)
    path.write_text("method,year,interaction_seconds,source,note\nX,2001,100,Some et al. 2001 Table 2,\n")
    assert read_literature(path)[0]["interaction_seconds"] == "100"
    assert read_literature(tmp_path / "absent.csv") == []


# ---- end to end: a sweep's runs, then `harness report` from MLflow alone -------------------------


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """3 learners x 1 task x seeds 2-4 (see tests/harness/sweep_site.py for what each does)."""
    from harness.tracking import default_tracking_uri

    uri = default_tracking_uri(tmp_path_factory.mktemp("report-store"))
    paths = sweep_site.install(tmp_path_factory.mktemp("report-plugins"))
    with pytest.MonkeyPatch.context() as mp:
        sweep_site.activate(paths, mp)
        mp.setattr(pools, "LocalPool", sweep_site.InlinePool)
        spec = SweepSpec(("sweep-steps", "random", "sweep-boom"), ("sweep-toy",), (2, 3, 4), max_trials=2, eval_episodes=2)
        result = run_sweep(spec, uri)
    return uri, result, paths


def read_rows(path: Path) -> dict[str, dict[str, str]]:
    with open(path) as fh:
        return {row.get("learner") or row["label"]: row for row in csv.DictReader(fh)}


def test_report_regenerates_tables_and_figures_from_mlflow(swept, tmp_path):
    uri, result, _ = swept
    out = tmp_path / "results"
    cli = CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--sweep", result.sweep_id, "--out", str(out), "--fig5-task", "sweep-toy"])
    assert cli.exit_code == 0, cli.output
    for name in ("comparison_sweep-toy.md", "comparison_sweep-toy.csv", "table1.md", "table1.csv", "fig5.png", "fig5.csv",
                 "curves_sweep-toy.png", "curves_sweep-toy.csv", "runs_sweep-toy.md", "runs_sweep-toy.csv", "sweeps.md"):
        assert (out / name).stat().st_size > 0, name

    rows = read_rows(out / "comparison_sweep-toy.csv")
    steps = rows["sweep-steps"]  # times to success 4, 8 and one unsolved run (inf)
    assert (steps["runs"], steps["solved"], steps["errors"]) == ("3", "2", "0")
    assert float(steps["median_time_to_success_s"]) == 8.0 and float(steps["iqm_time_to_success_s"]) == math.inf
    assert float(steps["median_ci_low_s"]) <= 8.0 <= float(steps["median_ci_high_s"])
    assert (float(steps["trials_to_success_min"]), float(steps["trials_to_success_max"])) == (1.0, 2.0)
    assert float(steps["unsolved_interaction_min_s"]) == 8.0
    assert (rows["random"]["runs"], rows["random"]["solved"]) == ("3", "0")
    assert float(rows["random"]["median_time_to_success_s"]) == math.inf
    boom = rows["sweep-boom"]  # the learner raised: counted as unsolved and named, not dropped
    assert (boom["runs"], boom["solved"], boom["errors"]) == ("3", "0", "3")
    assert "| sweep-steps | 2/3 | 8.0 [" in (out / "comparison_sweep-toy.md").read_text()
    per_run = (out / "runs_sweep-toy.md").read_text()
    assert "| sweep-steps | 2 | yes | 4.0 |" in per_run and "| sweep-steps | 4 | no | > 8.0 (unsolved) |" in per_run
    notes = (out / "sweeps.md").read_text()
    assert "sweep-boom on sweep-toy, seed 3" in notes and "RuntimeError: boom in the learner" in notes
    assert SweepSpec(("sweep-steps", "random", "sweep-boom"), ("sweep-toy",), (2, 3, 4), max_trials=2, eval_episodes=2).command() in notes

    fig5 = read_rows(out / "fig5.csv")
    assert fig5["sweep-steps"]["seed_times_s"] == "4 8 inf" and float(fig5["sweep-steps"]["censored_at_s"]) == 8.0
    assert fig5["sweep-steps"]["task"] == "sweep-toy" and fig5["sweep-steps"]["seed_interaction_s"] == "4 8 8"

    # learning curves: success rate held between hand-overs; seeds 2, 3, 4 succeed from 4 s, from 8 s, never
    with open(out / "curves_sweep-toy.csv") as fh:
        curve = [r for r in csv.DictReader(fh) if r["learner"] == "sweep-steps"]
    at = {float(r["interaction_s"]): float(r["success_mean"]) for r in curve}
    assert at[4.0] == pytest.approx(1 / 3) and at[8.0] == pytest.approx(2 / 3)

    # the comparison in the store: a run per task with the whole table (every learner a row) and the files
    store = Store(uri)
    experiment = store.experiment_id("sweep-toy")
    (comparison,) = store.search([experiment], "tags.`harness.role` = 'comparison'")
    assert comparison.name == "comparison · sweep-toy" and comparison.status == "FINISHED"
    logged = json.loads(comparison.file("report/comparison.json").read_text())
    table = {row[logged["columns"].index("learner")]: dict(zip(logged["columns"], row)) for row in logged["data"]}
    assert set(table) == {"sweep-steps", "random", "sweep-boom"}
    assert table["sweep-steps"]["median_time_to_success_s"] == 8.0 and table["sweep-steps"]["iqm_time_to_success_s"] is None
    assert {a.path for a in comparison.artifacts("report")} >= {"report/comparison.json", "report/comparison_sweep-toy.md",
                                                                  "report/curves_sweep-toy.png", "report/fig5.png"}
    assert "| sweep-steps | 2/3 | 8.0 [" in comparison.tags["mlflow.note.content"]
    # a run per row whose metrics are the row's statistics, unsolved runs counted: the learner that
    # never solved keeps a row (solved fraction 0, a median only as a lower bound), none is dropped
    rows = {r.tags["harness.report_row"]: r for r in store.search([experiment], "tags.`harness.role` = 'comparison-row'")}
    assert {r.tags["harness.comparison_run"] for r in rows.values()} == {comparison.run_id}
    assert set(rows) == {"sweep-steps", "random", "sweep-boom"} and rows["random"].name == "random · sweep-toy"
    steps, never = rows["sweep-steps"].metrics, rows["random"].metrics
    assert (steps["runs"], steps["solved_runs"], steps["solved_fraction"]) == (3, 2, pytest.approx(2 / 3))
    assert steps["median_time_to_success_seconds"] == 8.0 and steps["median_time_to_success_at_least_seconds"] == 8.0
    assert steps["median_ci_low_seconds"] <= 8.0 and "iqm_time_to_success_seconds" not in steps  # infinite: not logged
    assert never["solved_fraction"] == 0.0 and never["median_time_to_success_at_least_seconds"] == 8.0
    assert "median_time_to_success_seconds" not in never
    assert rows["sweep-boom"].metrics["failed_runs"] == 3
    # every counted run says which row it is in, and carries its configuration's hash and label
    for run in sweep_site.sweep_runs(uri, result, "cell"):
        assert run.tags["harness.report_row"] == run.tags["learner"]
        assert run.tags["harness.config_hash"].startswith("bench-") and run.tags["harness.config_label"] == run.tags["learner"]

    # a second report replaces the rows (no stale statistic stays) and keeps the comparison run
    again = CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--sweep", result.sweep_id, "--out", str(out)])
    assert again.exit_code == 0, again.output
    (same,) = store.search([experiment], "tags.`harness.role` = 'comparison'")
    assert same.run_id == comparison.run_id and len(store.search([experiment], "tags.`harness.role` = 'comparison-row'")) == 3


def test_report_is_deterministic_and_rejects_unknown_sweeps(swept, tmp_path):
    uri, result, _ = swept
    for out in ("a", "b"):
        assert CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--out", str(tmp_path / out)]).exit_code == 0
    assert (tmp_path / "a" / "comparison_sweep-toy.csv").read_text() == (tmp_path / "b" / "comparison_sweep-toy.csv").read_text()
    bad = CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--sweep", "000000000000", "--out", str(tmp_path / "c")])
    assert bad.exit_code == 2 and f"unknown sweep id 000000000000; sweeps in this store: {result.sweep_id}" in bad.stderr


def test_bench_runs_are_grouped_by_configuration(swept, tmp_path, monkeypatch):
    from harness.runner import RunConfig, run
    from harness.tracking import MlflowTracker

    uri, result, paths = swept
    sweep_site.activate(paths, monkeypatch)
    for seed, trials in ((2, 2), (3, 2), (2, 3)):  # two configurations: --max-trials 2 (seeds 2, 3) and 3 (seed 2)
        run(RunConfig("sweep-steps", "sweep-toy", seed, max_trials=trials, eval_episodes=2), tracker=MlflowTracker(uri))
    out = tmp_path / "bench"
    cli = CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--include-bench", "--out", str(out)])
    assert cli.exit_code == 0, cli.output
    rows = read_rows(out / "comparison_sweep-toy.csv")
    # the sweep's own row is kept apart from the bench runs made with its settings; rows are named by them
    assert rows[f"sweep-steps [max_trials=2]@{result.sweep_id}"]["runs"] == "3"
    bench = {label: row for label, row in rows.items() if label.startswith("sweep-steps") and not label.endswith(result.sweep_id)}
    assert len(bench) == 2 and "sweep-steps [max_trials=3]" in bench
    assert any(label.startswith("sweep-steps [max_trials=2]@bench-") for label in bench)
    assert sorted((r["runs"], r["solved"], float(r["median_time_to_success_s"])) for r in bench.values()) == [("1", "1", 4.0), ("2", "2", 6.0)]
    assert "harness bench --learner sweep-steps --task sweep-toy --seed S --max-trials 2 --eval-episodes 2  (S = 2-3" in (out / "sweeps.md").read_text()


def test_bench_group_ignores_options_at_their_default():
    """A run logged before an option existed and one with the option at its default share a group;
    the option set otherwise, or any other setting, splits it. Defaults come from the installed plugins."""
    from harness.configuration import bench_group_id
    from harness.configuration import option_defaults as _option_defaults

    old = {"learner": "pilco", "task": "unicycle", "max_trials": "30", "learner.planning_horizon": "20"}
    defaults = _option_defaults("pilco", "unicycle")
    assert defaults["learner.plan_with_noise"] == "False" and defaults["task.init"] == "code"
    assert bench_group_id({**old, "learner.plan_with_noise": "False"}, defaults) == bench_group_id(old, defaults)
    assert bench_group_id({**old, "learner.plan_with_noise": "True"}, defaults) != bench_group_id(old, defaults)
    assert bench_group_id({**old, "max_trials": "40"}, defaults) != bench_group_id(old, defaults)
    assert _option_defaults("no-such-learner", "no-such-task") == {}


def test_bench_command_reproduces_the_group_configuration():
    """The command written for a bench group, parsed back through the CLI's option routing,
    resolves to the same limits and options (so the group id too): every non-default option
    appears as --set, no default does."""
    import shlex

    from harness.options import parse_assignments
    from harness.configuration import bench_command, bench_group_id, run_config
    from harness.configuration import option_defaults as _option_defaults
    from harness.runner import RunConfig, prepare, route_options, run_params

    defaults = _option_defaults("pilco", "double-pendulum")
    config = {**{k: v for k, v in defaults.items()}, "learner": "pilco", "task": "double-pendulum", "max_trials": "40",
              "budget_seconds": "None", "eval_episodes": "10", "task.horizon": "60", "learner.gp_fitc_evals": "300"}
    command = bench_command(config, defaults, "0-2")
    assert command.endswith("(S = 0-2)") and command.count("--set") == 2
    assert "--set learner.gp_fitc_evals=300" in command and "--set task.horizon=60" in command
    argv = shlex.split(command.split("  (S =")[0])
    sets = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
    to_learner, to_task = route_options("pilco", "double-pendulum", parse_assignments(sets))
    prep = prepare(RunConfig("pilco", "double-pendulum", 0, to_learner, to_task, int(argv[argv.index("--max-trials") + 1]), None, 10))
    rebuilt = {"learner": "pilco", "task": "double-pendulum"} | run_config({k: str(v) for k, v in run_params(prep).items()})
    assert bench_group_id(rebuilt, defaults) == bench_group_id(config, defaults)
    # a plugin not installed here: its options are written out, whatever their value
    assert "--set learner.x=1" in bench_command({"learner": "gone", "task": "t", "eval_episodes": "10", "learner.x": "1"}, {}, "0")


def test_test_table_marks_runs_stopped_before_their_limit():
    from harness.report.from_runs import test_markdown

    rows = [{"learner": "pilco", "seed": 0, "solved": False, "finished": False, "test_episodes": 1000, "test_success_rate": 0.0, "run_id": "abcdef123"},
            {"learner": "pilco", "seed": 1, "solved": True, "finished": True, "test_episodes": 1000, "test_success_rate": 0.931, "run_id": "bcdefa234"}]
    md = test_markdown("unicycle", rows)
    # with the Wilson 95 % interval: 0 of 1000 -> [0, 0.38 %], 931 of 1000 -> [91.4, 94.5 %] (scipy's, below)
    assert "| pilco | 0 | no (run stopped before its limit) | 1000 | 0.0 % [0.0, 0.4] | `abcdef12` |" in md
    assert "| pilco | 1 | yes | 1000 | 93.1 % [91.4, 94.5] | `bcdefa23` |" in md


@pytest.mark.parametrize("successes,n", [(0, 1000), (931, 1000), (714, 1000), (0, 12), (12, 12), (3, 7), (1, 1)])
def test_wilson_interval_matches_scipys(successes, n):
    from harness.statistics import wilson_interval

    reference = stats.binomtest(successes, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert wilson_interval(successes, n) == pytest.approx((reference.low, reference.high), abs=1e-12)
    with pytest.raises(ValueError, match="successes of"):
        wilson_interval(n + 1, n)
