"""Concurrent writers on a tracking store: K processes, each logging N metrics with the MLflow client
(through :class:`harness.store.Store`: one ``log_batch`` request per write of one metric) to (a) the default
SQLite store and (b) a served store (``harness store serve``: MLflow on PostgreSQL). Reports writes/s
over all writers and the p50/p99 latency of one write.

    python benchmarks/store_load.py --writers 1,2,4,8 --writes 200 --out results/benchmarks/store_load.md

Without ``--server-uri`` a server is started for the run in a temporary folder (PostgreSQL's binaries on
PATH, ports ``--port`` and ``--port``+1) and stopped at the end.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def writer(uri: str, experiment_id: str, writes: int, barrier, results) -> None:
    """One process: a run of its own, then ``writes`` timed single-metric writes once every writer is ready."""
    from harness.store import Store

    store = Store(uri)
    run_id = store.create_run(experiment_id, f"writer-{os.getpid()}", {})
    barrier.wait()
    latencies = []
    for step in range(writes):
        start = time.perf_counter()
        store.log_metrics(run_id, {"load": float(step)}, step=step)
        latencies.append(time.perf_counter() - start)
    store.set_status(run_id, "FINISHED")
    results.put((time.perf_counter(), latencies))


def measure(uri: str, writers: int, writes: int) -> dict[str, float]:
    """``writers`` processes at once on ``uri``: writes/s from the common start to the last writer's end, latencies in ms."""
    from harness.store import Store

    # opened here first: a fresh SQLite store is created before the writers open it (no migration race)
    experiment_id = Store(uri).ensure_experiment(f"store-load-{writers}-{time.time_ns()}")
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(writers + 1), ctx.Queue()
    processes = [ctx.Process(target=writer, args=(uri, experiment_id, writes, barrier, results)) for _ in range(writers)]
    for p in processes:
        p.start()
    barrier.wait()
    start = time.perf_counter()
    done = [results.get(timeout=1800) for _ in processes]
    for p in processes:
        p.join()
    elapsed = max(end for end, _ in done) - start
    latencies = sorted(x * 1000 for _, lat in done for x in lat)
    return {"writes_per_s": len(latencies) / elapsed, "p50_ms": statistics.median(latencies),
            "p99_ms": latencies[min(len(latencies) - 1, int(0.99 * len(latencies)))], "seconds": elapsed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--writers", default="1,2,4,8", help="Numbers of concurrent writer processes.")
    parser.add_argument("--writes", type=int, default=200, help="Metric writes per writer.")
    parser.add_argument("--server-uri", default=None, help="A running served store (default: start one for the run).")
    parser.add_argument("--port", type=int, default=15100, help="MLflow port of the server started for the run (PostgreSQL: +1).")
    parser.add_argument("--out", type=Path, default=None, help="Markdown file for the table (default: print only).")
    args = parser.parse_args()
    counts = [int(k) for k in args.writers.split(",")]

    from benchmarks.report_file import command_line, load_average, machine_line, write_report
    from harness.store.server import StoreServer

    folder = Path(tempfile.mkdtemp(prefix="store-load-"))
    folder.chmod(0o755)  # as root, PostgreSQL runs as the user postgres
    server = None if args.server_uri else StoreServer(folder / "served", port=args.port, db_port=args.port + 1).start()
    stores = {"SQLite (default, local file)": f"sqlite:///{folder / 'mlflow.db'}",
              "server (MLflow on PostgreSQL)": args.server_uri or server.uri}
    rows, load_at_start = [], load_average()
    try:
        for name, uri in stores.items():
            for k in counts:
                result = measure(uri, k, args.writes)
                rows.append((name, k, result))
                print(f"{name:32s} K={k}: {result['writes_per_s']:7.1f} writes/s, p50 {result['p50_ms']:6.1f} ms, "
                      f"p99 {result['p99_ms']:7.1f} ms ({result['seconds']:.1f} s)", flush=True)
    finally:
        if server is not None:
            server.stop()
        shutil.rmtree(folder, ignore_errors=True)

    lines = [f"    {command_line(__file__)}", "", machine_line(load_at_start), "",
             f"{args.writes} writes of one metric (`Store.log_metrics`: one MLflow `log_batch` request) per writer, each writer a process with its own run; writes/s from the "
             "common start to the last writer's end.", "",
             "| store | writers K | writes/s (all writers) | p50 latency per write (ms) | p99 latency per write (ms) |",
             "|---|---|---|---|---|"]
    lines += [f"| {name} | {k} | {r['writes_per_s']:.1f} | {r['p50_ms']:.1f} | {r['p99_ms']:.1f} |" for name, k, r in rows]
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
