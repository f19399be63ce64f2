"""Non-dominance (the paper's Pareto test) and the hypervolume of a front, by pymoo and moocore."""

from __future__ import annotations

import numpy as np

#: Fronts up to this many points get moocore's exact hypervolume; larger ones its deterministic
#: approximation (exact 7-objective hypervolume grows steeply: ~0.5 s at 100 points, ~30 s at 300).
EXACT_HV_POINTS = 120
#: Samples of moocore's approximation (Rphi-FWE+; relative error ~1e-4 on 7-objective fronts).
APPROX_HV_SAMPLES = 2**18


def dominates(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether a dominates b (minimisation): a <= b in every objective and a < b in one.

    a, b : (..., M) objective vectors (broadcast). Returns (...,) bool. Equal vectors do not
    dominate each other, so duplicates are both non-dominated.
    """
    return np.all(a <= b, axis=-1) & np.any(a < b, axis=-1)


def non_dominated(F: np.ndarray, feasible: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool mask of the non-dominated rows of F (N, M), among the feasible ones.

    Infeasible rows are never in the front; duplicates of a front point are all in it. pymoo's
    find_non_dominated does the sorting.
    """
    from pymoo.util.nds.non_dominated_sorting import find_non_dominated

    F = np.asarray(F, float)
    ok = np.ones(len(F), bool) if feasible is None else np.asarray(feasible, bool)
    idx = np.flatnonzero(ok)
    out = np.zeros(len(F), bool)
    if len(idx):
        out[idx[np.asarray(find_non_dominated(F[idx]), int)]] = True
    return out


def normalise(F: np.ndarray, ideal: np.ndarray, nadir: np.ndarray) -> np.ndarray:
    """Scale objectives to [0, 1] between ideal and nadir (constant objectives map to 0)."""
    span = np.where(nadir - ideal > 0, nadir - ideal, 1.0)
    return (F - ideal) / span


def hypervolume(F_norm: np.ndarray, ref: float = 1.1) -> tuple[float, bool]:
    """Hypervolume of normalised points F_norm (N, M) against (ref, ..., ref), in units of the
    normalised box (so ref**M is the whole box [0, ref]^M), and whether it is exact.

    moocore's exact algorithm up to EXACT_HV_POINTS points that dominate the reference point,
    its deterministic approximation beyond. Points not below the reference add nothing.
    """
    import moocore

    F_norm = np.asarray(F_norm, float)
    pts = F_norm[np.all(F_norm < ref, axis=1)]
    if len(pts) == 0:
        return 0.0, True
    r = np.full(F_norm.shape[1], float(ref))
    if len(pts) <= EXACT_HV_POINTS:
        return float(moocore.hypervolume(pts, ref=r)), True
    return float(moocore.hv_approx(pts, ref=r, nsamples=APPROX_HV_SAMPLES)), False
