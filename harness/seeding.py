"""Seeding: one run seed fans out into independent streams for each consumer."""

from __future__ import annotations

import random
import sys

import numpy as np

#: stream names, in spawn order (never reorder: it would change every seeded result)
STREAMS = ("interaction", "evaluation", "learner")


def derive_seeds(seed: int) -> dict[str, int]:
    """Independent 31-bit seeds per stream, from :class:`numpy.random.SeedSequence`."""
    children = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))
    return {name: int(child.generate_state(1)[0] & 0x7FFFFFFF) for name, child in zip(STREAMS, children)}


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's global and (if imported) torch's generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.manual_seed(seed)
