"""What `mlflow ui` shows of a store, in a real browser: per task, the comparison rows as a runs table and
as charts, the comparison run (its description: the table), the logged table, and every run of the task.

    python benchmarks/ui_screenshots.py --tracking-uri sqlite:///$PWD/results/runs/mlflow.db --out results/ui

Starts ``mlflow ui`` on the store (a free port on 127.0.0.1), drives headless Chromium (Debian's
``chromium``: ``apt-get install -y chromium``) to each page and saves a PNG per page, then writes
``<out>/README.md`` with the command, the pages and their addresses. The store needs the comparison
runs that ``harness report --sweep ...`` writes (``--publish``), and its artifact locations in its own
folder (``harness store relocate`` after a copy). Each page is loaded once with a fresh browser profile;
the browser waits ``--wait`` seconds of page time for the UI's requests (``--virtual-time-budget``).
"""

from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, write_report  # noqa: E402
from harness.store import Store, layout  # noqa: E402

CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run", "--hide-scrollbars")


@dataclass(frozen=True)
class Page:
    """One screenshot: ``name`` (the PNG's stem), what it shows, its address under the UI's root, and
    texts the rendered page must hold (else the UI did not show what it should, and the script fails)."""

    name: str
    shows: str
    path: str
    expect: tuple[str, ...] = ()
    #: the window's height in pixels (the charts render only where the window reaches)
    height: int = 1100


def pages(store: Store, tasks: list[str] | None = None) -> list[Page]:
    """The pages of every task with a comparison run (or of ``tasks``); an error naming the fix if there is none."""
    found = store.search(None, f"tags.`{layout.ROLE_TAG}` = '{layout.ROLE_COMPARISON}'")
    by_task = {r.tags.get(layout.TASK_TAG, ""): r for r in sorted(found, key=lambda r: r.start_time)}
    chosen = tasks or sorted(by_task)
    missing = [t for t in chosen if t not in by_task]
    if not chosen or missing:
        sys.exit(f"no comparison run for {', '.join(missing) or 'any task'} in {store.uri}; "
                 "write them with `harness report --tracking-uri URI --sweep ID ...` (or --publish) first")
    out = []
    for task in chosen:
        comparison = by_task[task]
        rows = store.search([comparison.experiment_id], f"tags.`{layout.ROLE_TAG}` = '{layout.ROLE_ROW}'")
        names = tuple(r.name for r in rows)
        runs = f"#/experiments/{comparison.experiment_id}/runs"
        where = urllib.parse.urlencode({"searchFilter": f"tags.`{layout.ROLE_TAG}` = '{layout.ROLE_ROW}'"}, quote_via=urllib.parse.quote)
        out += [
            Page(f"{task}_rows", f"{task}: the comparison rows as runs, sorted by solved fraction (their statistics are metric "
                 "columns: pick them under Columns, MLflow 3 shows none by default)",
                 f"{runs}?{where}&orderByKey=metrics.%60solved_fraction%60&orderByAsc=false", (*names, "solved_fraction")),
            Page(f"{task}_charts", f"{task}: the rows' statistics charted (a bar per row)", f"{runs}?{where}&compareRunsMode=CHART",
                 charted(rows), height=2400),
            Page(f"{task}_comparison", f"{task}: the run `{comparison.name}`, its description the comparison table",
                 f"#/experiments/{comparison.experiment_id}/runs/{comparison.run_id}", (comparison.name, "unsolved runs counted")),
            Page(f"{task}_table", f"{task}: the logged table `{layout.REPORT}/{layout.COMPARISON_TABLE}`",
                 f"#/experiments/{comparison.experiment_id}/runs/{comparison.run_id}/artifacts/{layout.REPORT}/{layout.COMPARISON_TABLE}",
                 ("median_time_to_success_s",)),
            Page(f"{task}_runs", f"{task}: every run of the task (sweep parents and cells, bench runs), by name", f"{runs}",
                 (layout.comparison_name(task),)),
        ]
    return out


def charted(rows: list) -> tuple[str, ...]:
    """The statistics a task's charts must show: the solved fraction and the median's lower bound where a
    row has finished runs (a row of stopped runs only has neither), else the run counts."""
    logged = {key for row in rows for key in row.metrics}
    return tuple(k for k in ("solved_fraction", "median_time_to_success_at_least_seconds") if k in logged) or ("stopped_runs",)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def mlflow_ui(tracking_uri: str, port: int, timeout: float = 120.0):
    """``mlflow ui`` on the store at ``http://127.0.0.1:<port>``, stopped afterwards (its output shown if it fails to start)."""
    log = tempfile.TemporaryFile("w+")
    server = subprocess.Popen([sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", tracking_uri, "--host", "127.0.0.1",
                               "--port", str(port), "--workers", "1"], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as response:
                    if response.status == 200:
                        break
            except OSError:
                pass
            if server.poll() is not None or time.monotonic() > deadline:
                log.seek(0)
                sys.exit(f"mlflow ui did not start (exit {server.poll()}); its output:\n{log.read()[-2000:]}")
            time.sleep(0.5)
        yield url
    finally:
        log.close()
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def _chromium(chromium: str, url: str, size: tuple[int, int], wait_ms: int, *action: str) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory(prefix="ui-shot-") as profile:
        return subprocess.run([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
                               f"--virtual-time-budget={wait_ms}", *action, url], capture_output=True, text=True, timeout=180)


def screenshot(chromium: str, url: str, target: Path, size: tuple[int, int], wait_ms: int) -> None:
    """One page as a PNG, in a fresh profile; an error with the browser's output if no file came out."""
    done = _chromium(chromium, url, size, wait_ms, f"--screenshot={target}")
    if not target.exists() or target.stat().st_size == 0:
        sys.exit(f"chromium wrote no screenshot of {url} (exit {done.returncode}): {done.stderr[-1500:]}")


def rendered(chromium: str, url: str, size: tuple[int, int], wait_ms: int) -> str:
    """The page's HTML once the UI has rendered it (what the screenshot shows, as text)."""
    return _chromium(chromium, url, size, wait_ms, "--dump-dom").stdout


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tracking-uri", required=True, help="the store, e.g. sqlite:///$PWD/results/runs/mlflow.db")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "ui", help="folder for the PNGs and README.md")
    parser.add_argument("--task", action="append", dest="tasks", help="only this task (repeatable; default: every task with a comparison)")
    parser.add_argument("--chromium", default=shutil.which("chromium") or "chromium", help="the browser (Debian: apt-get install -y chromium)")
    parser.add_argument("--width", type=int, default=1700)
    parser.add_argument("--wait", type=float, default=60.0, help="seconds of page time for the UI to load its data")
    args = parser.parse_args(argv)
    if shutil.which(args.chromium) is None:
        sys.exit(f"no browser {args.chromium!r}; install Debian's with `apt-get install -y chromium` or pass --chromium PATH")

    store = Store(args.tracking_uri)
    shots = pages(store, args.tasks)
    args.out.mkdir(parents=True, exist_ok=True)
    lines = ["# `mlflow ui` on the store, in headless Chromium", "", f"Command: `{command_line(__file__, argv)}`  ",
             f"Store: `{store.uri}`; `mlflow ui --backend-store-uri {store.uri}`, then the addresses below.", "",
             "| page | what it shows | address |", "|---|---|---|"]
    with mlflow_ui(store.uri, free_port()) as url:
        wait = int(args.wait * 1000)
        for page in shots:
            target, size = args.out / f"{page.name}.png", (args.width, page.height)
            screenshot(args.chromium, f"{url}/{page.path}", target, size, wait)
            html = rendered(args.chromium, f"{url}/{page.path}", size, wait)
            missing = [text for text in page.expect if text not in html]
            if missing:
                sys.exit(f"the page {page.name} ({url}/{page.path}) does not show {', '.join(map(repr, missing))}; see {target}")
            lines.append(f"| [`{target.name}`]({target.name}) | {page.shows} | `/{page.path}` |")
    write_report(lines, args.out / "README.md")


if __name__ == "__main__":
    main()
