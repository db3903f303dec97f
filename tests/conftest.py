"""Test-session settings shared by every test: headless MuJoCo, one torch thread, quiet MLflow."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RAY_AUTH_MODE", "disabled")

import pytest  # noqa: E402


def pytest_configure(config: pytest.Config) -> None:
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover
        pass


@pytest.fixture(autouse=True)
def _restore_sigterm_handler():
    """Tests that run the CLI in this process install its SIGTERM handler; the next test starts with
    the handler the test process had."""
    import signal

    handler = signal.getsignal(signal.SIGTERM)
    yield
    if signal.getsignal(signal.SIGTERM) is not handler:
        signal.signal(signal.SIGTERM, handler)


@pytest.fixture(scope="session")
def mlflow_uri(tmp_path_factory: pytest.TempPathFactory) -> str:
    """One SQLite store per test session (creating one costs ~2-3 s of schema migration)."""
    from harness.tracking import default_tracking_uri, open_client

    directory = tmp_path_factory.mktemp("mlflow")
    uri = default_tracking_uri(directory)
    open_client(uri)
    return uri
