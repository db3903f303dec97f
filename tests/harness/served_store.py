"""Fixtures for tests against a served store (`harness store serve`: MLflow on PostgreSQL); import
them into the test module. Their tests need PostgreSQL's binaries on PATH
(:func:`harness.store.server.postgres_available`). As root, PostgreSQL runs as the user ``postgres``,
so the store's folder is made in the system temp folder, traversable by every user.

Ports come from the OS, or from ``HARNESS_TEST_PORTS=LOW-HIGH`` where a machine's tests must keep to a range.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import tempfile
from pathlib import Path

import pytest

from harness.store.server import ServerPaths, stop_postgres
from tests.processes import HarnessProcess

_handed_out: set[int] = set()


def _listenable(port: int) -> bool:
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_ports(count: int) -> list[int]:
    """``count`` consecutive free ports (never handed out twice in this process)."""
    bounds = os.environ.get("HARNESS_TEST_PORTS")
    if not bounds:
        ports = []
        while len(ports) < count:
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", 0))
                port = sock.getsockname()[1]
            if count == 1 or (not ports or port == ports[-1] + 1):
                ports.append(port)
            else:  # not consecutive: start again from a range above the OS's choice
                ports = [p for p in range(port, port + count) if p not in _handed_out and _listenable(p)]
                if len(ports) < count:
                    ports = []
        _handed_out.update(ports)
        return ports
    low, high = (int(b) for b in bounds.split("-"))
    for first in range(low, high - count + 2):
        block = range(first, first + count)
        if not _handed_out.intersection(block) and all(_listenable(p) for p in block):
            _handed_out.update(block)
            return list(block)
    raise RuntimeError(f"no {count} free consecutive ports in HARNESS_TEST_PORTS={bounds}")


def free_port() -> int:
    return free_ports(1)[0]


@pytest.fixture
def store_dir(tmp_path):
    """A folder for a served store that PostgreSQL (the user ``postgres`` when the tests run as root) can reach."""
    if os.geteuid() != 0:
        yield tmp_path / "store"
        return
    base = Path(tempfile.mkdtemp(prefix="harness-serve-"))
    base.chmod(0o755)
    try:
        yield base / "store"
    finally:
        if (base / "store" / "postgres").exists():
            stop_postgres(ServerPaths(base / "store"))
        shutil.rmtree(base, ignore_errors=True)


class ServedStore:
    """`harness store serve` on one store folder and fixed ports, started and stopped (SIGTERM) as often
    as a test needs: a restart serves the same store at the same URI."""

    def __init__(self, store_dir: Path, log_dir: Path) -> None:
        port, db_port = free_port(), free_port()
        self.args = ["store", "serve", "--dir", str(store_dir), "--port", str(port), "--db-port", str(db_port), "--workers", "1"]
        self.uri = f"http://127.0.0.1:{port}"
        self.paths = ServerPaths(store_dir)
        self.log_dir = log_dir
        self.proc: HarnessProcess | None = None

    def start(self) -> HarnessProcess:
        """Start serving and return once the tracking URI is printed."""
        self.proc = HarnessProcess(self.args, self.log_dir)
        self.proc.wait_for("tracking URI: ", timeout=240)
        return self.proc

    def stop(self, timeout: float = 90) -> int | None:
        """SIGTERM the running server and its exit code (``None`` if it was not running)."""
        if self.proc is None or self.proc.proc.poll() is not None:
            return None
        self.proc.signal(signal.SIGTERM)
        return self.proc.wait(timeout=timeout)


@pytest.fixture
def serving(store_dir, tmp_path):
    """A running `harness store serve` process and its tracking URI; stopped (SIGTERM, then PostgreSQL) however the test ends."""
    served = ServedStore(store_dir, tmp_path)
    try:
        proc = served.start()
        yield proc, served.uri, served.paths
    finally:
        try:
            served.stop(timeout=60)
        except AssertionError:
            pass
        stop_postgres(served.paths)
