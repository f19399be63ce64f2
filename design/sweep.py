"""Running a sweep: batches of evaluations, local or on Dask, checkpointed so a kill loses nothing.

Files in the output folder while a sweep runs:

``sweep.toml``        the sweep as run (a resume refuses a different one)
``evaluations.csv``   every design evaluated, appended and flushed as each finishes
``state.pkl``         the search algorithm after the last completed batch (atomic rename)
``INCOMPLETE``        present until the run ends (kinematics.outdir), with ``.wvr-lock``, which
                      keeps a second run out of the folder while this one writes it

A resume restores the algorithm from ``state.pkl``; because every algorithm is deterministic
for its saved random state, it asks the same next batch again, and any design of that batch
already in ``evaluations.csv`` is reused instead of evaluated again. So killed at any moment,
even mid-write, a sweep resumes with no evaluation lost or repeated.
"""

from __future__ import annotations

import csv
import os
import pickle
import re

import cloudpickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from kinematics.progress import progress_bar

from kinematics.outdir import output_folder

from .problem import EvaluationContext, HeadLayoutProblem, evaluate_design
from .search import RandomVariation, nsga3
from .sweep_file import CONSTRAINTS, CRITERIA, VARIABLES, SweepSpec, dump_spec

#: The kind (kinematics.outdir) of a sweep's folder; it continues its own (--resume).
SWEEP = "design optimise"
COLUMNS = ("eval_id", "batch", "index", "algorithm", *VARIABLES, *CRITERIA, *CONSTRAINTS, "feasible")


class SweepStateError(ValueError):
    """A sweep folder that cannot be started or resumed as asked; the message says what to do."""


@dataclass
class SweepState:
    digest: str
    algorithm_name: str
    seed: int
    algorithm: object
    batches_done: int = 0
    evaluations_done: int = 0


@dataclass
class SweepResult:
    X: np.ndarray          # (n, 12)
    F: np.ndarray          # (n, 7)
    G: np.ndarray          # (n, 3)
    batch: np.ndarray      # (n,)
    ctx: EvaluationContext
    algorithm: str
    reused: int = 0        # evaluations taken from the log on resume
    evaluated: int = 0     # evaluations computed in this run

    @property
    def feasible(self) -> np.ndarray:
        return np.all(self.G <= 0, axis=1)


def make_algorithm(name: str, ctx: EvaluationContext, seed: int):
    spec = ctx.spec
    if name == "nsga3":
        return nsga3(HeadLayoutProblem(ctx), seed, spec.partitions)
    if name == "random":
        # Same batch size as NSGA-III's population, so the two compare batch for batch.
        from pymoo.util.ref_dirs import get_reference_directions
        n = len(get_reference_directions("das-dennis", len(CRITERIA), n_partitions=spec.partitions))
        return RandomVariation(spec.xl, spec.xu, n, seed)
    raise SweepStateError(f"unknown algorithm {name!r}; use 'nsga3' or 'random'")


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _read_log(path: Path) -> list[dict]:
    """Rows of evaluations.csv; a torn last line (killed mid-write) is dropped and the file mended."""
    if not path.exists():
        return []
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    good = [lines[0]] if lines else []
    rows = []
    for line in lines[1:]:
        vals = next(csv.reader([line]))
        if not line.endswith("\n") or len(vals) != len(COLUMNS):
            break
        try:
            row = dict(zip(COLUMNS, vals))
            row["x"] = np.array([float(row[v]) for v in VARIABLES])
            row["F"] = np.array([float(row[c]) for c in CRITERIA])
            row["G"] = np.array([float(row[c]) for c in CONSTRAINTS])
        except ValueError:
            break
        rows.append(row)
        good.append(line)
    if len(good) != len(lines):
        _write_atomic(path, "".join(good).encode())
    return rows


class _Log:
    """Append-only evaluations.csv, flushed and synced per row."""

    def __init__(self, path: Path, next_id: int):
        new = not path.exists()
        self.file = open(path, "a", newline="")
        self.writer = csv.writer(self.file)
        if new:
            self.writer.writerow(COLUMNS)
        self.next_id = next_id

    def add(self, batch: int, index: int, algorithm: str, x, F, G) -> None:
        feasible = bool(np.all(G <= 0))
        self.writer.writerow([self.next_id, batch, index, algorithm, *map(repr, map(float, x)),
                              *map(repr, map(float, F)), *map(repr, map(float, G)), int(feasible)])
        self.file.flush()
        os.fsync(self.file.fileno())
        self.next_id += 1

    def close(self) -> None:
        self.file.close()


def _evaluate_many(X: np.ndarray, ctx, client, on_done) -> None:
    """Evaluate rows of X, calling on_done(i, F, G) as each finishes (any order).

    ``ctx`` is the EvaluationContext itself, or, with a client, its scattered future."""
    if client is None:
        for i, x in enumerate(X):
            F, G = evaluate_design(x, ctx)
            on_done(i, F, G)
        return
    from dask.distributed import as_completed

    futures = {client.submit(evaluate_design, x, ctx, pure=False): i for i, x in enumerate(X)}
    for fut in as_completed(futures):
        F, G = fut.result()
        on_done(futures[fut], F, G)


def check_client_options(workers: int | None = None, scheduler: str | None = None) -> None:
    """Refuse, before any work, a worker count or scheduler address that cannot be used."""
    if workers is not None and scheduler is not None:
        raise ValueError("give either workers (a local Dask cluster) or a scheduler address, not both")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers = {workers!r}: give at least 1 worker process (or none, to evaluate here)")
    if scheduler is not None and not re.fullmatch(r"(tcp|tls)://[^\s:/]+:\d{1,5}", str(scheduler)):
        raise ValueError(f"scheduler {scheduler!r}: give a Dask scheduler address as tcp://HOST:PORT, "
                         f"e.g. tcp://127.0.0.1:8786")


#: Seconds to wait for a remote scheduler before giving up with a one-line error.
SCHEDULER_TIMEOUT_S = 5.0


def open_client(workers: int | None = None, scheduler: str | None = None):
    """A dask.distributed Client: a LocalCluster of ``workers`` processes, or an existing scheduler
    (None when neither is given: evaluate in this process). Bad options and a scheduler that does
    not answer within SCHEDULER_TIMEOUT_S raise ValueError."""
    check_client_options(workers, scheduler)
    if workers is None and scheduler is None:
        return None
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            return Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT_S:g}s")
        except (OSError, TimeoutError) as e:
            raise ValueError(f"scheduler {scheduler}: no Dask scheduler answered within {SCHEDULER_TIMEOUT_S:g} s "
                             f"({type(e).__name__}); start one ('dask scheduler') or check the address") from None
    # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which turns off glibc's
    # adaptive mmap threshold and makes every large temporary of the voxel sweep a fresh mapping
    # (page faults halve a worker's rate; benchmarks/NOTES.md). Start the workers with the plain
    # process's allocator, and one BLAS thread each, as the nanny does.
    import dask

    env = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": env}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    return Client(cluster)


def check_sweep_folder(spec: SweepSpec, out: Path, seed: int, algorithm: str, resume: bool) -> None:
    """Refuse, before anything is written, a folder the sweep cannot start or resume in."""
    out = Path(out)
    state_path, log_path, spec_path = out / "state.pkl", out / "evaluations.csv", out / "sweep.toml"
    if resume:
        if not state_path.exists():
            raise SweepStateError(f"{out}: nothing to resume (no state.pkl); run without --resume to start")
        state: SweepState = pickle.loads(state_path.read_bytes())
        if state.digest != spec.digest():
            raise SweepStateError(f"{out}: the sweep file differs from the one this sweep started with "
                                  f"({spec_path}); resume with that file, or start a new --out")
        if state.seed != seed or state.algorithm_name != algorithm:
            raise SweepStateError(f"{out}: started with seed {state.seed} and algorithm {state.algorithm_name!r}; "
                                  "resume with the same ones")
    elif state_path.exists() or log_path.exists():
        raise SweepStateError(f"{out} already holds a sweep; use --resume to continue it, or choose a new --out")


def run_options(spec: SweepSpec, evaluations: int | None, seed: int | None,
                algorithm: str | None) -> tuple[int, int, str]:
    """(budget, seed, algorithm): the run's options, the sweep file's where not given; checked."""
    budget = spec.evaluations if evaluations is None else evaluations
    if isinstance(budget, bool) or int(budget) != budget or budget < 1:
        raise SweepStateError(f"evaluations = {budget!r}: give a budget of at least 1 evaluation (e.g. 200)")
    algorithm = spec.algorithm if algorithm is None else algorithm
    if algorithm not in ("nsga3", "random"):
        raise SweepStateError(f"unknown algorithm {algorithm!r}; use 'nsga3' or 'random'")
    return int(budget), spec.seed if seed is None else int(seed), algorithm


def run_sweep(spec: SweepSpec, out: Path, *, evaluations: int | None = None, seed: int | None = None,
              algorithm: str | None = None, resume: bool = False, client=None, progress: bool = True,
              ctx: EvaluationContext | None = None) -> SweepResult:
    """Run (or resume) a sweep into ``out``; returns every evaluation of the sweep.

    ``client`` is a dask.distributed Client (see :func:`open_client`) or None for this process.
    Results do not depend on the client: evaluations are pure functions of the design vector,
    and their results are placed by index, not by arrival. The folder is written inside
    :func:`kinematics.outdir.output_folder` (locked against a second run, INCOMPLETE until done).
    """
    out = Path(out)
    budget, seed, algorithm = run_options(spec, evaluations, seed, algorithm)
    with output_folder(out, check=lambda d: check_sweep_folder(spec, d, seed, algorithm, resume), kind=SWEEP, reuse=True):
        return _run(spec, out, budget, seed, algorithm, resume, client, progress, ctx)


def _run(spec: SweepSpec, out: Path, budget: int, seed: int, algorithm: str, resume: bool, client, progress: bool,
         ctx: EvaluationContext | None) -> SweepResult:
    state_path, log_path, spec_path = out / "state.pkl", out / "evaluations.csv", out / "sweep.toml"
    ctx = ctx or EvaluationContext.from_spec(spec)
    if resume:
        state: SweepState = pickle.loads(state_path.read_bytes())
        _attach_context(state.algorithm, ctx)
    else:
        state = SweepState(spec.digest(), algorithm, seed, make_algorithm(algorithm, ctx, seed))
        spec_path.write_text(dump_spec(spec))
        _write_atomic(state_path, cloudpickle.dumps(state))

    # Ship the context (workload arrays) to every worker once per run, not once per batch.
    ctx_remote = ctx if client is None else client.scatter(ctx, broadcast=True)
    rows = _read_log(log_path)
    logged = {(int(r["batch"]), int(r["index"])): r for r in rows}
    log = _Log(log_path, next_id=len(rows))
    reused = evaluated = 0
    bar = progress_bar(total=budget, initial=state.evaluations_done, desc=f"design {algorithm}", unit="eval",
               disable=not progress)
    try:
        while state.evaluations_done < budget:
            X = state.algorithm.ask()[: budget - state.evaluations_done]
            F = np.empty((len(X), len(CRITERIA)))
            G = np.empty((len(X), len(CONSTRAINTS)))
            todo = []
            for i, x in enumerate(X):
                r = logged.get((state.batches_done, i))
                if r is not None and np.array_equal(r["x"], x):
                    F[i], G[i] = r["F"], r["G"]
                    reused += 1
                    bar.update(1)
                else:
                    todo.append(i)

            def done(j, f, g, batch=state.batches_done, idx=todo):
                i = idx[j]
                F[i], G[i] = f, g
                log.add(batch, i, algorithm, X[i], f, g)
                bar.update(1)

            _evaluate_many(X[todo], ctx_remote, client, done)
            evaluated += len(todo)
            state.algorithm.tell(X, F, G)
            state.batches_done += 1
            state.evaluations_done += len(X)
            _write_atomic(state_path, cloudpickle.dumps(state))
    finally:
        bar.close()
        log.close()
    rows = [r for r in _read_log(log_path) if int(r["batch"]) < state.batches_done]
    # One row per (batch, index): a design re-evaluated after a mismatch supersedes the old row.
    by_key = {}
    for r in rows:
        by_key[(int(r["batch"]), int(r["index"]))] = r
    rows = [by_key[k] for k in sorted(by_key)]
    return SweepResult(X=np.array([r["x"] for r in rows]).reshape(-1, len(VARIABLES)),
                       F=np.array([r["F"] for r in rows]).reshape(-1, len(CRITERIA)),
                       G=np.array([r["G"] for r in rows]).reshape(-1, len(CONSTRAINTS)),
                       batch=np.array([int(r["batch"]) for r in rows], dtype=int),
                       ctx=ctx, algorithm=algorithm, reused=reused, evaluated=evaluated)


def _attach_context(alg, ctx: EvaluationContext) -> None:
    problem = getattr(alg, "problem", None)
    if problem is not None:
        problem.ctx = ctx
