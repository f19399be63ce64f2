"""How fast a sweep converges: the share of a baseline's budget it needs to match the baseline.

The measure of issue 48: given the evaluations of an algorithm and of a baseline (the paper's
random variation), both over the same sweep, the baseline's hypervolume after ``at``
evaluations is the target, and the fraction is the smallest prefix of the algorithm's
evaluations whose feasible front reaches it, divided by ``at``. Both fronts are normalised on
the ideal and nadir of the union of both runs' feasible fronts (``at`` evaluations each),
reference point 1.1 in every objective, so the two hypervolumes are on one scale.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .pareto import hypervolume, non_dominated, normalise
from .sweep_file import CONSTRAINTS, CRITERIA


@dataclass(frozen=True)
class Convergence:
    """fraction : evaluations the algorithm needed / ``at`` (inf if it never reached the target).
    needed : that number of evaluations. target : the baseline's hypervolume at ``at``. reached :
    the algorithm's at ``at``. exact : whether every hypervolume was exact."""

    fraction: float
    needed: int | None
    at: int
    target: float
    reached: float
    exact: bool


def read_evaluations(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(F (n, 7), feasible (n,)) of an evaluations.csv, in evaluation order (batch, index)."""
    path = Path(path)
    if path.is_dir():
        path = path / "evaluations.csv"
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or any(c not in rows[0] for c in CRITERIA + CONSTRAINTS):
        raise ValueError(f"{path}: not a design sweep's evaluations.csv (no rows, or columns missing)")
    rows.sort(key=lambda r: (int(r["batch"]), int(r["index"])))
    F = np.array([[float(r[c]) for c in CRITERIA] for r in rows])
    G = np.array([[float(r[c]) for c in CONSTRAINTS] for r in rows])
    return F, np.all(G <= 0, axis=1)


def fraction_to_match(F_alg, feasible_alg, F_base, feasible_base, at: int = 2520) -> Convergence:
    """The fraction of ``at`` evaluations the algorithm needs to reach the baseline's hypervolume."""
    if len(F_alg) < at or len(F_base) < at:
        raise ValueError(f"both runs need at least {at} evaluations (have {len(F_alg)} and {len(F_base)})")
    Fa, fa = np.asarray(F_alg[:at]), np.asarray(feasible_alg[:at], bool)
    Fb, fb = np.asarray(F_base[:at]), np.asarray(feasible_base[:at], bool)
    fronts = [Fa[non_dominated(Fa, fa)], Fb[non_dominated(Fb, fb)]]
    union = np.vstack(fronts)
    if len(union) == 0:
        raise ValueError("neither run has a feasible design")
    ideal, nadir = union.min(axis=0), union.max(axis=0)

    exact = True

    def hv_prefix(n: int) -> float:
        nonlocal exact
        P = Fa[:n][non_dominated(Fa[:n], fa[:n])]
        h, e = hypervolume(normalise(P, ideal, nadir), 1.1)
        exact &= e
        return h

    target, e = hypervolume(normalise(fronts[1], ideal, nadir), 1.1)
    exact &= e
    reached = hv_prefix(at)
    if reached < target:
        return Convergence(float("inf"), None, at, target, reached, exact)
    lo, hi = 0, at          # hv_prefix is non-decreasing in n: bisect for the first n reaching the target
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if hv_prefix(mid) >= target:
            hi = mid
        else:
            lo = mid
    return Convergence(hi / at, hi, at, target, reached, exact)
