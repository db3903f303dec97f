"""Real ``harness`` processes for tests, isolated from the test process and always cleaned up.

Each command runs in its own session (``start_new_session``), so it and everything it starts
(pool workers, Ray's daemons) share one process group that :meth:`HarnessProcess.stop` kills as a
whole, even after the command itself has died. Output goes to a file, not a pipe: a descendant that
outlives the command cannot block a read, and the test runner's own output pipe is never handed on
(an orphan holding it would keep CI waiting for end-of-file long after pytest finished).

Use as a context manager::

    with HarnessProcess(["bench", ...], tmp_path) as proc:
        proc.wait_for("trial 2/5", timeout=120)
        proc.signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 130, proc.output()
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path


class HarnessProcess:
    """``python -m harness <args>`` in a new session; stdout and stderr go to ``<log_dir>/harness-<n>.log``."""

    _count = 0

    def __init__(self, args: list[str], log_dir: Path, cwd: Path | None = None, env: dict[str, str] | None = None) -> None:
        HarnessProcess._count += 1
        self.log_path = Path(log_dir) / f"harness-{os.getpid()}-{HarnessProcess._count}.log"
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "harness", *args], cwd=cwd or log_dir,
                                     env={**os.environ, **(env or {}), "PYTHONUNBUFFERED": "1"},
                                     stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def output(self) -> str:
        """Everything the command (and its descendants) printed so far."""
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_for(self, marker: str, timeout: float) -> None:
        """Return once ``marker`` appears in the output; fail (with the output) if the command ends first or ``timeout`` s pass."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if marker in self.output():
                return
            if self.proc.poll() is not None:
                raise AssertionError(f"the command ended (exit {self.proc.returncode}) before printing {marker!r}:\n{self.output()}")
            time.sleep(0.05)
        raise AssertionError(f"{marker!r} not printed within {timeout} s:\n{self.output()}")

    def signal(self, signum: int) -> None:
        """Send ``signum`` to the command alone (not its process group), as ``kill PID`` does."""
        self.proc.send_signal(signum)

    def wait(self, timeout: float) -> int:
        """The command's exit code; fail (with the output) if it runs longer than ``timeout`` s."""
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            raise AssertionError(f"the command did not exit within {timeout} s:\n{self.output()}") from None

    def stop(self) -> None:
        """SIGKILL the command's whole process group (it and every descendant still in it)."""
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self.proc.wait()

    def __enter__(self) -> HarnessProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
        self._log.close()


def run_harness(args: list[str], log_dir: Path, timeout: float, cwd: Path | None = None) -> tuple[int, str]:
    """Run ``harness <args>`` to completion in its own session: ``(exit code, output)``."""
    with HarnessProcess(args, log_dir, cwd) as proc:
        code = proc.wait(timeout)
        return code, proc.output()
