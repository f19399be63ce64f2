"""Non-dominance (the paper's Pareto test) and a hypervolume estimate for 7 objectives."""

from __future__ import annotations

import numpy as np


def dominates(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether a dominates b (minimisation): a <= b in every objective and a < b in one.

    a, b : (..., M) objective vectors (broadcast). Returns (...,) bool. Equal vectors do not
    dominate each other, so duplicates are both non-dominated.
    """
    return np.all(a <= b, axis=-1) & np.any(a < b, axis=-1)


def non_dominated(F: np.ndarray, feasible: np.ndarray | None = None, chunk: int = 512) -> np.ndarray:
    """(N,) bool mask of the non-dominated rows of F (N, M), among the feasible ones.

    Infeasible rows are never in the front. O(N^2 M) comparisons, vectorised in chunks; fine
    for the tens of thousands of evaluations a sweep makes.
    """
    F = np.asarray(F, float)
    n = len(F)
    ok = np.ones(n, bool) if feasible is None else np.asarray(feasible, bool).copy()
    idx = np.flatnonzero(ok)
    Ff = F[idx]
    keep = np.ones(len(idx), bool)
    for s in range(0, len(idx), chunk):
        block = Ff[s:s + chunk]
        # dominated[j] if any row dominates block row j
        dom = dominates(Ff[:, None, :], block[None, :, :]).any(axis=0)
        keep[s:s + chunk] = ~dom
    out = np.zeros(n, bool)
    out[idx[keep]] = True
    return out


def normalise(F: np.ndarray, ideal: np.ndarray, nadir: np.ndarray) -> np.ndarray:
    """Scale objectives to [0, 1] between ideal and nadir (constant objectives map to 0)."""
    span = np.where(nadir - ideal > 0, nadir - ideal, 1.0)
    return (F - ideal) / span


def hypervolume_mc(F_norm: np.ndarray, ref: float = 1.1, n_samples: int = 200_000, seed: int = 0,
                   chunk: int = 20_000) -> tuple[float, float]:
    """Monte Carlo hypervolume of normalised points F_norm (N, M) against the reference point
    (ref, ..., ref), over the box [0, ref]^M. Returns (estimate, standard error), in units of
    the normalised box (so 1.1^M is the whole box).

    Exact hypervolume in 7 dimensions is expensive and needs no more precision than this for
    comparing fronts; the same seed gives the same samples, so comparisons are paired.
    """
    F_norm = np.asarray(F_norm, float)
    M = F_norm.shape[1]
    box = ref**M
    pts = F_norm[np.all(F_norm < ref, axis=1)]
    if len(pts) == 0:
        return 0.0, 0.0
    rng = np.random.default_rng(seed)
    hits = 0
    for s in range(0, n_samples, chunk):
        m = min(chunk, n_samples - s)
        u = rng.uniform(0.0, ref, (m, M))
        covered = np.zeros(m, bool)
        for p in pts:
            covered |= np.all(u >= p, axis=1)
        hits += int(covered.sum())
    frac = hits / n_samples
    return frac * box, box * np.sqrt(frac * (1 - frac) / n_samples)
