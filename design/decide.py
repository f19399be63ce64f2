"""Choosing one design from the front, by pymoo's decision-making tools.

``pseudo-weights`` (default): each design's pseudo-weight vector is its normalised distance
from the worst value in each objective, normalised to sum to one; the design whose
pseudo-weights are closest (L1) to the sweep's ``[decision].weights`` is chosen. Equal weights
pick a balanced design; a larger weight favours that criterion.

``knee``: pymoo's high trade-off points (designs whose neighbours all trade a lot of one
criterion for little of another); among several, the one nearest the ideal point in
normalised objectives; with none, fall back to pseudo-weights.

Objectives constant over the front carry no information and are left out of the decision.
"""

from __future__ import annotations

import numpy as np
from pymoo.mcdm.high_tradeoff import HighTradeoffPoints
from pymoo.mcdm.pseudo_weights import PseudoWeights

from .pareto import normalise


def choose_design(F_front: np.ndarray, method: str = "pseudo-weights", weights=None) -> tuple[int, str]:
    """Index into F_front (n, M) of the chosen design, and a sentence saying how it was chosen."""
    F = np.asarray(F_front, float)
    if len(F) == 0:
        raise ValueError("the front is empty: no feasible design was found; widen the bounds or raise the budget")
    if len(F) == 1:
        return 0, "the front holds a single design"
    M = F.shape[1]
    w = np.ones(M) if weights is None else np.asarray(weights, float)
    varying = F.max(axis=0) > F.min(axis=0)
    if not varying.any():
        return 0, "all designs on the front score the same"
    Fv, wv = F[:, varying], w[varying]
    if method == "knee":
        knees = HighTradeoffPoints().do(Fv)
        if knees is not None and len(np.atleast_1d(knees)) > 0:
            knees = np.atleast_1d(knees)
            Fn = normalise(Fv, Fv.min(axis=0), Fv.max(axis=0))
            best = int(knees[np.argmin(np.linalg.norm(Fn[knees], axis=1))])
            return best, f"knee point (pymoo high trade-off points: {len(knees)} found; nearest the ideal chosen)"
        method_note = "no knee point found; "
    elif method == "pseudo-weights":
        method_note = ""
    else:
        raise ValueError(f"decision method {method!r} must be 'pseudo-weights' or 'knee'")
    if wv.sum() <= 0:
        wv = np.ones_like(wv)
    idx = int(PseudoWeights(wv / wv.sum()).do(Fv))
    return idx, f"{method_note}pseudo-weights closest to the sweep's weights {np.round(w, 3).tolist()}"
