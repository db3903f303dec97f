"""Wall time of the PILCO GP dynamics-model fit (prints only; writes no files).

Data: d = 6 inputs uniform in [-2, 2]^6, E = 4 outputs, each a smooth random function
(sums of sines of random projections) plus noise of std 0.01 - the size of the cart-pole model
(4 state differences from 5 state features + 1 control). One thread.

Also compares the two L-BFGS implementations on the same full-GP objective (scipy L-BFGS-B with
torch gradients, as used by ``plugins.pilco.gp``, versus ``torch.optim.LBFGS`` with a strong-Wolfe
line search).

Usage: ``.venv/bin/python benchmarks/bench_gp_fit.py [--sizes 100 300 1000] [--compare-optimisers]``
"""

from __future__ import annotations

import argparse
import time

import torch

from plugins.pilco.gp import (
    GPModel,
    initial_hyperparameters,
    input_scale,
    hyp_curb_penalty,
    negative_log_marginal_likelihood,
    noise_floor,
    optimise_hyperparameters,
)

DT = torch.float64


def make_data(n: int, d: int = 6, e: int = 4, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, d, generator=gen, dtype=DT) * 4 - 2
    w = torch.randn(3, d, e, generator=gen, dtype=DT) * 0.6
    y = sum(torch.sin(x @ w[k] + k) for k in range(3)) + 0.01 * torch.randn(n, e, generator=gen, dtype=DT)
    return x, y


def bench_fit(sizes: list[int]) -> None:
    d = GPModel()
    print(
        f"GPModel.fit (defaults: sparse_threshold={d.sparse_threshold}, num_pseudo={d.num_pseudo}, "
        f"max_evals_full={d.max_evals_full}, max_evals_fitc={d.max_evals_fitc} x{d.fitc_first_factor} first time)"
    )
    print(f"{'n':>6} {'sparse':>6} {'n_hyp':>6} {'evals':>6} {'seconds':>8}  first fit / warm-started refit with +10% data")
    for n in sizes:
        x, y = make_data(int(n * 1.1))
        model = GPModel()
        first = model.fit(x[:n], y[:n])
        second = model.fit(x, y, warm_start=first.hyperparameters)
        print(
            f"{n:>6} {str(first.sparse):>6} {first.n_hyper_points:>6} {first.evaluations:>6} {first.seconds:>8.2f}"
            f"  | refit n={x.shape[0]}: evals {second.evaluations}, {second.seconds:.2f} s"
        )
        for msg in first.messages:
            print(f"{'':>8}{msg}")
        if first.sparse:
            full = GPModel(sparse_threshold=10**9).fit(x[:n], y[:n])
            print(f"{'':>8}for comparison, a full GP on all {n} points: {full.evaluations} evals, {full.seconds:.2f} s")


def bench_optimisers(n: int, max_evals: int = 300) -> None:
    x, y = make_data(n)
    init = initial_hyperparameters(x, y)
    floor = noise_floor(y)
    t0 = time.perf_counter()
    _, nll, res = optimise_hyperparameters(x, y, init, floor, max_evals)
    t_scipy = time.perf_counter() - t0
    print(f"n={n}: scipy L-BFGS-B  {t_scipy:6.2f} s, {res.evaluations:4d} evals, penalised NLL {float(nll.sum()):.4f}")

    s = input_scale(x)
    params = torch.cat([init.log_ell.reshape(-1), init.log_alpha, init.log_sigma]).clone().requires_grad_(True)
    e, d = y.shape[1], x.shape[1]
    evals = [0]

    def objective() -> torch.Tensor:
        evals[0] += 1
        le, la, ls = params[: e * d].reshape(e, d), params[e * d : e * d + e], params[e * d + e :]
        return (negative_log_marginal_likelihood(x, y, le, la, ls) + hyp_curb_penalty(le, la, ls, s)).sum()

    opt = torch.optim.LBFGS(
        [params], lr=1.0, max_iter=max_evals, max_eval=max_evals, history_size=10,
        tolerance_grad=1e-5, tolerance_change=1e-9, line_search_fn="strong_wolfe",
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = objective()
        loss.backward()
        return loss

    t0 = time.perf_counter()
    opt.step(closure)
    t_torch = time.perf_counter() - t0
    with torch.no_grad():
        final = float(objective())
    print(f"n={n}: torch.optim.LBFGS {t_torch:6.2f} s, {evals[0] - 1:4d} evals, penalised NLL {final:.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 300, 1000])
    parser.add_argument("--compare-optimisers", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}")
    if args.compare_optimisers:
        for n in (100, 300):
            bench_optimisers(n)
    bench_fit(args.sizes)


if __name__ == "__main__":
    main()
