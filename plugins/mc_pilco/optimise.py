"""MC-PILCO's policy optimisation: Adam on the particle estimate, with dropout reduced as it stalls.

Each step draws fresh particles, model noise and dropout masks, estimates ``J_hat`` and its gradient
(:class:`~plugins.mc_pilco.particles.ParticleObjective`) and takes one Adam step. The estimate is
noisy, so progress is judged on window means (the paper's monitoring signal, as a windowed mean
instead of a filtered one): when the mean of the last ``window`` estimates is not at least
``min_improvement`` (relative) below the mean of the window before, the dropout probability drops by
``dropout_step`` and the learning rate is multiplied by ``lr_decay``; once dropout is 0 and
progress stalls again, or after ``max_steps``, the search ends. With ``lr_reductions`` = k > 0 a stall at
dropout 0 instead multiplies the learning rate by ``lr_decay`` again, up to k times, before the next
one ends the search (not the paper's rule: a search without dropout otherwise never lowers its rate). The parameters at the end are
kept (``keep="last"``, the paper's rule); with ``keep="best"`` the search keeps, of its start, the
end of each window and its end, the parameters whose estimate on one fixed set of particles (no
dropout, the random numbers of ``J_before``/``J_after``) is lowest: common random numbers make those
estimates comparable, which single steps' noisy estimates are not. It costs one estimate without
gradient per window. With ``keep="best"`` and ``revert`` the search also backtracks (not the paper's rule):
a window end that the fixed particles do not rate below the best so far sends the parameters back to the
best, restarts Adam there at the learning rate times ``lr_decay`` and counts as one of the
``lr_reductions``; once they are used up, such a window ends the search. A search that runs uphill from
its start then retries with smaller steps instead of climbing on. With ``revert``, ``lr_growth`` > 1 makes that a
trust region (not the paper's rule): a window end that the fixed particles rate below the best so far multiplies the
learning rate by ``lr_growth``, up to ``lr``, so that a search that found a descending step size does not keep a rate
halved by an earlier backtrack.

Adam moves every parameter by about the learning rate per step whatever its gradient's size, so the
parameters' units matter. ``step_scales`` (one tensor per parameter, its shape) sets them: Adam runs
on ``phi = theta / scale``, i.e. it is handed ``scale * dJ/dtheta`` and ``theta`` moves by ``scale``
times Adam's step (``None``: every parameter in its own units, the paper's).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from plugins.mc_pilco.particles import ParticleObjective


@dataclass
class ParticleSearchResult:
    """Outcome of :func:`optimise_particles`.

    Attributes:
        J_before, J_after: particle estimates (no dropout, the same fresh particles) at the start and
            at the parameters kept.
        J_last: the same estimate at the last step's parameters (= ``J_after`` with ``keep="last"``).
        kept_step: the Adam step whose parameters were kept (0: the start; ``steps``: the last).
        steps: Adam steps taken; skipped: steps whose estimate was not finite (no update).
        reductions: dropout reductions; lr_reductions: learning-rate reductions at dropout 0 (option
            ``lr_reductions``; with ``revert``, its backtracks are among them); reverts: backtracks to the best
            parameters (``revert``); growths: learning-rate increases (``lr_growth``); final_dropout, final_lr: their
            values at the end.
        seconds: wall time; trace: window means of the estimates (with dropout), for plots; rates: the learning
            rate Adam steps with after each window.
    """

    J_before: float
    J_after: float
    J_last: float
    kept_step: int
    steps: int
    skipped: int
    reductions: int
    lr_reductions: int
    reverts: int
    growths: int
    final_dropout: float
    final_lr: float
    seconds: float
    trace: list[float]
    rates: list[float]


def adam_step(opt: torch.optim.Adam, params: list[torch.Tensor], grads: list[torch.Tensor | None],
              step_scales: list[torch.Tensor] | None = None) -> None:
    """One step of ``opt`` (an Adam over ``params``) with gradient ``grads`` of J wrt ``params``; with
    ``step_scales``, Adam on ``phi = theta / scale``: it is handed ``scale * g`` and ``theta`` moves by
    ``scale`` times its step (Adam's state then lives in ``phi``'s units)."""
    if step_scales is None:
        for q, g in zip(params, grads):
            q.grad = g
        opt.step()
        return
    before = [q.detach().clone() for q in params]
    for q, g, c in zip(params, grads, step_scales):
        q.grad = None if g is None else g * c
    opt.step()
    with torch.no_grad():
        for q, b, c in zip(params, before, step_scales):
            q.copy_(b + c * (q - b))


def optimise_particles(objective: ParticleObjective, *, max_steps: int, lr: float, dropout: float, dropout_step: float,
                       lr_decay: float, window: int, min_improvement: float, seed: int, keep: str = "last",
                       lr_reductions: int = 0, revert: bool = False, lr_growth: float = 1.0,
                       step_scales: list[torch.Tensor] | None = None,
                       on_step: Callable[[int, float, float], None] | None = None) -> ParticleSearchResult:
    """Minimise ``J_hat`` over the controller's parameters, left at the last step's values
    (``keep="last"``) or at those of the start or a window's end that the fixed particles rate lowest
    (``keep="best"``). ``step_scales``: Adam in the units ``theta / scale`` (see the module docstring;
    one tensor per :meth:`~plugins.mc_pilco.particles.ParticleObjective.parameters` entry, its shape).
    ``lr_reductions``: stalls at dropout 0 (and with ``revert``, windows that end above the best so far) that lower
    the learning rate (by ``lr_decay``) before one ends the search; ``revert`` needs ``keep="best"``; ``lr_growth``:
    with ``revert``, the factor (up to ``lr``) a window end rated below the best so far raises the learning rate by.

    ``on_step(step, window mean of J_hat or nan before the first window, dropout)``, if given, is
    called after every Adam step (for progress)."""
    start = time.perf_counter()
    params = objective.parameters()

    def checked() -> float:  # the same fresh particles before and after, no dropout
        with torch.no_grad():
            value = float(objective.value(torch.Generator().manual_seed(int(seed) + 1)))
        return value if math.isfinite(value) else math.inf

    if keep not in ("last", "best"):
        raise ValueError(f"keep must be 'last' or 'best', got {keep!r}")
    if revert and keep != "best":
        raise ValueError("revert=True goes back to the best parameters so far, which only keep='best' tracks")
    if int(lr_reductions) < 0:
        raise ValueError(f"lr_reductions must be >= 0, got {lr_reductions}")
    lr_reductions = int(lr_reductions)
    if not lr_growth >= 1.0:
        raise ValueError(f"lr_growth must be >= 1, got {lr_growth}")
    if lr_growth > 1.0 and not revert:
        raise ValueError("lr_growth > 1 raises the rate after a window that set a new best, which only revert=True "
                         "backtracks from when it overshoots")
    if step_scales is not None and [tuple(q.shape) for q in step_scales] != [tuple(q.shape) for q in params]:
        raise ValueError(f"step_scales must have the parameters' shapes {[tuple(q.shape) for q in params]}, got "
                         f"{[tuple(q.shape) for q in step_scales]}")
    J_before = checked()
    best = (J_before, 0, [q.detach().clone() for q in params]) if keep == "best" else None  # (estimate, step, parameters)

    def candidate(step: int) -> bool:  # keep="best": the parameters after `step` if the fixed particles rate them lower
        nonlocal best
        value = checked()
        if value < best[0]:
            best = (value, step, [q.detach().clone() for q in params])
            return True
        return False

    def restore(values: list[torch.Tensor]) -> None:  # the parameters set to kept values
        with torch.no_grad():
            for q, b in zip(params, values):
                q.copy_(b)

    opt = torch.optim.Adam(params, lr=lr)
    gen = torch.Generator().manual_seed(int(seed))
    estimates: list[float] = []
    trace: list[float] = []
    rates: list[float] = []
    skipped = reductions = late = reverts = growths = steps = 0
    p, rate = float(dropout), float(lr)
    for steps in range(1, int(max_steps) + 1):
        J, usable, grads = objective.value_and_grad(gen, p)  # on a GPU: a CUDA graph replayed (cuda_graph)
        if not usable:  # J_hat or its gradient not finite
            skipped += 1
            continue
        adam_step(opt, params, grads, step_scales)
        estimates.append(J)
        if len(estimates) % window == 0:
            trace.append(float(np.mean(estimates[-window:])))
            improved = keep == "best" and candidate(steps)
            if keep == "best" and not improved and revert:
                if late >= lr_reductions:
                    break
                restore(best[2])  # back to the best so far, Adam afresh with smaller steps
                rate *= lr_decay
                late += 1
                reverts += 1
                opt = torch.optim.Adam(params, lr=rate)
            else:
                stalled = len(trace) >= 2 and trace[-2] - trace[-1] < min_improvement * abs(trace[-2])
                if stalled and p <= 0.0 and late >= lr_reductions:
                    break  # the search ends here: no growth of a rate nobody uses
                if improved and lr_growth > 1.0 and rate < lr:  # trust region: a new best widens the step again
                    rate = min(float(lr), rate * lr_growth)
                    growths += 1
                if stalled:
                    if p > 0.0:
                        p, rate = max(0.0, p - dropout_step), rate * lr_decay
                        reductions += 1
                    else:
                        rate *= lr_decay
                        late += 1
                for group in opt.param_groups:
                    group["lr"] = rate
            rates.append(rate)
        if on_step is not None:
            on_step(steps, trace[-1] if trace else math.nan, p)
    J_last = checked()
    J_after, kept_step = J_last, steps
    if keep == "best" and not J_last <= best[0]:  # a tie keeps the last
        J_after, kept_step = best[0], best[1]
        restore(best[2])
    return ParticleSearchResult(J_before=J_before, J_after=J_after, J_last=J_last, kept_step=kept_step, steps=steps,
                                skipped=skipped, reductions=reductions, lr_reductions=late, reverts=reverts, growths=growths,
                                final_dropout=p, final_lr=rate, seconds=time.perf_counter() - start, trace=trace, rates=rates)
