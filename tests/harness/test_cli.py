"""The command line: listing, a real bench run read back from MLflow, and one-line errors."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from harness.cli import main

HARNESS = [sys.executable, "-m", "harness"]


def run_cli(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*HARNESS, *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=300)


HEAVY = ("mlflow", "scipy.optimize", "stable_baselines3", "torch")


def heavy_modules_after(args: list[str]) -> tuple[str, list[str]]:
    """The output of ``harness ARGS`` in a fresh interpreter and which of :data:`HEAVY` it imported."""
    code = (
        "import sys\n"
        "from harness.cli import main\n"
        f"try:\n    main({args!r})\nexcept SystemExit:\n    pass\n"
        f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stdout.strip()
    *shown, loaded = out.splitlines()
    return "\n".join(shown), ast.literal_eval(loaded)


def test_help_and_version_do_not_import_mlflow_or_torch():
    shown, loaded = heavy_modules_after(["--help"])
    assert "Commands:" in shown and loaded == []
    assert "harness, version 0.1.0" in CliRunner().invoke(main, ["--version"]).output


def test_list_does_not_import_torch_or_mlflow():
    """``harness list --options`` loads every plugin class but none of torch, SB3 or MLflow (~2.5 s
    each): learners import their machinery when they run."""
    shown, loaded = heavy_modules_after(["list", "--options"])
    assert "pilco" in shown and "mc-pilco" in shown and "unicycle" in shown
    assert loaded == []


def test_output_into_a_closed_pipe_stops_quietly():
    """`harness list | head -1`: once the reader has gone, the command stops without an error message
    (exit 141, as a Unix tool killed by SIGPIPE) instead of reporting an unexpected BrokenPipeError."""
    proc = subprocess.Popen([*HARNESS, "list", "--options"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader goes before the first line is written
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141, err
    assert err == ""


def test_list_shows_plugins():
    result = CliRunner().invoke(main, ["list", "--options"])
    assert result.exit_code == 0
    assert "random" in result.output and "cartpole" in result.output
    assert "--set scale (float, default 1.0" in result.output


def test_list_names_shows_those_plugins_with_their_options():
    """`harness list NAME...` lists only the named learners and tasks, options included (no --options needed)."""
    result = CliRunner().invoke(main, ["list", "random", "unicycle"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert "Learners:" in lines and "Tasks:" in lines
    named = [line.split()[0] for line in lines if line.startswith("  ") and not line.strip().startswith("--set")]
    assert named == ["random", "unicycle"]
    assert "--set scale (float, default 1.0" in result.output and "--set init (str, default 'code'" in result.output
    only_task = CliRunner().invoke(main, ["list", "cartpole"])
    assert only_task.exit_code == 0 and "Learners:" not in only_task.output and "--set" in only_task.output


def test_list_unknown_name_is_one_line_error():
    result = CliRunner().invoke(main, ["list", "unicycel"])
    assert result.exit_code != 0
    assert "no learner or task named 'unicycel'. Did you mean 'unicycle'?" in result.output
    assert "Installed:" in result.output and "Traceback" not in result.output


@pytest.mark.parametrize(
    "args,message",
    [
        (["bench", "--learner", "nosuch", "--task", "cartpole"], "unknown learner 'nosuch'. Available learners:"),
        (["bench", "--learner", "random", "--task", "cartpol"], "Did you mean 'cartpole'?"),
        (["bench", "-l", "random", "-t", "cartpole", "--set", "bogus=1"], "unknown option 'bogus'"),
        (["bench", "-l", "random", "-t", "cartpole", "--set", "scale=big"], "expects a number"),
        (["bench", "-l", "random", "-t", "cartpole", "--set", "scale"], "--set expects key=value"),
        (["bench", "-l", "random", "-t", "cartpole", "--budget-seconds", "-5"], "--budget-seconds must be a positive"),
        (["bench", "-l", "random", "-t", "cartpole", "--budget-seconds", "lots"], "expects a number of seconds"),
        (["bench", "-l", "random", "-t", "cartpole", "--max-trials", "0"], "--max-trials must be >= 1"),
        (["bench", "-l", "random", "-t", "cartpole", "--seed", "-1"], "--seed must be >= 0"),
    ],
)
def test_bad_input_is_one_line_and_nonzero(args, message):
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_unwritable_store_is_a_one_line_error(tmp_path):
    result = CliRunner().invoke(
        main, ["bench", "-l", "random", "-t", "cartpole", "--max-trials", "1", "--tracking-uri", "sqlite:////nonexistent/dir/mlflow.db"]
    )
    assert result.exit_code == 2 and "not writable" in result.output and "Traceback" not in result.output


def test_bench_writes_an_mlflow_run_that_reads_back(tmp_path, mlflow_uri):
    proc = run_cli(
        "bench", "--learner", "random", "--task", "cartpole", "--seed", "0", "--max-trials", "3",
        "--eval-episodes", "3", "--tracking-uri", mlflow_uri, "--set", "horizon=20", cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert "trial 3/3" in proc.stderr  # progress, a line per trial
    import mlflow

    mlflow.set_tracking_uri(mlflow_uri)
    runs = mlflow.search_runs(experiment_names=["cartpole"], filter_string="params.learner = 'random'")
    assert len(runs) >= 1
    row = runs.iloc[0]
    assert row["status"] == "FINISHED"
    for key, value in {"learner": "random", "task": "cartpole", "seed": "0", "task.horizon": "20", "learner.scale": "1.0"}.items():
        assert row[f"params.{key}"] == value
    assert row["params.git_sha"] and row["params.version.torch"]
    assert row["metrics.interaction_seconds"] == pytest.approx(3 * 20 * 0.1)
    assert row["metrics.solved"] == 0.0 and row["tags.solved"] == "false"
    assert "metrics.interaction_time_to_success_seconds" not in runs.columns or runs["metrics.interaction_time_to_success_seconds"].isna().all()
    client = mlflow.MlflowClient(mlflow_uri)
    history = client.get_metric_history(row["run_id"], "eval_success_rate")
    assert [m.step for m in history] == [1, 2, 3]
    artifacts = {a.path for a in client.list_artifacts(row["run_id"])}
    assert {"policies", "episodes", "result.json"} <= artifacts
    assert not (tmp_path / "mlruns").exists()  # artifacts live beside the store, not in the cwd
    # the printed report command selects this configuration's runs
    import re

    command = re.search(r"report: (harness report .*--sweep (bench-[0-9a-f]{8}))", proc.stdout)
    assert command, proc.stdout
    out = tmp_path / "by-group"
    report = CliRunner().invoke(main, ["report", "--tracking-uri", mlflow_uri, "--sweep", command.group(2), "--out", str(out)])
    assert report.exit_code == 0, report.output
    assert f"`{row['run_id'][:8]}`" in (out / "runs_cartpole.md").read_text()


def test_main_module_entry_point_help():
    proc = run_cli("--help")
    assert proc.returncode == 0 and "bench" in proc.stdout


def test_eval_tests_a_saved_policy_and_logs_to_the_run(tmp_path, mlflow_uri):
    import mlflow

    proc = run_cli("bench", "-l", "random", "-t", "cartpole", "--seed", "5", "--max-trials", "1", "--eval-episodes", "1",
                   "--tracking-uri", mlflow_uri, "-q", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    mlflow.set_tracking_uri(mlflow_uri)
    run_id = mlflow.search_runs(experiment_names=["cartpole"], filter_string="params.seed = '5'").iloc[0]["run_id"]
    result = CliRunner().invoke(main, ["eval", run_id, "--episodes", "12", "--out", str(tmp_path / "ev"), "--tracking-uri", mlflow_uri])
    assert result.exit_code == 0, result.output
    assert "succeeded in 0.0% of 12 test episodes (95 % interval 0.0-24.2%" in result.output  # Wilson: 1.96^2 / (12 + 1.96^2)
    import json

    summary = json.loads((tmp_path / "ev" / "test_summary.json").read_text())
    assert summary["episodes"] == 12 and summary["success_rate"] == 0.0 and summary["final_distance_median"] > 0.08
    assert (tmp_path / "ev" / "test_final_distance.png").exists()
    run = mlflow.MlflowClient(mlflow_uri).get_run(run_id)
    assert run.data.metrics["test_success_rate"] == 0.0 and run.data.metrics["test_episodes"] == 12
    missing = CliRunner().invoke(main, ["eval", "no-such-run", "--tracking-uri", mlflow_uri])
    assert missing.exit_code == 2 and "no run 'no-such-run'" in missing.output

    # `harness report` picks the test up from the store: a per-task table and the histogram (Fig. 4b)
    out = tmp_path / "results"
    report = CliRunner().invoke(main, ["report", "--tracking-uri", mlflow_uri, "--include-bench", "--out", str(out)])
    assert report.exit_code == 0, report.output
    table = (out / "test_cartpole.md").read_text()
    assert f"| 5 | no | 12 | 0.0 % [0.0, 24.2] | `{run_id[:8]}` |" in table
    assert len(list(out.glob("fig4b_cartpole_random*.png"))) == 1


def test_two_bench_processes_on_one_fresh_store(tmp_path):
    """Both runs complete and are recorded (the store's creation is serialised by a file lock)."""
    uri = f"sqlite:///{tmp_path / 'fresh.db'}"
    procs = [
        subprocess.Popen([*HARNESS, "bench", "-l", "random", "-t", "cartpole", "--seed", str(s), "--max-trials", "2",
                          "--eval-episodes", "1", "--tracking-uri", uri, "-q"], cwd=tmp_path, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
        for s in (0, 1)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-500:] for o in outs]
    import mlflow

    mlflow.set_tracking_uri(uri)
    runs = mlflow.search_runs(experiment_names=["cartpole"])
    assert sorted(runs["params.seed"]) == ["0", "1"] and set(runs["status"]) == {"FINISHED"}


def test_bench_runs_record_the_task_sizes(tmp_path, mlflow_uri):
    """Table 1 reads the state dimension from every run, sweep child or plain bench run."""
    proc = run_cli("bench", "-l", "random", "-t", "cartpole", "--seed", "7", "--max-trials", "1", "--eval-episodes", "1",
                   "--tracking-uri", mlflow_uri, "-q", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    import mlflow

    mlflow.set_tracking_uri(mlflow_uri)
    row = mlflow.search_runs(experiment_names=["cartpole"], filter_string="params.seed = '7'").iloc[0]
    assert (row["params.spec.state_dim"], row["params.spec.action_dim"], row["params.spec.dt"], row["params.spec.horizon"]) == ("4", "1", "0.1", "40")
