"""Success predicates shared by the swing-up tasks: "the tip stayed close to its target".

Two rules over the per-step distances ``d`` (metres) of an episode's TRUE states:

* ``"consecutive"`` (default): ``d <= radius`` for at least ``steps`` consecutive recorded steps
  anywhere in the episode. This is the cart-pole criterion of Kamthe & Deisenroth (AISTATS 2018):
  "the pendulum tip is closer than 8 cm to the target position for ten consecutive time steps";
  with it, the harness's PILCO numbers are comparable to theirs (PILCO: ~5 trials, ~15 s).
* ``"final"``: ``d <= radius`` in each of the last ``steps`` recorded steps (still balanced when the
  episode ends): stricter; the harness's default before 2026-11-22.
"""

from __future__ import annotations

import numpy as np

#: the rules :func:`held_within` accepts (the tasks' ``success_rule`` option)
SUCCESS_RULES = ("consecutive", "final")


def held_within(distances: np.ndarray, radius: float, steps: int, rule: str = "consecutive") -> bool:
    """Whether ``distances`` ``(T,)`` stay ``<= radius`` for ``steps`` steps under ``rule``.

    Episodes shorter than ``steps`` never succeed.
    """
    d = np.asarray(distances, dtype=np.float64).reshape(-1)
    if rule not in SUCCESS_RULES:
        raise ValueError(f"unknown success rule {rule!r}; choose one of {', '.join(SUCCESS_RULES)}")
    if d.shape[0] < steps:
        return False
    inside = d <= radius
    if rule == "final":
        return bool(inside[-steps:].all())
    run = 0
    for flag in inside:
        run = run + 1 if flag else 0
        if run >= steps:
            return True
    return False
