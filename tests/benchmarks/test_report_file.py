"""The benchmarks' shared output: the command beside every result file, one way of writing it."""

from __future__ import annotations

import ast
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.report_file import command_line, cpu_description, machine_line, write_report

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def test_command_line_can_be_pasted_back():
    line = command_line("/somewhere/benchmarks/gp_check.py", ["--runs", "ab12", "--note", "two words", "--x=$HOME"],
                        env="OMP_NUM_THREADS=1")
    assert line == "OMP_NUM_THREADS=1 python benchmarks/gp_check.py --runs ab12 --note 'two words' '--x=$HOME'"
    assert shlex.split(line)[2:] == ["benchmarks/gp_check.py", "--runs", "ab12", "--note", "two words", "--x=$HOME"]
    assert command_line("gp_check.py", []) == "python benchmarks/gp_check.py"


def test_machine_line_says_when_and_under_what_load():
    line = machine_line(1.25)
    assert line.startswith("Date: 20") and " UTC; " in line
    assert "load average (1 min) 1.2 at the start, " in line and line.endswith(" at the end.")
    assert "at the start" not in machine_line()


CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 1
model name\t: AMD EPYC

processor\t: 1
cpu family\t: 23
model\t\t: 49
model name\t: another CPU
"""


def test_cpu_description_names_family_and_model_of_the_first_processor():
    """A virtual machine's "AMD EPYC" is any of five generations: family and model tell them apart."""
    text = cpu_description(CPUINFO)
    assert text.startswith("AMD EPYC (family 25 model 1")
    assert "another CPU" not in text and "family 23" not in text
    assert cpu_description("").split(" (")[0] != ""  # without /proc/cpuinfo: platform's name
    assert f"; {cpu_description()}, " in machine_line()


def test_write_report_creates_the_folder_writes_once_and_says_where(tmp_path, capsys):
    out = tmp_path / "new" / "folder" / "table.md"
    text = write_report(["# title", "", "| a |", "|---|", ""], out)
    assert text == "# title\n\n| a |\n|---|\n" == out.read_text()
    printed = capsys.readouterr().out
    assert printed.startswith("# title\n") and printed.rstrip().endswith(f"wrote {out}")
    assert write_report(["quiet"], None, echo=False) == "quiet\n"
    assert capsys.readouterr().out == ""


def _calls(path: Path) -> set[str]:
    """Names of the functions and methods a script calls; ``open`` only when it opens a file for writing."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            mode = node.args[1] if len(node.args) > 1 else next((k.value for k in node.keywords if k.arg == "mode"), None)
            if name != "open" or (isinstance(mode, ast.Constant) and "w" in mode.value):
                names.add(name)
    return names


@pytest.mark.parametrize("script", sorted(p.name for p in BENCHMARKS.glob("*.py") if p.name != "report_file.py"))
def test_every_benchmark_writes_its_files_through_write_report(script):
    """(Appending a row to a CSV is not writing a report.)"""
    calls = _calls(BENCHMARKS / script)
    assert not calls & {"write_text", "open"}, f"{script} writes a file itself; use benchmarks.report_file.write_report"
    if "Command: `" in (BENCHMARKS / script).read_text():
        assert "command_line" in calls, f"{script} spells its command line itself; use benchmarks.report_file.command_line"


def test_a_benchmark_run_as_a_script_writes_its_command_and_machine(tmp_path):
    """bench_env_steps imports the helper after its workers' branch (a worker may have a baseline checkout first
    on its path); run it the way the README does, tiny."""
    out = tmp_path / "env.md"
    subprocess.run([sys.executable, str(BENCHMARKS / "bench_env_steps.py"), "--tasks", "cartpole", "--steps", "20",
                    "--repeats", "1", "--out", str(out)], check=True, capture_output=True, text=True, timeout=300)
    lines = out.read_text().splitlines()
    assert lines[2] == f"Command: `python benchmarks/bench_env_steps.py --tasks cartpole --steps 20 --repeats 1 --out {out}`  "
    assert lines[3].startswith("Date: ") and "load average (1 min)" in lines[3]
    assert any(line.startswith("| cartpole | 0.") for line in lines)
