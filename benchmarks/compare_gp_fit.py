"""Side-by-side timing of one PILCO dynamics-model fit (GP hyperparameters + FITC pseudo-inputs) for
two checkouts of this repo, on the data of a real run's late trial.

Usage::

    # once: the GP training data and warm start of a stored checkpoint, as .npz (no pickle needed later)
    .venv/bin/python benchmarks/compare_gp_fit.py --extract CHECKPOINT.pkl --out-data benchmarks/data/NAME.npz
    # the comparison
    .venv/bin/python benchmarks/compare_gp_fit.py --before /path/to/old/checkout --data benchmarks/data/NAME.npz [--threads 1 2]

The data file holds the run's transitions up to that trial (inputs ``x (n, d)``, targets ``y (n, E)``),
the GP hyperparameters and pseudo-inputs the run carried into the next fit (its warm start) and the
learner's GP settings. Every fit runs in a fresh subprocess (``PYTHONPATH`` = that checkout, so each
side imports its own ``plugins.pilco.gp``) with the given number of torch threads; sides alternate
``before, after, before, ...``. Reported per thread count: median wall and CPU seconds of the fit and
of its two stages, the evaluations, and the fitted models' penalised NLL and FITC NLL on the same data
(two implementations that round differently part after some L-BFGS iterations: equal NLLs to a few
digits mean equally good fits, not the same path).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # for benchmarks.report_file; the measured code is imported by the child processes

from benchmarks.report_file import command_line, load_average, machine_line, write_report  # noqa: E402

CHILD = r"""
import json, sys, time
root, data_file, threads = sys.argv[1], sys.argv[2], int(sys.argv[3])
sys.path.insert(0, root)
import numpy as np, torch
torch.set_num_threads(threads)
import plugins.pilco.gp as gp
data = np.load(data_file)
settings = json.loads(str(data["settings"]))
stage = {}
def timed(name, f):
    def g(*a, **k):
        t0, c0 = time.perf_counter(), time.process_time()
        r = f(*a, **k)
        stage[name + "_wall"] = stage.get(name + "_wall", 0.0) + time.perf_counter() - t0
        stage[name + "_cpu"] = stage.get(name + "_cpu", 0.0) + time.process_time() - c0
        return r
    return g
gp.optimise_hyperparameters = timed("hyper", gp.optimise_hyperparameters)
gp.optimise_pseudo_inputs = timed("pseudo", gp.optimise_pseudo_inputs)
warm = gp.GPHyperparameters(*(torch.tensor(data[k]) for k in ("log_ell", "log_alpha", "log_sigma", "pseudo_inputs")))
model = gp.GPModel(sparse_threshold=settings["sparse_threshold"], num_pseudo=settings["num_pseudo"],
                   max_evals_full=settings["gp_max_evals"], max_evals_fitc=settings["gp_fitc_evals"],
                   hyper_subset=settings["gp_hyper_subset"], refresh_pseudo=settings["gp_refresh_pseudo"])
t0, c0 = time.perf_counter(), time.process_time()
report = model.fit(data["x"], data["y"], warm_start=warm, seed=settings["seed"])
out = dict(wall=time.perf_counter() - t0, cpu=time.process_time() - c0, evaluations=report.evaluations, nll=report.nll,
           fitc_nll=report.fitc_nll, n=int(data["x"].shape[0]), **stage)
print(json.dumps(out))
"""


def extract(checkpoint: str, out: str) -> None:
    """Write the GP data of a PILCO checkpoint (transitions, warm start, GP settings) to ``out`` (.npz)."""
    import numpy as np

    from harness.checkpoint import load_checkpoint
    from harness.interaction import Episode
    from harness.runner import config_from_identity, new_learner, prepare
    from plugins.pilco.policy import transitions

    ck = load_checkpoint(Path(checkpoint))
    ident = ck.identity
    learner = new_learner(prepare(config_from_identity(ident)))
    x, y = transitions([Episode(**e) for e in ck.interaction["episodes"]], learner.layout)  # a checkpoint holds plain data
    h = {k: np.asarray(v) for k, v in ck.learner["hyperparameters"].items()}
    o = learner.options
    settings = {"sparse_threshold": learner.preset.sparse_threshold, "num_pseudo": learner.num_pseudo,
                "gp_max_evals": o["gp_max_evals"], "gp_fitc_evals": o["gp_fitc_evals"], "gp_hyper_subset": o["gp_hyper_subset"],
                "gp_refresh_pseudo": o["gp_refresh_pseudo"], "seed": ident["seed"] + ck.trial + 1,
                "source": f"{Path(checkpoint).name} of a {ident['learner']} run on {ident['task']} (seed {ident['seed']}), "
                          f"data before trial {ck.trial + 1}"}
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, x=x, y=y, log_ell=h["log_ell"], log_alpha=h["log_alpha"], log_sigma=h["log_sigma"],
                        pseudo_inputs=h["pseudo_inputs"], settings=json.dumps(settings))
    print(f"wrote {out}: n = {x.shape[0]}, d = {x.shape[1]}, E = {y.shape[1]}; {settings['source']}")


def run_child(root: str, data: str, threads: int) -> dict:
    env = dict(os.environ, PYTHONPATH=root, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    proc = subprocess.run([sys.executable, "-c", CHILD, root, data, str(threads)], capture_output=True, text=True, env=env,
                          cwd=root, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed for {root}:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--extract", metavar="CHECKPOINT", help="write the GP data of this checkpoint to --out-data and stop")
    parser.add_argument("--out-data", help="with --extract: the .npz to write")
    parser.add_argument("--before", help="checkout with the old implementation")
    parser.add_argument("--after", default=str(ROOT), help="checkout with the new implementation")
    parser.add_argument("--data", help="a file written by --extract")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", default=str(ROOT / "results" / "benchmarks" / "gp_fit_before_after.md"))
    args = parser.parse_args()
    if args.extract:
        if not args.out_data:
            parser.error("--extract needs --out-data")
        extract(args.extract, args.out_data)
        return
    if not (args.before and args.data):
        parser.error("give --before and --data (or --extract)")
    import numpy as np

    settings = json.loads(str(np.load(args.data)["settings"]))
    sides = {"before": str(Path(args.before).resolve()), "after": str(Path(args.after).resolve())}
    load_before = load_average()
    results = {t: {side: [] for side in sides} for t in args.threads}
    for _ in range(args.rounds):
        for t in args.threads:
            for side, root in sides.items():
                r = run_child(root, args.data, t)
                results[t][side].append(r)
                print(f"{t} thread(s) {side:6s} wall {r['wall']:6.1f} s cpu {r['cpu']:6.1f} s (hyper {r['hyper_wall']:.1f} s, "
                      f"pseudo {r.get('pseudo_wall', 0):.1f} s)", flush=True)
    n = results[args.threads[0]]["before"][0]["n"]
    lines = [
        "# PILCO dynamics-model fit: before / after, side by side",
        "",
        f"Command: `{command_line(__file__)}`  ",
        f"{machine_line(load_before)} Prefer CPU time and ratios.  ",
        f"Data: `{Path(args.data).name}` ({settings['source']}; n = {n} transitions); GP settings {json.dumps({k: v for k, v in settings.items() if k != 'source'})}.  ",
        f"before = `{sides['before']}`, after = `{sides['after']}`; {args.rounds} rounds per side and thread count, alternating "
        "subprocesses; medians.",
        "",
        "| threads | wall s before / after | CPU s before / after | wall speed-up | hyperparameters wall s | pseudo-inputs wall s "
        "| evaluations | penalised NLL | FITC NLL |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for t, per_side in results.items():
        med = {s: {k: statistics.median(r.get(k, 0.0) for r in runs) for k in ("wall", "cpu", "hyper_wall", "pseudo_wall")}
               for s, runs in per_side.items()}
        b, a = per_side["before"][0], per_side["after"][0]
        lines.append(
            f"| {t} | {med['before']['wall']:.1f} / {med['after']['wall']:.1f} | {med['before']['cpu']:.1f} / {med['after']['cpu']:.1f} "
            f"| {med['before']['wall'] / med['after']['wall']:.2f} | {med['before']['hyper_wall']:.1f} / {med['after']['hyper_wall']:.1f} "
            f"| {med['before']['pseudo_wall']:.1f} / {med['after']['pseudo_wall']:.1f} | {b['evaluations']} / {a['evaluations']} "
            f"| {b['nll']:.3f} / {a['nll']:.3f} | {b['fitc_nll']:.3f} / {a['fitc_nll']:.3f} |"
        )
    write_report(lines, args.out)


if __name__ == "__main__":
    main()
