"""The paper's tables: Table 1 measured (state dimension, trials, experience, policy parameters) beside
ICML 2011's values, and the sourced literature rows of Fig. 5."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from harness.errors import HarnessError
from harness.report.baselines import MODEL_FREE, Outcome, best_outcome, fmt_outcome, outcome, pilco_vs_model_free
from harness.report.formatting import fmt_range, value_range, fmt_decimal
from harness.report.records import RunRecord

#: ICML 2011 Table 1, per harness task name: (paper task name, state space, # trials, experience, parameters)
PAPER_TABLE1: dict[str, tuple[str, str, str, str, str]] = {
    "cartpole": ("cart-pole", "R^4", "<= 10", "~ 20 s", "R^305"),
    "double-pendulum": ("cart-double-pole", "R^6", "20-30", "~ 60-90 s", "R^1816"),
    "unicycle": ("unicycle", "R^12", "~ 20", "~ 20-30 s", "R^28"),
}


def table1_rows(runs_by_task: dict[str, dict[str, list[RunRecord]]], learner: str,
                incomplete: Sequence[RunRecord] = ()) -> list[dict[str, Any]]:
    """Table 1 measured for ``learner`` on the paper's tasks that were run: a row per task and row
    label (several where the learner ran on a task in differently configured sweeps)."""
    rows = []
    for task in PAPER_TABLE1:
        counted = {label: runs for label, runs in runs_by_task.get(task, {}).items() if runs and runs[0].learner == learner}
        labels = dict.fromkeys([*counted, *(r.label for r in incomplete if r.task == task and r.learner == learner)])
        for label in labels:
            runs = counted.get(label, [])
            stopped = [r for r in incomplete if r.task == task and r.label == label]
            rows.append({**_table1_row(task, label, runs, stopped), **_beside_model_free(runs_by_task.get(task, {}), label, runs)})
    return rows


def _beside_model_free(by_label: dict[str, list[RunRecord]], label: str, runs: Sequence[RunRecord]) -> dict[str, Any]:
    """The row's own :class:`~harness.report.baselines.Outcome` (``None`` without counted runs), each
    model-free learner's best row on the task (``None``: not run) and the ratio of the medians."""
    own = outcome(label, runs) if runs else None
    baselines = {learner: best_outcome(by_label, learner) for learner in MODEL_FREE}
    return {"outcome": own, "model_free": baselines, "vs_model_free": pilco_vs_model_free(own, list(baselines.values()))}


def _table1_row(task: str, label: str, runs: Sequence[RunRecord], stopped: Sequence[RunRecord]) -> dict[str, Any]:
    paper_task, p_state, p_trials, p_exp, p_params = PAPER_TABLE1[task]
    solved = [r for r in runs if r.solved]
    dims = sorted({r.state_dim for r in [*runs, *stopped] if r.state_dim is not None})
    return {
        "task": task, "learner": label, "paper_task": paper_task, "runs": len(runs), "solved": len(solved),
        "stopped": len(stopped),
        "stopped_episodes": value_range([r.episodes for r in stopped if r.episodes is not None]),
        "stopped_interaction_s": value_range([r.interaction_seconds for r in stopped]),
        "state_dim": "/".join(str(d) for d in dims) or "?",
        "trials": value_range([r.trials_to_success for r in solved if r.trials_to_success is not None]),
        "experience_s": value_range([r.time_to_success for r in solved if r.time_to_success is not None]),
        "policy_parameters": value_range([r.policy_parameters for r in [*runs, *stopped] if r.policy_parameters is not None]),
        "paper": {"state": p_state, "trials": p_trials, "experience": p_exp, "parameters": p_params},
    }


def table1_markdown(rows: Sequence[dict[str, Any]], learner: str) -> str:
    lines = [
        f"# Table 1 (Deisenroth & Rasmussen, ICML 2011): measured for `{learner}`, median [min–max] over seeds",
        "",
        "Trials and experience are over the **solved** runs only; the `solved` column says how many of "
        "the runs that is (unsolved runs have no time to success; see the comparison tables for "
        "statistics that count them). Trials = interaction episodes up to the first solved evaluation, "
        "the initial random ones included. Experience = interaction time to success (system seconds). "
        "Parameters = the policy's parameter count logged by the learner (`policy_parameters`). "
        "Runs stopped before their limit (KILLED or still running, e.g. at the end of a session) are not counted; "
        "they are listed under the table with the trials and interaction they reached, unsolved so far.",
        "",
        "PILCO beside the model-free baselines: solved/n and the median interaction time to success in s over "
        "**all** counted runs, unsolved = ∞ (where the median is not reached, ≥ the least interaction an unsolved "
        "run consumed); SAC and PPO: the learner's best row on the task, \"not run\" without runs. "
        "PILCO vs best model-free: how many times less interaction PILCO needed than the better of SAC and PPO "
        "(ratio of the medians).",
        "",
        "| task | solved | state space (ours / paper) | # trials (ours / paper) | experience in s (ours / paper) | policy parameters (ours / paper) "
        "| PILCO (unsolved = ∞) | " + " | ".join(learner.upper() for learner in MODEL_FREE) + " | PILCO vs best model-free |",
        "|---|---|---|---|---|---|---|" + "---|" * len(MODEL_FREE) + "---|",
    ]
    for r in rows:
        p = r["paper"]
        params = r["policy_parameters"]
        variant = f", `{r['learner']}`" if r["learner"] != learner else ""
        lines.append(
            f"| {r['task']} ({r['paper_task']}){variant} | {r['solved']}/{r['runs']} | R^{r['state_dim']} / {p['state']} "
            f"| {fmt_range(*r['trials'])} / {p['trials']} | {fmt_range(*r['experience_s'], fmt=fmt_decimal)} / {p['experience']} "
            f"| {'R^' + fmt_range(*params) if not math.isnan(params[0]) else '–'} / {p['parameters']} | {_model_free_cells(r)} |"
        )
    if not rows:
        lines.append(f"| (no runs of `{learner}` on cartpole, double-pendulum or unicycle in the selected sweeps) | | | | | |" + " |" * (len(MODEL_FREE) + 2))
    notes = [r for r in rows if r["stopped"]]
    if notes:
        lines += ["", "Stopped before their limit, not solved so far (lower bounds, not results):", ""]
        for r in notes:
            variant = f" (`{r['learner']}`)" if r["learner"] != learner else ""
            lines.append(f"- {r['task']}{variant}: {r['stopped']} run(s) at {fmt_range(*r['stopped_episodes'])} trials, "
                         f"{fmt_range(*r['stopped_interaction_s'], fmt=fmt_decimal)} s of interaction")
    return "\n".join(lines) + "\n"


def _model_free_cells(row: dict[str, Any]) -> str:
    """The row's cells beside the model-free learners: its own outcome, each learner's, the ratio."""
    own = fmt_outcome(row["outcome"]) if row["outcome"] is not None else "no counted runs"
    return " | ".join([own, *(fmt_outcome(row["model_free"][learner]) for learner in MODEL_FREE), row["vs_model_free"]])


#: the columns of an outcome in ``table1.csv``, each after the learner's name
OUTCOME_KEYS = ("runs", "solved", "median_s", "unsolved_min_s")


def _flat_outcome(prefix: str, o: Outcome | None) -> dict[str, Any]:
    """``{prefix}_runs``, ``_solved``, ``_median_s``, ``_unsolved_min_s`` (empty where not run)."""
    values = (o.runs, o.solved, o.median_s, o.unsolved_min_s) if o is not None else ("",) * 4
    return {f"{prefix}_{key}": value for key, value in zip(OUTCOME_KEYS, values)}


def flat_table1(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for r in rows:
        flat = {"task": r["task"], "learner": r["learner"], "paper_task": r["paper_task"], "runs": r["runs"], "solved": r["solved"],
                "stopped": r["stopped"], "state_dim": r["state_dim"]}
        for key in ("trials", "experience_s", "policy_parameters", "stopped_episodes", "stopped_interaction_s"):
            flat[f"{key}_median"], flat[f"{key}_min"], flat[f"{key}_max"] = r[key]
        flat.update({f"paper_{k}": v for k, v in r["paper"].items()})
        flat["all_median_s"] = r["outcome"].median_s if r["outcome"] is not None else ""
        for learner in MODEL_FREE:
            flat.update(_flat_outcome(learner, r["model_free"][learner]))
        flat["pilco_vs_best_model_free"] = r["vs_model_free"]
        out.append(flat)
    return out


TABLE1_FIELDS = ["task", "learner", "paper_task", "runs", "solved", "stopped", "state_dim"] + [
    f"{key}_{part}" for key in ("trials", "experience_s", "policy_parameters", "stopped_episodes", "stopped_interaction_s")
    for part in ("median", "min", "max")
] + ["paper_state", "paper_trials", "paper_experience", "paper_parameters", "all_median_s"] + [
    f"{learner}_{key}" for learner in MODEL_FREE for key in OUTCOME_KEYS
] + ["pilco_vs_best_model_free"]



def read_literature(path: Path | None) -> list[dict[str, str]]:
    """Rows of ``literature_fig5.csv`` (``#`` lines are comments); a row without a source is an error."""
    if path is None or not Path(path).exists():
        return []
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(line for line in fh if line.strip() and not line.lstrip().startswith("#")))
    for row in rows:
        if not (row.get("source") or "").strip():
            raise HarnessError(f"{path}: the row {row.get('method')!r} has no source; every literature value needs a citable source")
        float(row["interaction_seconds"])
    return rows
