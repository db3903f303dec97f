"""`benchmarks/ui_screenshots.py`: `mlflow ui` on a small store, in headless Chromium, shows the comparison."""

from __future__ import annotations

import shutil

import pytest
from click.testing import CliRunner
from PIL import Image

from harness.cli import main
from harness.sweep import SweepSpec, pools, run_sweep
from tests.harness import sweep_site

pytestmark = pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed (apt-get install -y chromium)")


def test_the_ui_shows_every_learner_of_the_comparison(tmp_path, monkeypatch):
    from benchmarks.ui_screenshots import main as screenshots

    sweep_site.activate(sweep_site.install(tmp_path / "plugins"), monkeypatch)
    monkeypatch.setattr(pools, "LocalPool", sweep_site.InlinePool)
    uri = f"sqlite:///{tmp_path}/store/mlflow.db"
    (tmp_path / "store").mkdir()
    result = run_sweep(SweepSpec(("sweep-steps", "random", "sweep-boom"), ("sweep-toy",), (2, 3, 4), max_trials=2, eval_episodes=1), uri)
    report = CliRunner().invoke(main, ["report", "--tracking-uri", uri, "--sweep", result.sweep_id, "--out", str(tmp_path / "report"),
                                       "--fig5-task", "sweep-toy"])
    assert report.exit_code == 0, report.output
    out = tmp_path / "ui"
    # fails if a page does not show its rows, metrics, table (the script checks the rendered page's text)
    screenshots(["--tracking-uri", uri, "--out", str(out)])
    shots = sorted(p.name for p in out.glob("*.png"))
    assert shots == [f"sweep-toy_{page}.png" for page in ("charts", "comparison", "rows", "runs", "table")]
    assert [Image.open(out / name).size for name in shots] == [(1700, 2400)] + [(1700, 1100)] * 4
    index = (out / "README.md").read_text()
    assert f"Command: `python benchmarks/ui_screenshots.py --tracking-uri {uri} --out {out}`" in index
