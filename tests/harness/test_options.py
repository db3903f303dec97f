"""Declared options: parsing, validation and routing of --set values."""

from __future__ import annotations

import pytest

from harness.errors import OptionError
from harness.options import Option, OptionSet, parse_assignments, split_assignments

OPTS = OptionSet(
    (
        Option("n_centres", int, 50, "centres", low=1),
        Option("width", float, 0.25, "cost width", low=0.0),
        Option("controller", str, "rbf", "type", choices=("rbf", "linear")),
        Option("sparse", bool, True, "use FITC"),
    ),
    "learner 'x'",
)


def test_defaults_and_parsing():
    assert OPTS.resolve({}) == {"n_centres": 50, "width": 0.25, "controller": "rbf", "sparse": True}
    got = OPTS.resolve({"n_centres": "10", "width": "1e-1", "controller": "linear", "sparse": "no"})
    assert got == {"n_centres": 10, "width": 0.1, "controller": "linear", "sparse": False}


@pytest.mark.parametrize(
    "key,value,message",
    [
        ("n_centres", "ten", "expects an integer"),
        ("n_centres", "2.5", "expects an integer"),
        ("n_centres", "0", "must be >= 1"),
        ("width", "nan", "finite"),
        ("width", "-1", "must be >= 0"),
        ("controller", "mlp", "must be one of rbf, linear"),
        ("sparse", "maybe", "true/false"),
    ],
)
def test_bad_values_name_the_option_and_the_expectation(key, value, message):
    with pytest.raises(OptionError, match=message) as err:
        OPTS.resolve({key: value})
    assert key in str(err.value) and "\n" not in str(err.value)


def test_unknown_key_lists_valid_keys_and_suggests():
    with pytest.raises(OptionError, match="Did you mean 'n_centres'.*Valid options: n_centres, width, controller, sparse"):
        OPTS.resolve({"n_centers": 3})


def test_assignments_need_key_and_value():
    assert parse_assignments(["a=1", "b = x=y"]) == [("a", "1"), ("b", " x=y")]
    for bad in ("novalue", "=3"):
        with pytest.raises(OptionError, match="key=value"):
            parse_assignments([bad])


def test_routing_between_learner_and_task():
    task = OptionSet((Option("horizon", int, 40, "steps"), Option("width", float, 0.25, "w")), "task 't'")
    learner, tsk = split_assignments([("n_centres", "5"), ("horizon", "30"), ("task.width", "0.3")], OPTS, task)
    assert learner == {"n_centres": "5"} and tsk == {"horizon": "30", "width": "0.3"}
    with pytest.raises(OptionError, match="both"):
        split_assignments([("width", "0.3")], OPTS, task)
    with pytest.raises(OptionError, match="unknown option 'nope'"):
        split_assignments([("nope", "1")], OPTS, task)
