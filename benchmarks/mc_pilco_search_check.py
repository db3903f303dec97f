"""How far does mc-pilco's policy search get? One stored trial's search redone under other settings.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mc_pilco_search_check.py --run RUN_ID --trial K
        --variants "" "max_steps=3000,min_improvement=0" "particles=1600" [--episodes 50] [--seed 777]
        [--tracking-uri URI] [--out FILE]

Rebuilds the state in which a stored ``mc-pilco`` run searched at trial ``K``: the data of its
trial-``K`` checkpoint (every episode recorded before that hand-over), the GP fitted as the learner
fitted it (warm-started from the trial ``K-1`` checkpoint's hyperparameters, the same seed), and the
controller that search started from (trial ``K-1``'s; the initial one for ``K = 1``). Then each
variant (learner options over the run's own, ``key=value`` pairs separated by commas; ``""``: the
run's options) searches from that start with the run's random numbers. The empty variant repeats the
run's own search: its J after the search is checked against the stored ``J_after`` of trial ``K``.

Three keys of a variant are not learner options but its start: ``start=fresh`` searches from a fresh
initial controller instead of trial ``K-1``'s (the same GP, data and random numbers), drawn as the run
drew its first one but with generator seed ``learner seed + start_seed`` (``start_seed``, default 0: the
run's own initial controller); ``start=RUN_ID,start_trial=J`` from the policy another stored run
(``pilco``, ``pilco-mean`` or ``mc-pilco`` on the same task) handed over at its trial ``J``, its
controller as it is (its squashing included). They answer whether a restart of the search gets out of
where the run's search from its last policy settled, and how the run's model rates a policy that solves
the task (``max_steps=1``: its J on the search's particles, nearly unchanged).

Each resulting policy is scored where it counts, on ``--episodes`` episodes of the real task (the same
initial states for every variant): mean task cost and success rate (Wilson 95 % interval).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report_file import command_line, write_report  # noqa: E402
from benchmarks.swingup_failure_modes import add_test_arguments  # noqa: E402
from harness.statistics import wilson_interval  # noqa: E402
from harness.errors import CheckpointError, OptionError, exit_on_error  # noqa: E402
from harness.evaluation import Evaluator  # noqa: E402
from harness.runner import RunConfig, prepare  # noqa: E402
from harness.seeding import derive_seeds  # noqa: E402
from harness.store import Store  # noqa: E402


START_KEYS = ("start", "start_seed", "start_trial")


@dataclasses.dataclass(frozen=True)
class Start:
    """Where a variant's search starts: trial ``K-1``'s controller (``kind="stored"``), a fresh initial one
    drawn with the learner's seed + ``offset`` (``"fresh"``), or the policy run ``run_id`` handed over at
    ``trial`` (``"run"``)."""

    kind: str = "stored"
    offset: int = 0
    run_id: str | None = None
    trial: int | None = None


def split_start(overrides: dict[str, str]) -> tuple[dict[str, str], Start]:
    """A variant's learner options and its :class:`Start` (keys ``start``, ``start_seed``, ``start_trial``)."""
    options = {k: v for k, v in overrides.items() if k not in START_KEYS}
    start = overrides.get("start", "stored")

    def integer(key: str) -> int:
        try:
            return int(overrides[key])
        except ValueError:
            raise OptionError(f"variant {key}={overrides[key]!r}: {key} is an integer") from None

    if start != "fresh" and "start_seed" in overrides:
        raise OptionError("variant start_seed without start=fresh: start_seed draws a fresh controller; add start=fresh")
    if start in ("stored", "fresh") and "start_trial" in overrides:
        raise OptionError("variant start_trial without a run: write start=RUN_ID,start_trial=J for another run's policy")
    if start == "stored":
        return options, Start()
    if start == "fresh":
        return options, Start("fresh", offset=integer("start_seed") if "start_seed" in overrides else 0)
    if "start_trial" not in overrides:
        raise OptionError(f"variant start={start}: a run's policy needs its trial; add start_trial=J (or start=stored, "
                          "start=fresh)")
    return options, Start("run", run_id=start, trial=integer("start_trial"))


def start_controller(learner, start: Start, controller_state, tracking_uri: str | None):
    """The controller a variant's search starts from (see :class:`Start`), on the CPU."""
    if start.kind == "run":
        from plugins.pilco.saved_run import SavedPilcoRun

        with SavedPilcoRun(start.run_id, tracking_uri) as other:
            if other.task.spec.name != learner.spec.name:
                raise OptionError(f"variant start={start.run_id}: that run is on {other.task.spec.name}, this one on "
                                  f"{learner.spec.name}")
            return copy.deepcopy(other.policy(start.trial).controller)
    controller = learner.new_controller(torch.Generator().manual_seed(learner.seed + start.offset))
    if controller_state is not None and start.kind == "stored":
        controller.load_state_dict(controller_state)
    return controller


def parse_variant(text: str) -> dict[str, str]:
    """``"max_steps=3000,particles=1600"`` -> ``{"max_steps": "3000", "particles": "1600"}`` (``""`` -> ``{}``)."""
    pairs = [p.strip() for p in text.split(",") if p.strip()]
    bad = [p for p in pairs if "=" not in p]
    if bad:
        raise OptionError(f"variant {text!r}: {bad[0]!r} is not key=value; write e.g. \"max_steps=3000,particles=1600\"")
    return dict(p.split("=", 1) for p in pairs)


def stored_start(run_id: str, trial: int, tracking_uri: str | None):
    """``(run configuration, data episodes, warm-start hyperparameters or None, start controller state or
    None, stored J_after of the trial, the trial's planning horizon in steps or None where not logged)``
    of a stored ``mc-pilco`` run at trial ``trial``; the configuration is the checkpoint's own
    (:func:`~harness.runner.config_from_identity`)."""
    from harness.checkpoint import checkpoint_name, load_checkpoint
    from harness.runner import config_from_identity
    from harness.store import layout

    reader = Store(tracking_uri).run(run_id)
    learner = reader.params.get("learner")
    if learner != "mc-pilco":
        raise CheckpointError(f"run {run_id} is a {learner!r} run; this needs an mc-pilco run")

    def checkpoint(k: int):
        return load_checkpoint(reader.file(f"{layout.CHECKPOINTS}/{checkpoint_name(k)}"))

    after = checkpoint(trial)
    before = checkpoint(trial - 1) if trial > 1 else None
    stored = reader.history("J_after").get(trial)
    horizon = reader.history("planning_horizon").get(trial)
    reader.close()
    return (config_from_identity(after.identity), after.interaction["episodes"],
            before.learner["hyperparameters"] if before else None, before.learner["controller"] if before else None, stored,
            None if horizon is None else int(horizon))


def search_variant(config: RunConfig, overrides: dict[str, str], episodes, hyperparameters, controller_state, trial: int,
                   horizon: int | None = None, start: Start = Start(), tracking_uri: str | None = None):
    """One variant's search from the stored start, with the run's learner as the runner built it
    (:func:`~harness.runner.new_learner`: its options with ``overrides`` replaced, on the CPU; its derived
    seed), planning over ``horizon`` steps (the trial's logged horizon, which a growing schedule may have
    raised above the option's start) unless the variant sets ``planning_horizon``, from ``start`` (trial
    ``K-1``'s controller unless the variant set its own, :func:`split_start`; ``overrides`` are learner
    options only): ``(search result, policy, planning cost in words)``."""
    from harness.runner import new_learner, prepare
    from harness.task import Episode
    from plugins.pilco.gp import GPHyperparameters
    from plugins.pilco.policy import PilcoPolicy, transitions

    options = {**config.learner_options, **overrides, "device": "cpu"}
    learner = new_learner(prepare(dataclasses.replace(config, learner_options=options)))
    if horizon is not None and "planning_horizon" not in overrides:
        learner.schedule.horizon = horizon
    model = learner.new_model()
    x, y = transitions([Episode(**ep) for ep in episodes], learner.layout)
    warm = GPHyperparameters.from_dict(hyperparameters) if hyperparameters is not None else None
    model.fit(x, y, warm_start=warm, seed=learner.seed + trial)
    controller = start_controller(learner, start, controller_state, tracking_uri)
    posterior = model.posterior(max_basis=learner.options["planning_basis"]).detach()
    _, search = learner.search_trial(controller, posterior, trial, [Episode(**ep) for ep in episodes])
    cost = "MC-PILCO's" if learner.options["cost"] == "paper" else f"width {learner.planning_width(trial):g}"
    return search, PilcoPolicy.snapshot(controller, learner.layout), cost


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--trial", type=int, required=True)
    parser.add_argument("--variants", nargs="+", default=[""])
    add_test_arguments(parser, episodes=50)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    start = time.perf_counter()
    # (text, learner options, start), every variant checked before the first search
    variants = [(text, *split_start(parse_variant(text))) for text in args.variants]
    config, episodes, hyperparameters, controller_state, stored, horizon = stored_start(args.run, args.trial, args.tracking_uri)
    task, seed = prepare(config).task, derive_seeds(config.seed)["learner"]
    evaluator = Evaluator(task, n_episodes=args.episodes, seed=args.seed)
    rows = []
    for text, overrides, variant_start in variants:
        search, policy, cost_text = search_variant(config, overrides, episodes, hyperparameters, controller_state, args.trial,
                                                  horizon, variant_start, args.tracking_uri)
        result = evaluator(policy)
        successes = round(result.success_rate * args.episodes)
        rows.append((text or "the run's options", search, cost_text, result.mean_cost, successes))
        print(f"{text or 'run':40s} steps {search.steps:5d} J {search.J_before:.2f} -> {search.J_after:.2f} "
              f"(last {search.J_last:.2f}, kept step {search.kept_step}) real cost {result.mean_cost:.2f} success {successes}/{args.episodes} ({search.seconds:.0f} s)", flush=True)
    evaluator.close()

    run_options = ", ".join(f"{k}={v}" for k, v in sorted(config.learner_options.items())) or "defaults"
    repeat = next((r for r in rows if r[0] == "the run's options"), None)
    horizon_text = (f"{horizon} steps (the trial's logged horizon; a variant that sets planning_horizon plans over its own)"
                    if horizon is not None else "the run's planning horizon")
    lines = [
        f"# mc-pilco's policy search redone: run `{args.run[:8]}`, trial {args.trial}", "",
        f"Command: `{command_line(__file__, argv, env='OMP_NUM_THREADS=1')}`  ",
        f"Run: {task.spec.name}, learner seed {seed}, options {run_options}. The search starts from the controller of trial "
        f"{args.trial - 1 if args.trial > 1 else 'none (the initial one)'} (a `start=fresh` variant: from a fresh initial "
        f"controller, generator seed {seed} + start_seed; `start=RUN`: that run's policy of trial start_trial), over {horizon_text}, on the GP fitted to the {len(episodes)} episodes recorded "
        f"before trial {args.trial}'s hand-over, as the run did; the run's random numbers. Real: {args.episodes} episodes of "
        f"the task (seed {args.seed}), its own cost and success rule. One thread, wall time on a shared machine.", "",
    ]
    if repeat is not None and stored is not None:
        lines += [f"The run's own search repeated: J after {repeat[1].J_after:.6f}, stored {stored:.6f}.", ""]
    lines += ["| variant (learner options over the run's) | planning cost | Adam steps | dropout reductions | J_hat before -> after (last step's; kept step) "
              "| search s | real cost (mean) | real success (95 % CI) |", "|---|---|---|---|---|---|---|---|"]
    for text, search, cost_text, cost, successes in rows:
        low, high = wilson_interval(successes, args.episodes)
        lines.append(f"| {text} | {cost_text} | {search.steps} | {search.reductions} | {search.J_before:.2f} -> {search.J_after:.2f} "
                     f"({search.J_last:.2f}; {search.kept_step}) | {search.seconds:.0f} | {cost:.2f} | {successes}/{args.episodes} ({100 * low:.0f}-{100 * high:.0f} %) |")
    lines += ["", f"Wall time {time.perf_counter() - start:.0f} s."]
    write_report(lines, args.out)


if __name__ == "__main__":
    exit_on_error(main)
