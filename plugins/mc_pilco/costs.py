"""Planning costs of the MC-PILCO paper, per task (Amadio et al., IEEE T-RO 2022).

Particles need the cost only at known states, so MC-PILCO plans with costs that have no closed-form
moments under a Gaussian. Its cart-pole cost acts on the pole's angle and the cart's position
separately, with the angle *unwrapped*::

    c(x) = 1 - exp(-((|theta| - pi) / 3)^2 - (x / 1)^2)        theta in rad (0: hanging), x in m

Upright either way round (theta = +-pi) costs 0 and hanging costs 1 - exp(-(pi/3)^2) = 0.67; a pole
that has turned a whole circle past upright (|theta| = 3 pi) costs 0.99, so a policy that spins the pole
is charged for it. The task's own cost (the pole tip's distance from the upright target, a function
of sin and cos of theta) charges a spinning pole only while the tip is away from the target.

:class:`StateCost` is that form for any task: a saturating cost of chosen state entries, each folded by
``|.|`` where asked, with per-entry targets and length-scales (no factor 1/2, as MC-PILCO writes it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class StateCost:
    """``c(x) = 1 - exp(-sum_k ((g_k(x[indices_k]) - targets_k) / lengthscales_k)^2)``, ``g_k = |.|``
    where ``folded_k``, else the identity; in ``[0, 1)``.

    Attributes:
        name: what the cost is, in words (named in its error messages).
        indices: the state entries costed, ``(K,)``.
        targets: their targets, in the state's units, ``(K,)``.
        lengthscales: their length-scales, in the state's units, ``(K,)``, each > 0.
        folded: whether an entry enters as its absolute value, ``(K,)``.
    """

    name: str
    indices: tuple[int, ...]
    targets: tuple[float, ...]
    lengthscales: tuple[float, ...]
    folded: tuple[bool, ...]

    def __post_init__(self) -> None:
        k = len(self.indices)
        if not (len(self.targets) == len(self.lengthscales) == len(self.folded) == k) or k == 0:
            raise ValueError(f"{self.name}: indices, targets, lengthscales and folded need the same length >= 1")
        if not all(ell > 0 for ell in self.lengthscales):
            raise ValueError(f"{self.name}: length-scales must be > 0, got {self.lengthscales}")

    def _distance(self, entries, absolute, targets, lengthscales):
        g = [absolute(entries[..., k]) if fold else entries[..., k] for k, fold in enumerate(self.folded)]
        return sum(((g[k] - targets[k]) / lengthscales[k]) ** 2 for k in range(len(g)))

    def sample(self, x: torch.Tensor) -> torch.Tensor:
        """The cost at known states ``x (..., D)`` -> ``(...)``, differentiable in ``x``."""
        entries = x[..., list(self.indices)]
        return 1.0 - torch.exp(-self._distance(entries, torch.abs, self.targets, self.lengthscales))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """The same cost on a NumPy array of states ``(..., D)`` -> ``(...)``."""
        entries = np.asarray(x, dtype=np.float64)[..., list(self.indices)]
        return 1.0 - np.exp(-self._distance(entries, np.abs, self.targets, self.lengthscales))


#: MC-PILCO's cart-pole cost on this harness's cart-pole state ``(x, xdot, thetadot, theta)``: the
#: paper's length-scales 3 rad (angle) and 1 m (position), target theta = +-pi, x = 0.
CARTPOLE = StateCost("MC-PILCO's cart-pole cost: 1 - exp(-((|theta| - pi)/3)^2 - (x/1)^2), theta unwrapped",
                     indices=(3, 0), targets=(math.pi, 0.0), lengthscales=(3.0, 1.0), folded=(True, False))

#: the MC-PILCO paper's planning cost per task name (those it defines for a task of this harness)
PAPER_COSTS: dict[str, StateCost] = {"cartpole": CARTPOLE}
