"""Device helpers shared by the tests of the GPU paths (``pilco``, ``mc-pilco``)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import torch

#: marks a test that needs a CUDA GPU; without one it is skipped and ``pytest -ra`` says why
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here: the CUDA path is not exercised")


@contextmanager
def default_device(device: str) -> Iterator[None]:
    """torch's default device set to ``device`` inside the block.

    With ``"meta"`` (a device that holds no data) a tensor created without an explicit device lands
    there, and the first operation that mixes it with the real (CPU) tensors fails: code that passes
    under it leaves nothing on the host when its inputs live on a GPU.
    """
    torch.set_default_device(device)
    try:
        yield
    finally:
        torch.set_default_device(None)


def run_on_cuda(learner: str, options: dict[str, str]):
    """A two-trial run of ``learner`` on a short cart-pole (15 steps, 2 evaluation episodes) with
    ``device=cuda`` added to its ``options``; returns its :class:`~harness.runner.RunResult`."""
    from harness.runner import RunConfig, run

    return run(RunConfig(learner, "cartpole", seed=0, learner_options={**options, "device": "cuda"},
                         task_options={"horizon": 15}, max_trials=2, eval_episodes=2))
