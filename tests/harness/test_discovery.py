"""Entry-point discovery with a real third-party package installed by the test."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from harness.discovery import LEARNER_GROUP, TASK_GROUP, list_plugins, load_learner, load_task
from harness.errors import PluginNotFoundError

PLUGIN = '''
import numpy as np
from harness.learner import Learner
from harness.options import Option


class ZeroLearner(Learner):
    """Always applies zero control."""

    name = "zero"
    description = "third-party demo: zero control"
    options = (Option("level", float, 0.0, "constant control"),)

    def learn(self, interaction):
        level = self.options["level"]
        policy = lambda obs: np.full(self.spec.action_dim, level)
        while True:
            interaction.rollout(policy)
            yield policy


class NeedsExtra(ZeroLearner):
    name = "needs-extra"
    description = "needs a module that is not installed"
    extra = "fancy"
    requires = ("not_installed_module_xyz",)
'''


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """pip-installs a throwaway distribution with one good and two broken plugins into a folder."""
    root = tmp_path_factory.mktemp("thirdparty")
    src = root / "src"
    src.mkdir()
    (src / "demo_plugin.py").write_text(PLUGIN)
    (src / "demo_broken.py").write_text("import this_module_does_not_exist_anywhere\n")
    (src / "pyproject.toml").write_text(
        textwrap.dedent(
            """
            [build-system]
            requires = ["setuptools"]
            build-backend = "setuptools.build_meta"
            [project]
            name = "harness-demo-plugins"
            version = "1.2.3"
            [tool.setuptools]
            py-modules = ["demo_plugin", "demo_broken"]
            [project.entry-points."harness.learners"]
            zero = "demo_plugin:ZeroLearner"
            broken = "demo_broken:Whatever"
            notaclass = "demo_plugin:np"
            needs-extra = "demo_plugin:NeedsExtra"
            """
        )
    )
    target = root / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--target", str(target), str(src)],
        check=True, capture_output=True, timeout=300,
    )
    return target


def harness(site: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(site) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "harness", *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def test_third_party_learner_is_listed_and_runs(site, tmp_path):
    listing = harness(site, "list", cwd=tmp_path)
    assert listing.returncode == 0, listing.stderr
    assert "zero" in listing.stdout and "third-party demo: zero control" in listing.stdout
    assert "random" in listing.stdout and "cartpole" in listing.stdout  # ours still there
    bench = harness(site, "bench", "--learner", "zero", "--task", "cartpole", "--max-trials", "2", "--eval-episodes", "2",
                    "--set", "level=1.5", "--no-tracking", "--quiet", cwd=tmp_path)
    assert bench.returncode == 0, bench.stderr
    assert "zero on cartpole (seed 0): not solved (max trials) after 8.0 s" in bench.stdout


def test_broken_plugins_are_listed_with_their_error_and_break_nothing(site, tmp_path):
    listing = harness(site, "list", cwd=tmp_path)
    assert listing.returncode == 0
    lines = {line.split()[0]: line for line in listing.stdout.splitlines() if line.startswith("  ")}
    assert "[BROKEN]" in lines["broken"] and "this_module_does_not_exist_anywhere" in lines["broken"]
    assert "harness-demo-plugins 1.2.3" in lines["broken"]
    assert "[BROKEN]" in lines["notaclass"] and "not a subclass" in lines["notaclass"]
    bench = harness(site, "bench", "--learner", "broken", "--task", "cartpole", "--no-tracking", cwd=tmp_path)
    assert bench.returncode == 2 and "learner plugin 'broken' from harness-demo-plugins 1.2.3 is broken" in bench.stderr
    assert "Traceback" not in bench.stderr


def test_plugin_with_missing_extra_is_unavailable_with_install_hint(site, tmp_path):
    listing = harness(site, "list", cwd=tmp_path)
    line = next(l for l in listing.stdout.splitlines() if l.strip().startswith("needs-extra"))
    assert "[UNAVAILABLE]" in line and "pip install 'harness-demo-plugins[fancy]'" in line
    bench = harness(site, "bench", "--learner", "needs-extra", "--task", "cartpole", "--no-tracking", cwd=tmp_path)
    assert bench.returncode == 2 and "not_installed_module_xyz" in bench.stderr and "pip install" in bench.stderr


def test_own_plugins_are_registered_through_entry_points():
    names = {p.name: p for p in list_plugins(LEARNER_GROUP)}
    assert names["random"].status == "ok" and names["random"].value == "plugins.random_learner:RandomLearner"
    assert {p.name for p in list_plugins(TASK_GROUP)} >= {"cartpole"}
    assert load_task("cartpole").name == "cartpole" and load_learner("random").name == "random"
    with pytest.raises(PluginNotFoundError, match="unknown task 'unicorn'"):
        load_task("unicorn")
