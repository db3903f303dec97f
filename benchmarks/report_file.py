"""What every benchmark's markdown file carries: the command that made it, when and where, and the write.

A result is only worth as much as its provenance (the command that produced it, beside it). Each
script in ``benchmarks/`` builds its table as a list of markdown lines and hands it to
:func:`write_report`; :func:`command_line` gives the shell command that reproduces the file, and
:func:`machine_line` when and on what it was measured (for the scripts that time something).
"""

from __future__ import annotations

import math
import os
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path


def command_line(script: str, argv: Sequence[str] | None = None, *, env: str = "") -> str:
    """The shell command that reproduces a benchmark's output: ``[env ]python benchmarks/<script> <args>``.

    ``script``: the benchmark's ``__file__`` (only its name is used); ``argv``: the arguments its
    ``main`` parsed (default ``sys.argv[1:]``), each shell-quoted so that the line can be pasted
    back; ``env``: variables the run needs set first, e.g. ``"OMP_NUM_THREADS=1"``.
    """
    words = [f"python benchmarks/{Path(script).name}", *(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))]
    return " ".join([env, *words] if env else words)


def load_average() -> float:
    """The 1-minute load average (NaN where the platform has none)."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan


def cpu_description(cpuinfo: str | None = None) -> str:
    """The CPU as a reader can look it up: ``"AMD EPYC (family 25 model 1, LLVM znver3)"``.

    ``model name``, ``cpu family`` and ``model`` of ``/proc/cpuinfo`` (or of the ``cpuinfo`` text given),
    and the name LLVM gives the host (the target numba compiles for) where llvmlite is installed. A
    model name alone says neither the generation (a virtual machine's "AMD EPYC" is any of five) nor
    the vector units; family and model do. Falls back to :func:`platform.processor`.
    """
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            if fields:
                break  # the first processor's block only
            continue
        fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name") or platform.processor() or platform.machine()
    details = [f"family {fields['cpu family']} model {fields['model']}"] if "cpu family" in fields and "model" in fields else []
    try:
        import llvmlite.binding as llvm

        details.append(f"LLVM {llvm.get_host_cpu_name()}")
    except Exception:  # noqa: BLE001 - llvmlite absent or unable to tell: the line goes without it
        pass
    return f"{name} ({', '.join(details)})" if details else name


def machine_line(load_at_start: float | None = None) -> str:
    """One line: ``Date: <UTC>; <cpu (cpu_description)>, <n> CPUs (shared with other jobs); Python <v>[, torch <v>]; load average ...``.

    ``load_at_start``: :func:`load_average` taken before the measurement, shown beside the load
    now, so that a reader can tell a quiet run from a crowded one (this machine is shared).
    torch's version is given when the benchmark has imported torch.
    """
    torch = sys.modules.get("torch")
    software = f"Python {platform.python_version()}" + (f", torch {torch.__version__}" if torch is not None else "")
    now = load_average()
    load = (f"load average (1 min) {load_at_start:.1f} at the start, {now:.1f} at the end" if load_at_start is not None
            else f"load average (1 min) {now:.1f}")
    return (f"Date: {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}; {cpu_description()}, "
            f"{os.cpu_count()} CPUs (shared with other jobs); {software}; {load}.")


def write_report(lines: Sequence[str], out: Path | str | None, *, echo: bool = True) -> str:
    """Join ``lines`` into one markdown text ending in a newline, print it (``echo``), write it to ``out``.

    ``out=None`` prints only. The folder of ``out`` is created if missing, and the path written is
    printed last. Returns the text.
    """
    text = "\n".join(lines).rstrip("\n") + "\n"
    if echo:
        print(text, flush=True)
    if out is not None:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(f"wrote {path}", flush=True)
    return text
