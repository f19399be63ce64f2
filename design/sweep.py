"""Running a sweep: batches of evaluations, local or on Dask, checkpointed so a kill loses nothing.

Files in the output folder while a sweep runs:

``sweep.toml``        the sweep as run (a resume refuses a different one)
``evaluations.csv``   every design evaluated, appended and flushed as each finishes
``state.json``        what the sweep was started with: the sweep's digest, the algorithm, the seed
``INCOMPLETE``        present until the run ends (kinematics.outdir), with ``.wvr-lock``, which
                      keeps a second run out of the folder while this one writes it

A resume never loads a pickled object (a crafted pickle runs code): it rebuilds the algorithm
from its seed and replays it against ``evaluations.csv``. Every algorithm is deterministic for
its seed and what it is told, so it asks the same batches again, and every design already in
the log is reused instead of evaluated again. So killed at any moment, even mid-write, a sweep
resumes with no evaluation lost or repeated. Damaged rows of the log (a torn last line, a
garbled one) are named in a warning and evaluated again; the good rows after them are kept.
"""

from __future__ import annotations

import csv
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from kinematics.progress import progress_bar

from kinematics.outdir import output_folder

from .problem import EvaluationContext, HeadLayoutProblem, evaluate_batch
from .search import RandomVariation, agemoea2, nsga3, surrogate_agemoea2
from .sweep_file import ALGORITHMS, CONSTRAINTS, CRITERIA, VARIABLES, SweepSpec, dump_spec

#: The kind (kinematics.outdir) of a sweep's folder; it continues its own (--resume).
SWEEP = "design optimise"
COLUMNS = ("eval_id", "batch", "index", "algorithm", *VARIABLES, *CRITERIA, *CONSTRAINTS, "feasible")


class SweepStateError(ValueError):
    """A sweep folder that cannot be started or resumed as asked; the message says what to do."""


#: The checkpoint's format: state.json holds only these keys.
STATE_KEYS = ("format", "digest", "algorithm", "seed")
STATE_FORMAT = 1


@dataclass
class SweepState:
    digest: str
    algorithm_name: str
    seed: int
    algorithm: object
    batches_done: int = 0
    evaluations_done: int = 0


def _warn(message: str) -> None:
    print(f"wvr: warning: {message}", file=sys.stderr)


def _read_state(out: Path) -> dict:
    """state.json's keys, checked; SweepStateError in one line for anything else."""
    path = out / "state.json"
    if not path.exists():
        if (out / "state.pkl").exists():
            raise SweepStateError(f"{out}: holds state.pkl from an older wvr, which is never loaded (unpickling a "
                                  f"file can run code); start the sweep again in a new --out")
        raise SweepStateError(f"{out}: nothing to resume (no state.json); run without --resume to start")
    try:
        state = json.loads(path.read_text())
        if not isinstance(state, dict) or set(state) != set(STATE_KEYS) or state["format"] != STATE_FORMAT:
            raise ValueError("unexpected keys")
        if not (isinstance(state["digest"], str) and isinstance(state["algorithm"], str)
                and isinstance(state["seed"], int) and not isinstance(state["seed"], bool)):
            raise ValueError("unexpected values")
    except (ValueError, UnicodeDecodeError) as e:
        raise SweepStateError(f"{path}: damaged checkpoint ({e}); it should hold {{{', '.join(STATE_KEYS)}}}; "
                              f"start the sweep again in a new --out") from None
    return state


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


#: Random variation's batch: fixed, so that the paper's baseline does not change with NSGA-III's
#: population (it was 84 = the directions of 3 partitions when docs/design-sweeps.md measured it).
RANDOM_BATCH = 84


def make_algorithm(name: str, ctx: EvaluationContext, seed: int):
    spec = ctx.spec
    if name == "agemoea2":
        return agemoea2(HeadLayoutProblem(ctx), seed)
    if name == "surrogate":
        return surrogate_agemoea2(HeadLayoutProblem(ctx), seed)
    if name == "nsga3":
        return nsga3(HeadLayoutProblem(ctx), seed, spec.partitions)
    if name == "random":
        return RandomVariation(spec.xl, spec.xu, RANDOM_BATCH, seed)
    raise SweepStateError(f"unknown algorithm {name!r}; use one of {', '.join(ALGORITHMS)}")


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _read_log(path: Path) -> list[dict]:
    """Rows of evaluations.csv. Damaged rows (a torn last line, a garbled or short one) are
    dropped from the file with a warning naming their lines, so they are evaluated again; the
    good rows around them are kept. A file without its header is refused (or, empty, rebuilt)."""
    if not path.exists():
        return []
    text = path.read_text(errors="replace")
    lines = text.splitlines(keepends=True)
    header = ",".join(COLUMNS)
    if not lines:
        _warn(f"{path} was empty (no header, no rows): rebuilt with its header; no evaluation was in it")
        _write_atomic(path, (header + "\r\n").encode())
        return []
    if lines[0].strip() != header:
        raise SweepStateError(f"{path}: the first line is not the evaluations header ({COLUMNS[0]},{COLUMNS[1]},...); "
                              f"move the file aside and resume, or start a new --out")
    rows, good, bad = [], [lines[0]], []
    for number, line in enumerate(lines[1:], start=2):
        try:
            if not line.endswith("\n"):
                raise ValueError("torn")
            vals = next(csv.reader([line]))
            if len(vals) != len(COLUMNS):
                raise ValueError("short")
            row = dict(zip(COLUMNS, vals))
            row["x"] = np.array([float(row[v]) for v in VARIABLES])
            row["F"] = np.array([float(row[c]) for c in CRITERIA])
            row["G"] = np.array([float(row[c]) for c in CONSTRAINTS])
            int(row["batch"]), int(row["index"]), int(row["eval_id"])
        except (ValueError, StopIteration, csv.Error):
            bad.append(number)
            continue
        rows.append(row)
        good.append(line)
    if bad:
        _warn(f"{path}: dropped {len(bad)} damaged row(s) at line(s) {_ranges(bad)}; they are evaluated again")
        _write_atomic(path, "".join(good).encode())
    return rows


def _ranges(numbers: list[int]) -> str:
    """'3, 7-9' for [3, 7, 8, 9]."""
    out, start = [], numbers[0]
    for a, b in zip(numbers, numbers[1:] + [None]):
        if b != a + 1:
            out.append(f"{start}" if start == a else f"{start}-{a}")
            start = b
    return ", ".join(out)


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


#: Designs per Dask task: enough to amortise a task's overhead (about a millisecond), few enough
#: that every worker gets several tasks of a batch.
TASK_DESIGNS = 16


def _evaluate_many(X: np.ndarray, ctx, client, on_done) -> None:
    """Evaluate rows of X, calling on_done(i, F, G) as each finishes (any order).

    ``ctx`` is the EvaluationContext itself, or, with a client, its scattered future. Locally
    the whole batch is one evaluate_batch call; on Dask, each task takes TASK_DESIGNS rows."""
    if len(X) == 0:
        return
    if client is None:
        F, G = evaluate_batch(X, ctx)
        for i in range(len(X)):
            on_done(i, F[i], G[i])
        return
    from dask.distributed import as_completed

    starts = range(0, len(X), TASK_DESIGNS)
    futures = {client.submit(evaluate_batch, X[s:s + TASK_DESIGNS], ctx, pure=False): s for s in starts}
    for fut in as_completed(futures):
        F, G = fut.result()
        for k in range(len(F)):
            on_done(futures[fut] + k, F[k], G[k])


def check_client_options(workers: int | None = None, scheduler: str | None = None,
                         dashboard: str | None = None) -> None:
    """Refuse, before any work, a worker count or scheduler address that cannot be used."""
    if workers is not None and scheduler is not None:
        raise ValueError("give either workers (a local Dask cluster) or a scheduler address, not both")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers = {workers!r}: give at least 1 worker process (or none, to evaluate here)")
    if dashboard is not None and not re.fullmatch(r"[^\s:/]*:\d{1,5}", str(dashboard)):
        raise ValueError(f"dashboard {dashboard!r}: give HOST:PORT for Dask's dashboard, e.g. 127.0.0.1:8787")
    if scheduler is not None and not re.fullmatch(r"(tcp|tls)://[^\s:/]+:\d{1,5}", str(scheduler)):
        raise ValueError(f"scheduler {scheduler!r}: give a Dask scheduler address as tcp://HOST:PORT, "
                         f"e.g. tcp://127.0.0.1:8786")


#: Seconds to wait for a remote scheduler before giving up with a one-line error.
SCHEDULER_TIMEOUT_S = 5.0


def open_client(workers: int | None = None, scheduler: str | None = None, dashboard: str | None = None):
    """A dask.distributed Client: a LocalCluster of ``workers`` processes, or an existing scheduler
    (None when neither is given: evaluate in this process). Bad options and a scheduler that does
    not answer within SCHEDULER_TIMEOUT_S raise ValueError.

    The local cluster listens on loopback only, its dashboard too unless ``dashboard`` (HOST:PORT)
    asks for another address: Dask's dashboard has no authentication."""
    check_client_options(workers, scheduler, dashboard)
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
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=dashboard or "127.0.0.1:0")
    return Client(cluster)


#: Files a sweep writes; a folder holding other files is not a sweep's and is never written into.
SWEEP_FILES = {"sweep.toml", "evaluations.csv", "state.json", "INCOMPLETE", ".wvr-lock", "front.csv", "report.md",
               "chosen_head.toml", "head.xml", "front_parallel.png", "front_scatter.png", "chosen_head.png",
               "evaluations.csv.tmp", "state.json.tmp"}


def check_sweep_folder(spec: SweepSpec, out: Path, seed: int, algorithm: str, resume: bool,
                       budget: int | None = None) -> None:
    """Refuse, before anything is written, a folder the sweep cannot start or resume in (and a
    resume whose ``budget`` is below the evaluations already logged)."""
    out = Path(out)
    log_path, spec_path = out / "evaluations.csv", out / "sweep.toml"
    if resume:
        state = _read_state(out)
        if state["digest"] != spec.digest():
            raise SweepStateError(f"{out}: the sweep file differs from the one this sweep started with "
                                  f"({spec_path}); resume with that file, or start a new --out")
        if state["seed"] != seed or state["algorithm"] != algorithm:
            raise SweepStateError(f"{out}: started with seed {state['seed']} and algorithm {state['algorithm']!r}; "
                                  "resume with the same ones")
        if budget is not None and log_path.exists():
            with open(log_path, errors="replace") as f:
                logged = sum(1 for line in f if line.endswith("\n")) - 1
            if logged > budget:
                raise SweepStateError(f"{out}: the sweep already holds {logged} evaluations, more than the budget of "
                                      f"{budget}; resume with --evaluations {logged} or more")
    elif (out / "state.json").exists() or (out / "state.pkl").exists() or log_path.exists():
        raise SweepStateError(f"{out} already holds a sweep; use --resume to continue it, or choose a new --out")
    elif out.is_dir():
        others = sorted(p.name for p in out.iterdir() if p.name not in SWEEP_FILES)
        if others or (out / "report.md").exists():
            shown = ", ".join((others or ["report.md"])[:3]) + (", ..." if len(others) > 3 else "")
            raise SweepStateError(f"{out} holds files that are not a design sweep's ({shown}); "
                                  f"choose a new --out (nothing there is overwritten)")


def run_options(spec: SweepSpec, evaluations: int | None, seed: int | None,
                algorithm: str | None) -> tuple[int, int, str]:
    """(budget, seed, algorithm): the run's options, the sweep file's where not given; checked."""
    budget = spec.evaluations if evaluations is None else evaluations
    if isinstance(budget, bool) or int(budget) != budget or budget < 1:
        raise SweepStateError(f"evaluations = {budget!r}: give a budget of at least 1 evaluation (e.g. 200)")
    algorithm = spec.algorithm if algorithm is None else algorithm
    if algorithm not in ALGORITHMS:
        raise SweepStateError(f"unknown algorithm {algorithm!r}; use one of {', '.join(ALGORITHMS)}")
    seed = spec.seed if seed is None else seed
    if isinstance(seed, bool) or int(seed) != seed or not 0 <= seed < 2**32:
        raise SweepStateError(f"seed = {seed!r}: give a whole number from 0 to {2**32 - 1}")
    return int(budget), int(seed), algorithm


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
    with output_folder(out, check=lambda d: check_sweep_folder(spec, d, seed, algorithm, resume, budget), kind=SWEEP,
                       reuse=True):
        return _run(spec, out, budget, seed, algorithm, resume, client, progress, ctx)


def _run(spec: SweepSpec, out: Path, budget: int, seed: int, algorithm: str, resume: bool, client, progress: bool,
         ctx: EvaluationContext | None) -> SweepResult:
    state_path, log_path, spec_path = out / "state.json", out / "evaluations.csv", out / "sweep.toml"
    ctx = ctx or EvaluationContext.from_spec(spec)
    # Started or resumed alike: the algorithm from its seed; a resume replays it against the log.
    state = SweepState(spec.digest(), algorithm, seed, make_algorithm(algorithm, ctx, seed))
    if not resume:
        spec_path.write_text(dump_spec(spec))
        _write_atomic(state_path, json.dumps({"format": STATE_FORMAT, "digest": state.digest,
                                              "algorithm": algorithm, "seed": seed}).encode())

    # Ship the context (workload arrays) to every worker once per run, not once per batch.
    ctx_remote = ctx if client is None else client.scatter(ctx, broadcast=True)
    rows = _read_log(log_path)
    logged = {(int(r["batch"]), int(r["index"])): r for r in rows}
    if resume and len(logged) > budget:
        raise SweepStateError(f"{out}: the sweep already holds {len(logged)} evaluations, more than the budget of "
                              f"{budget}; resume with --evaluations {len(logged)} or more")
    log = _Log(log_path, next_id=max((int(r["eval_id"]) for r in rows), default=-1) + 1)
    reused = evaluated = 0
    bar = progress_bar(total=budget, desc=f"design {algorithm}", unit="eval", disable=not progress)
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
