"""benchmarks/mc_pilco_search_check.py: a stored mc-pilco trial's search rebuilt exactly, then varied."""

from __future__ import annotations

import pytest

from harness.errors import OptionError
from harness.runner import RunConfig, run

TINY = {"num_centres": "4", "particles": "12", "max_steps": "10", "window": "3", "gp_max_evals": "15"}


def test_the_runs_own_search_is_repeated_exactly_and_a_variant_changes_only_its_options(tmp_path):
    from benchmarks.mc_pilco_search_check import main, stored_start
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path)
    # a horizon that grows 4 -> 8 before trial 2's search (any real episode is below 1000 per step): the
    # repeat must plan over the trial's grown horizon, not the option's start, to end where the run did
    growing = TINY | {"planning_horizon": "4", "grow_horizon_below": "1000", "grow_horizon_on": "realised"}
    result = run(RunConfig("mc-pilco", "cartpole", seed=4, learner_options=growing, task_options={"horizon": 10}, max_trials=3,
                           eval_episodes=1), tracker=MlflowTracker(uri))
    config, *_, stored, horizon = stored_start(result.run_id, 2, uri)
    assert config.seed == 4 and config.learner_options["max_steps"] == 10 and stored == result.history[1]["J_after"]
    assert result.history[0]["planning_horizon"] == 4 and horizon == 8
    out = tmp_path / "search.md"
    main(["--run", result.run_id, "--trial", "2", "--variants", "", "max_steps=2", "--episodes", "3", "--tracking-uri", uri,
          "--out", str(out)])
    text = out.read_text()
    # the GP, the start and the random numbers are the run's: the repeated search ends where the run's did, to the bit
    assert f"J after {stored:.6f}, stored {stored:.6f}." in text
    rows = [line.split("|")[1:-1] for line in text.splitlines() if line.startswith("| max_steps=2 ")]
    assert len(rows) == 1 and int(rows[0][2]) == 2  # two Adam steps, as asked
    assert int(rows[0][7].split("/")[1].split()[0]) == 3  # scored on the 3 test episodes


def test_a_fresh_start_is_the_runs_initial_controller_at_offset_0_and_another_one_elsewhere(tmp_path):
    from benchmarks.mc_pilco_search_check import main, stored_start
    from harness.tracking import MlflowTracker, default_tracking_uri

    uri = default_tracking_uri(tmp_path)
    # MC-PILCO's own cost: wide enough that three controllers' J differ over 10 steps (the task's saturates at 10)
    result = run(RunConfig("mc-pilco", "cartpole", seed=5, learner_options=TINY | {"cost": "paper"}, task_options={"horizon": 10}, max_trials=3,
                           eval_episodes=1), tracker=MlflowTracker(uri))
    *_, stored, _ = stored_start(result.run_id, 2, uri)
    out = tmp_path / "fresh.md"
    own = f"start={result.run_id},start_trial=1"  # the run's own stored policy of trial 1: trial 2's start
    main(["--run", result.run_id, "--trial", "2", "--variants", "", "start=fresh", "start=fresh,start_seed=1", own, "--episodes",
          "2", "--tracking-uri", uri, "--out", str(out)])
    rows = {line.split("|")[1].strip(): line.split("|")[5].strip() for line in out.read_text().splitlines()
            if line.startswith("| ") and not line.startswith("| variant")}
    before = {k: float(v.split("->")[0]) for k, v in rows.items()}
    # trial 2's search starts from trial 1's policy; a fresh start from the run's initial controller (offset 0)
    # and from another draw (offset 1): three different starting J on the same particles
    assert f"{stored:.2f}" in rows["the run's options"].split("->")[1]
    assert rows[own] == rows["the run's options"]  # the stored policy file is the checkpoint's controller
    assert len(before) == 4 and len(set(before.values())) == 3
    # trial 1's search started from the initial controller: offset 0 at trial 1 ends at the stored J (the table's 2 decimals)
    out1 = tmp_path / "fresh1.md"
    *_, stored1, _ = stored_start(result.run_id, 1, uri)
    main(["--run", result.run_id, "--trial", "1", "--variants", "start=fresh", "--episodes", "2", "--tracking-uri", uri,
          "--out", str(out1)])
    row = next(line for line in out1.read_text().splitlines() if line.startswith("| start=fresh "))
    assert row.split("|")[5].split("->")[1].split("(")[0].strip() == f"{stored1:.2f}"


def test_start_keys_are_checked():
    from benchmarks.mc_pilco_search_check import Start, split_start

    assert split_start({"max_steps": "3"}) == ({"max_steps": "3"}, Start())
    assert split_start({"start": "fresh", "start_seed": "2", "lr": "0.1"}) == ({"lr": "0.1"}, Start("fresh", offset=2))
    assert split_start({"start": "abc", "start_trial": "4"}) == ({}, Start("run", run_id="abc", trial=4))
    with pytest.raises(OptionError, match="add start=fresh"):
        split_start({"start_seed": "1"})
    with pytest.raises(OptionError, match="add start_trial=J"):
        split_start({"start": "abc"})
    with pytest.raises(OptionError, match="start_trial is an integer"):
        split_start({"start": "abc", "start_trial": "last"})
    with pytest.raises(OptionError, match="start_trial without a run"):
        split_start({"start": "fresh", "start_trial": "2"})


def test_variants_are_key_value_pairs():
    from benchmarks.mc_pilco_search_check import parse_variant

    assert parse_variant("") == {}
    assert parse_variant("max_steps=3000, particles=1600") == {"max_steps": "3000", "particles": "1600"}
    with pytest.raises(OptionError, match="'particles' is not key=value"):
        parse_variant("max_steps=3,particles")
