"""Fuzzing the command line: random option strings and malformed values never escape as a traceback."""

from __future__ import annotations

import random

from click.testing import CliRunner

from harness.cli import main

NAMES = ["random", "cartpole", "pilco", "", "CARTPOLE", "cart pole", "nosuch", "../etc", "ünïcode", "-1", "--set"]
KEYS = ["scale", "horizon", "pole_length", "cost_width", "measurement_noise", "substeps", "bogus", "", "learner.scale",
        "task.horizon", "task.", "learner.nosuch", "a=b", " scale "]
VALUES = ["0", "1", "-1", "0.5", "1e309", "nan", "inf", "-inf", "", " ", "abc", "1,5", "0x10", "True", "none", "None",
          "1" * 400, "2.5", "1e-300", "ä", "'1'", "[1]"]
FLAGS = [["--seed", "-3"], ["--seed", "x"], ["--max-trials", "0"], ["--max-trials", "2.5"], ["--budget-seconds", "nan"],
         ["--budget-seconds", "-0"], ["--budget-seconds", "1e-9"], ["--eval-episodes", "0"], ["--eval-episodes", "-2"], []]


def test_random_cli_input_never_shows_a_traceback():
    rng = random.Random(20261122)
    runner = CliRunner()
    outcomes = {0: 0, 2: 0}
    for _ in range(150):
        args = ["bench", "--no-tracking", "-q", "--max-trials", "1", "--eval-episodes", "1"]
        args += ["--learner", rng.choice(NAMES[:1] * 4 + NAMES), "--task", rng.choice(NAMES[1:2] * 4 + NAMES)]
        for _ in range(rng.randint(0, 3)):
            args += ["--set", f"{rng.choice(KEYS)}={rng.choice(VALUES)}" if rng.random() < 0.9 else rng.choice(KEYS)]
        args += rng.choice(FLAGS)
        result = runner.invoke(main, args)
        assert "Traceback" not in result.output, (args, result.output)
        assert result.exception is None or isinstance(result.exception, SystemExit), (args, repr(result.exception))
        assert result.exit_code in (0, 2), (args, result.exit_code, result.output)
        if result.exit_code == 2:
            lines = [line for line in result.output.strip().splitlines() if line.strip()]
            assert lines and (lines[-1].startswith("error:") or lines[-1].startswith("Error:")), (args, result.output)
        outcomes[result.exit_code] += 1
    assert outcomes[0] > 0 and outcomes[2] > 0  # both valid and invalid inputs were exercised
