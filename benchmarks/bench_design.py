"""Design sweep benchmarks (issue 48).

1. Evaluations per second on one core: the batched, compiled evaluation (design.problem.
   evaluate_batch) alternated with the old code kept in tests/design/reference_criteria.py, in
   rounds, in one process; the ratio of their median rates. Wall-clock and CPU time both.
2. With BENCH_DESIGN_DASK=N (designs, e.g. 20000): evaluations per second on a Dask LocalCluster
   of 1 and of 2 workers, each task 16 designs, and the scaling.
3. With BENCH_DESIGN_CONVERGENCE=DIR: the convergence fraction per seed (design.convergence;
   the same number as ``wvr design compare``) of DIR/<algorithm>_<seed> against
   DIR/random_<seed>, for the seeds and algorithm given by BENCH_DESIGN_SEEDS (default 0-4) and
   BENCH_DESIGN_ALGORITHM (default: the default sweep's, surrogate); missing runs are made (2520 evaluations each).

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_design.py`` from the repository root.
"""

import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "design")]   # this checkout, and the old code kept in its tests

import reference_criteria as RC  # noqa: E402
from design.convergence import fraction_to_match, read_evaluations  # noqa: E402
from design.layout import head_from_variables  # noqa: E402
from design.problem import EvaluationContext, evaluate_batch  # noqa: E402
from design.sweep import open_client, run_sweep  # noqa: E402
from design.sweep_file import load_sweep  # noqa: E402


#: Issue 48's target: evaluations per CPU second on one core, uniform random designs.
TARGET_PER_CPU_SECOND = 200.0


def rate(f, n):
    """(evaluations per second wall, per CPU second) of f() evaluating n designs."""
    w, c = time.perf_counter(), time.process_time()
    f()
    return n / (time.perf_counter() - w), n / (time.process_time() - c)


def speed(ctx, rounds=5, n_fast=400, n_ref=12):
    rng = np.random.default_rng(0)
    X = rng.uniform(ctx.spec.xl, ctx.spec.xu, (n_fast, len(ctx.spec.xl)))
    evaluate_batch(X[:4], ctx)          # compile (or load the cached kernels) and build the plan
    RC.reference_score(head_from_variables(X[0], ctx.spec), ctx)
    fast, ref = [], []
    for _ in range(rounds):
        fast.append(rate(lambda: evaluate_batch(X, ctx), n_fast))
        ref.append(rate(lambda: [RC.reference_score(head_from_variables(x, ctx.spec), ctx) for x in X[:n_ref]], n_ref))
    fast, ref = np.median(fast, axis=0), np.median(ref, axis=0)
    print(f"one core, median of {rounds} alternated rounds ({n_fast} and {n_ref} designs per round):")
    print(f"  batched, compiled: {fast[0]:8.1f} evaluations/s wall, {fast[1]:8.1f} per CPU second")
    print(f"  old code:          {ref[0]:8.1f} evaluations/s wall, {ref[1]:8.1f} per CPU second")
    print(f"  ratio:             {fast[0] / ref[0]:8.1f} x wall,       {fast[1] / ref[1]:8.1f} x CPU")
    verdict = "met" if fast[1] >= TARGET_PER_CPU_SECOND else "NOT met"
    print(f"  issue 48's {TARGET_PER_CPU_SECOND:.0f} per CPU second: {verdict} (load average {os.getloadavg()[0]:.1f})")


def dask_rates(ctx, n):
    from design.sweep import TASK_DESIGNS

    X = np.random.default_rng(1).uniform(ctx.spec.xl, ctx.spec.xu, (n, len(ctx.spec.xl)))
    out = {}
    for workers in (1, 2):
        client = open_client(workers=workers)
        try:
            ctx_f = client.scatter(ctx, broadcast=True)
            client.gather(client.map(evaluate_batch, [X[:4]] * workers, ctx=ctx_f, pure=False))   # warm up
            t = time.perf_counter()
            chunks = [X[s:s + TASK_DESIGNS] for s in range(0, n, TASK_DESIGNS)]
            client.gather(client.map(evaluate_batch, chunks, ctx=ctx_f, pure=False))
            out[workers] = n / (time.perf_counter() - t)
        finally:
            client.close()
        print(f"Dask LocalCluster, {workers} worker(s), {n} designs: {out[workers]:8.1f} evaluations/s")
    print(f"scaling 2 / 1 workers: x{out[2] / out[1]:.2f} on {os.cpu_count()} cores")


def convergence(spec, folder: Path, algorithm: str, seeds):
    fractions = []
    for seed in seeds:
        for alg in (algorithm, "random"):
            d = folder / f"{alg}_{seed}"
            if not (d / "evaluations.csv").exists():
                run_sweep(spec, d, evaluations=2520, seed=seed, algorithm=alg, progress=False)
        c = fraction_to_match(*read_evaluations(folder / f"{algorithm}_{seed}"),
                              *read_evaluations(folder / f"random_{seed}"), at=2520)
        fractions.append(c.fraction)
        print(f"seed {seed}: fraction {c.fraction:.3f} ({c.needed} evaluations; target {c.target:.5f}, "
              f"{'exact' if c.exact else 'approximate'})")
    print(f"median {np.median(fractions):.3f}, worst {np.max(fractions):.3f}")


def main():
    spec = load_sweep()
    ctx = EvaluationContext.from_spec(spec)
    speed(ctx)
    if os.environ.get("BENCH_DESIGN_DASK"):
        dask_rates(ctx, int(os.environ["BENCH_DESIGN_DASK"]))
    if os.environ.get("BENCH_DESIGN_CONVERGENCE"):
        seeds = [int(s) for s in os.environ.get("BENCH_DESIGN_SEEDS", "0,1,2,3,4").split(",")]
        algorithm = os.environ.get("BENCH_DESIGN_ALGORITHM", spec.algorithm)
        convergence(spec, Path(os.environ["BENCH_DESIGN_CONVERGENCE"]), algorithm, seeds)


if __name__ == "__main__":
    main()
