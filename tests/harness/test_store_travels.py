"""A store that travels: a copy of a store at another path reads every file, refuses writes until
relocated, and once relocated opens every artifact as `mlflow ui` does; a committed store keeps the
small files within the budget and says in each run's description what it left out."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
from click.testing import CliRunner

from harness.cli import main
from harness.errors import TrackingError
from harness.runner import RunConfig, run
from harness.store import Store, layout
from harness.store.committed import BUDGET_BYTES, MAX_FILE_BYTES, committed
from harness.sweep import SweepSpec, pools, run_sweep
from harness.tracking import MlflowTracker
from tests.harness import sweep_site
from tests.harness.trackers import InterruptedMlflow

REPO = Path(__file__).resolve().parents[2]


def uri_of(folder: Path) -> str:
    return f"sqlite:///{folder / 'mlflow.db'}"


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> Path:
    """A store with bench runs, a sweep and a published report (its comparison runs and their files)."""
    folder = tmp_path_factory.mktemp("original")
    paths = sweep_site.install(tmp_path_factory.mktemp("travel-plugins"))
    with pytest.MonkeyPatch.context() as mp:
        sweep_site.activate(paths, mp)
        mp.setattr(pools, "LocalPool", sweep_site.InlinePool)
        spec = SweepSpec(("sweep-steps", "random"), ("sweep-toy",), (2, 3), max_trials=2, eval_episodes=1)
        result = run_sweep(spec, uri_of(folder))
        for seed in (0, 1):
            run(RunConfig("random", "cartpole", seed, max_trials=2, eval_episodes=1), tracker=MlflowTracker(uri_of(folder)))
        report = CliRunner().invoke(main, ["report", "--tracking-uri", uri_of(folder), "--sweep", result.sweep_id,
                                           "--out", str(tmp_path_factory.mktemp("report")), "--fig5-task", "sweep-toy"])
        assert report.exit_code == 0, report.output
    return folder


def files_by_run(store: Store) -> dict[str, list[str]]:
    return {r.run_id: [a.path for a in r.all_artifacts()] for r in store.search(None)}


def test_a_copy_reads_every_file_refuses_writes_and_once_relocated_opens_every_artifact(original, tmp_path):
    copy = tmp_path / "elsewhere" / "runs"
    shutil.copytree(original, copy)
    before = files_by_run(Store(uri_of(original)))
    assert sum(map(len, before.values())) > 20 and any(p.startswith("report/") for paths in before.values() for p in paths)

    # the harness reads every file of the copy from the copy's own folder
    moved = Store(uri_of(copy))
    assert files_by_run(moved) == before
    for reader in moved.search(None):
        for artifact in reader.all_artifacts():
            assert reader.file(artifact.path).is_relative_to(copy)
    # but writes nothing where the store was recorded: new runs and files would land at the old path
    with pytest.raises(TrackingError, match=r"outside the store's folder .*harness store relocate --tracking-uri"):
        MlflowTracker(uri_of(copy)).start("cartpole", "x", {}, {})
    checked = CliRunner().invoke(main, ["store", "check", "--tracking-uri", uri_of(copy)])
    assert checked.exit_code == 1 and "harness store relocate" in checked.stderr and "its files are in this store's folder" in checked.output

    relocated = CliRunner().invoke(main, ["store", "relocate", "--tracking-uri", uri_of(copy)])
    assert relocated.exit_code == 0 and "10 runs now keep their artifacts in the store's folder" in relocated.output, relocated.output
    assert str(original / "mlruns") in relocated.output.split("(before: ")[1]  # and the Default experiment's, wherever it was
    assert "already in the store's folder" in CliRunner().invoke(main, ["store", "relocate", "--tracking-uri", uri_of(copy)]).output
    assert CliRunner().invoke(main, ["store", "check", "--tracking-uri", uri_of(copy)]).exit_code == 0
    # MLflow itself (what `mlflow ui` lists and serves) now finds every artifact in the copy
    client = Store(uri_of(copy)).client
    for run_id, paths in before.items():
        for path in paths:
            local = Path(client.download_artifacts(run_id, path, str(tmp_path / "downloads" / run_id)))
            assert local.read_bytes() == (copy / Path(moved.run(run_id).local_root).relative_to(copy) / path).read_bytes()
        assert client.get_run(run_id).info.artifact_uri.startswith((copy / "mlruns").as_uri())
    # and new runs write into the copy, not into the original
    result = run(RunConfig("random", "cartpole", 5, max_trials=1, eval_episodes=1), tracker=MlflowTracker(uri_of(copy)))
    assert Store(uri_of(copy)).run(result.run_id).local_root.is_relative_to(copy)
    assert files_by_run(Store(uri_of(original))) == before


def test_a_clone_with_only_the_committed_files_opens_every_link_and_says_what_it_left_out(original, tmp_path):
    described = CliRunner().invoke(main, ["store", "describe", "--tracking-uri", uri_of(original)])
    assert described.exit_code == 0 and "run descriptions say what is committed" in described.output
    clone = tmp_path / "clone"
    clone.mkdir()
    shutil.copy(original / "mlflow.db", clone / "mlflow.db")
    for path in (original / "mlruns").rglob("*"):
        if path.is_file() and committed(path.relative_to(original).as_posix()):
            (clone / path.relative_to(original).parent).mkdir(parents=True, exist_ok=True)
            shutil.copy(path, clone / path.relative_to(original))
    assert CliRunner().invoke(main, ["store", "relocate", "--tracking-uri", uri_of(clone)]).exit_code == 0
    store = Store(uri_of(clone))
    for reader in store.search(None):
        listed = [a.path for a in reader.all_artifacts()]
        for path in listed:  # every link the UI shows opens
            assert store.client.download_artifacts(reader.run_id, path, str(tmp_path / "dl" / reader.run_id))
        if reader.role in ("", layout.ROLE_CELL):
            assert layout.RESULT in listed  # what the README promises of every run
            note = reader.tags[layout.NOTE_TAG]
            assert "**Files** in the committed store" in note and "Not committed, on the machine that ran it: " in note
            has_policies = any(a.path.startswith("policies/") for a in Store(uri_of(original)).run(reader.run_id).all_artifacts())
            assert "`episodes/*.npz` (1, " in note and note.startswith("**")  # the end note kept
            assert ("`policies/*.policy` (" in note) == has_policies  # learners without policy_state save none
        if reader.role == layout.ROLE_COMPARISON:
            assert "report/comparison.json" in listed and "report/curves_sweep-toy.png" in listed
    # describing again replaces the files section instead of adding another
    CliRunner().invoke(main, ["store", "describe", "--tracking-uri", uri_of(original)])
    assert all(r.tags.get(layout.NOTE_TAG, "").count("**Files**") == 1 for r in Store(uri_of(original)).search(None))


def test_the_gitignore_lets_through_exactly_the_committed_kinds_of_file(tmp_path):
    """The repository's .gitignore and harness.store.committed agree on which artifacts a committed store keeps."""
    shutil.copy(REPO / ".gitignore", tmp_path / ".gitignore")
    artifacts = "results/runs/mlruns/cartpole/0123/artifacts"
    samples = [f"{artifacts}/{name}" for name in (
        "result.json", "policies/policy_trial001.pkl", "checkpoints/ckpt_trial003.pkl", "episodes/interaction_episodes.npz",
        "trial001/model_trial001.pt", "trial001/prediction_trial001.png", "trial001/gp_hyperparameters_trial001.json",
        "test/test_summary.json", "test/test_final_distances.npy", "test/test_final_distance.png",
        "report/comparison_cartpole.md", "report/comparison_cartpole.csv", "report/curves_cartpole.png", "trial012/other_plot.png")]
    for sample in [*samples, "mlruns/1/0123/artifacts/result.json", "mlflow.db"]:
        (tmp_path / sample).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / sample).write_text("x")
    git = lambda *args: subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True, text=True).stdout  # noqa: E731
    git("init", "-q")
    git("add", "-A")
    added = set(git("diff", "--cached", "--name-only").split()) - {".gitignore"}
    assert added == {s for s in samples if committed(s)} and len(added) == 7
    assert not any("/trial" in path and path.endswith(".png") for path in added)  # per-trial plots stay out


def test_the_committed_store_keeps_within_its_budget():
    """What the repository commits of results/runs/mlruns: no file over MAX_FILE_BYTES, all under BUDGET_BYTES."""
    listed = subprocess.run(["git", "ls-files", "-z", "results/runs/mlruns"], cwd=REPO, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    sizes = {path: (REPO / path).stat().st_size for path in listed.stdout.split("\0") if path and (REPO / path).exists()}
    assert [p for p, size in sizes.items() if size > MAX_FILE_BYTES] == []
    assert sum(sizes.values()) <= BUDGET_BYTES


def test_store_checkpoints_lists_the_newest_checkpoint_of_each_run_stopped_before_its_limit(tmp_path, monkeypatch):
    """`harness store checkpoints`: the runs a clone could not resume without a committed checkpoint, each with
    its newest one (--paths: the local files, for `git add -f`); finished runs are not listed."""
    uri = uri_of(tmp_path)
    config = RunConfig("random", "cartpole", 0, max_trials=4, eval_episodes=1)
    run(config, tracker=MlflowTracker(uri))
    stopped = InterruptedMlflow(uri, 3)
    with pytest.raises(KeyboardInterrupt):
        run(RunConfig("random", "cartpole", 1, max_trials=4, eval_episodes=1), tracker=stopped)
    runs = {r.run_id: r for r in Store(uri).search(None)}
    killed = [r for r in runs.values() if r.status == "KILLED"]
    assert len(runs) == 2 and len(killed) == 1
    saved = sorted(a.path for a in killed[0].artifacts("checkpoints"))
    assert len(saved) >= 2  # not vacuous: several checkpoints stored before the interrupt, the newest is the one

    listed = CliRunner().invoke(main, ["store", "checkpoints", "--tracking-uri", uri])
    assert listed.exit_code == 0, listed.output
    lines = [line for line in listed.output.splitlines() if line.startswith(killed[0].run_id[:8])]
    assert len(lines) == 1 and saved[-1] in lines[0] and "KILLED" in lines[0]
    assert "1 runs stopped before their limit" in listed.output and "1 have a checkpoint" in listed.output
    finished = next(r for r in runs.values() if r.status == "FINISHED")
    assert finished.run_id[:8] not in listed.output

    monkeypatch.chdir(tmp_path)
    only = CliRunner().invoke(main, ["store", "checkpoints", "--paths", "--tracking-uri", uri])
    assert only.exit_code == 0, only.output
    files = only.output.split()
    assert len(files) == 1 and files[0].endswith(Path(saved[-1]).name) and (tmp_path / files[0]).is_file()


def test_store_policies_lists_each_runs_last_policy_which_is_all_a_clone_needs_to_test_the_run(tmp_path, monkeypatch):
    """`harness store policies`: every run that saved a policy, finished or stopped, with its last one (what
    `harness eval RUN` tests; --paths: the local files, for `git add -f`). A copy of the store without the
    policies refuses `harness eval` with a message that names the way out; with that one file copied over,
    the copy tests the run."""
    uri = uri_of(tmp_path)
    run(RunConfig("random", "cartpole", 0, max_trials=3, eval_episodes=1), tracker=MlflowTracker(uri))
    with pytest.raises(KeyboardInterrupt):
        run(RunConfig("random", "cartpole", 1, max_trials=4, eval_episodes=1), tracker=InterruptedMlflow(uri, 3))
    runs = {r.status: r for r in Store(uri).search(None)}
    assert set(runs) == {"FINISHED", "KILLED"}
    saved = {status: r.policies() for status, r in runs.items()}
    assert len(saved["FINISHED"]) == 3 and len(saved["KILLED"]) >= 2  # not vacuous: the last is one of several

    listed = CliRunner().invoke(main, ["store", "policies", "--tracking-uri", uri])
    assert listed.exit_code == 0, listed.output
    for status, r in runs.items():
        lines = [line for line in listed.output.splitlines() if line.startswith(r.run_id[:8])]
        assert len(lines) == 1 and status in lines[0] and saved[status][-1] in lines[0]
    assert "2 runs have a saved policy here, 2 small enough to commit" in listed.output

    monkeypatch.chdir(tmp_path)
    only = CliRunner().invoke(main, ["store", "policies", "--paths", "--tracking-uri", uri])
    assert only.exit_code == 0, only.output
    files = only.output.split()
    assert sorted(Path(f).name for f in files) == sorted(Path(p[-1]).name for p in saved.values())
    assert all((tmp_path / f).is_file() for f in files)

    clone = tmp_path / "clone"
    clone.mkdir()
    shutil.copy(tmp_path / "mlflow.db", clone / "mlflow.db")
    relocated = CliRunner().invoke(main, ["store", "relocate", "--tracking-uri", uri_of(clone)])  # eval logs to the run
    assert relocated.exit_code == 0, relocated.output
    for f in files:  # a clone of the repository: the committed kinds of file only, here the policies just listed
        (clone / f).parent.mkdir(parents=True, exist_ok=True)
    finished = runs["FINISHED"].run_id
    refused = CliRunner().invoke(main, ["eval", finished, "--episodes", "2", "--tracking-uri", uri_of(clone)])
    assert refused.exit_code != 0
    assert "has no saved policy here" in refused.output and "harness store policies --paths" in refused.output
    for f in files:
        shutil.copy(tmp_path / f, clone / f)
    tested = CliRunner().invoke(main, ["eval", finished, "--episodes", "2", "--tracking-uri", uri_of(clone)])
    assert tested.exit_code == 0, tested.output
    assert Path(saved["FINISHED"][-1]).name in tested.output
