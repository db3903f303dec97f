"""Learner plugins shipped with pilco-harness (registered through entry points like any third party's)."""
