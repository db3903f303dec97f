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


def test_variants_are_key_value_pairs():
    from benchmarks.mc_pilco_search_check import parse_variant

    assert parse_variant("") == {}
    assert parse_variant("max_steps=3000, particles=1600") == {"max_steps": "3000", "particles": "1600"}
    with pytest.raises(OptionError, match="'particles' is not key=value"):
        parse_variant("max_steps=3,particles")
