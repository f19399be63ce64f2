"""Guided search: a few features' matches narrow the rest's search regions.

When the camera's prediction is uncertain (a fast or jerky motion) every feature's search ellipse
is large, and searching all of them costs the frame (on EuRoC's drone, 1.1-1.6 million pixels a
frame against 0.18 million at the median). As in PTAM's coarse stage and Davison's active search,
a few reliable features spread over the image are searched first; their matches, through the
linearised joint Gaussian of all the predicted measurements, give every other feature a
posterior prediction and a smaller ellipse, where it is then searched. Nothing is written to the
state: the frame's update is made afterwards from all the matches against the prior, as
without guidance (measure.Measurement.measure).

The posterior is the Gaussian conditional: for the rest R given the first features' inliers I,
``uv_R' = uv_R + C_RI S_II^-1 nu_I`` and ``S_R' = S_R - C_RI S_II^-1 C_IR`` (its 2 x 2 blocks),
with ``C = H P H^T`` off the diagonal and each feature's own ``S_i`` on it. The inliers are found
as in the 1-point RANSAC: each first match in turn conditions the others, and the one that
agrees with most within ``threshold_px`` wins.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .config import RansacSettings
from .filter import cross_covariance, innovation_nis
from .measurement import Prediction
from .state import State


class GuidedRegions(NamedTuple):
    """The rest's posterior predictions: uv (r, 2) px and S (r, 2, 2) px^2, and which of the
    first matches agreed (k,) bool (the inliers conditioned on)."""

    uv: np.ndarray
    S: np.ndarray
    used: np.ndarray


def first_inliers(J: np.ndarray, S_first: np.ndarray, uv: np.ndarray, z: np.ndarray, threshold_px: float) -> np.ndarray:
    """(k,) bool: the first matches that agree with the best 1-point hypothesis. ``J`` (2k, 2k)
    the first predictions' joint covariance with each ``S_first[i]`` (k, 2, 2) on its diagonal,
    ``uv`` (k, 2) their predictions, ``z`` (k, 2) their matches (NaN: none)."""
    k = len(uv)
    found = np.isfinite(z).all(axis=1)
    hyp = np.flatnonzero(found)
    if not len(hyp):
        return np.zeros(k, bool)
    nu = z[hyp] - uv[hyp]
    det = S_first[hyp, 0, 0] * S_first[hyp, 1, 1] - S_first[hyp, 0, 1] * S_first[hyp, 1, 0]
    ok = det > 0
    hyp, nu, det, Sh = hyp[ok], nu[ok], det[ok], S_first[hyp[ok]]
    if not len(hyp):
        return np.zeros(k, bool)
    # S_i^-1 nu_i in closed form, then each hypothesis's shift of every first prediction.
    w = np.stack([Sh[:, 1, 1] * nu[:, 0] - Sh[:, 0, 1] * nu[:, 1],
                  Sh[:, 0, 0] * nu[:, 1] - Sh[:, 1, 0] * nu[:, 0]], axis=1) / det[:, None]
    cols = J.reshape(2 * k, k, 2)[:, hyp, :]                      # (2k, h, 2)
    shift = np.einsum("rhc,hc->hr", cols, w).reshape(len(hyp), k, 2)
    err = np.linalg.norm(z[None] - (uv[None] + shift), axis=2)    # (h, k); NaN where not found
    agree = found[None] & (err < threshold_px)
    agree[np.arange(len(hyp)), hyp] = True
    return agree[int(np.argmax(agree.sum(axis=1)))]


def _condition(C: np.ndarray, S_II: np.ndarray, nu_I: np.ndarray, S_oo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian conditional of o predicted measurements on matches I: the shift of their
    predictions (o, 2) px, ``C S_II^-1 nu_I``, and their posterior covariances (o, 2, 2) px^2, the
    blocks of ``S_oo - C S_II^-1 C^T``. ``C`` (2o, 2i) their cross-covariance with I, ``S_II``
    (2i, 2i), ``nu_I`` (2i,) the matches' innovations, ``S_oo`` (o, 2, 2) their prior blocks.
    Raises LinAlgError for a singular ``S_II``."""
    X = np.linalg.solve(S_II, np.column_stack([nu_I, C.T]))
    o = len(S_oo)
    shift = (C @ X[:, 0]).reshape(o, 2)
    return shift, S_oo - np.einsum("rai,rbi->rab", C.reshape(o, 2, -1), X[:, 1:].T.reshape(o, 2, -1))


def _pairs(idx: np.ndarray) -> np.ndarray:
    """The (u, v) rows (2n,) of the features ``idx`` (n,) in a (2k, ...) stacked matrix."""
    return np.ravel(np.column_stack([2 * idx, 2 * idx + 1]))


def _rescued(J: np.ndarray, uv: np.ndarray, z: np.ndarray, inl: np.ndarray, chi2: float) -> np.ndarray:
    """(k,) bool: the found first matches outside ``inl`` within ``chi2`` of their prediction
    given the inliers' matches (the RANSAC's rescue of high-innovation inliers)."""
    out = np.zeros(len(uv), bool)
    others = np.flatnonzero(np.isfinite(z).all(axis=1) & ~inl)
    if not len(others):
        return out
    given = np.flatnonzero(inl)
    gi, oi = _pairs(given), _pairs(others)
    S_oo = np.stack([J[2 * j:2 * j + 2, 2 * j:2 * j + 2] for j in others])
    try:
        shift, cov = _condition(J[np.ix_(oi, gi)], J[np.ix_(gi, gi)], (z[given] - uv[given]).reshape(-1), S_oo)
    except np.linalg.LinAlgError:
        return out
    nu = z[others] - (uv[others] + shift)
    out[others] = innovation_nis(nu, cov) < chi2
    return out


def guided_regions(state: State, pred: Prediction, S: np.ndarray, first: np.ndarray, z_first: np.ndarray,
                   ransac: RansacSettings, floor_px: float, min_inliers: int = 3) -> GuidedRegions | None:
    """The posterior predictions of the features of ``pred`` (m) not in ``first`` (k indices),
    given the first ones' matches ``z_first`` (k, 2) px (NaN: not found); ``S`` (m, 2, 2) px^2 the
    prior innovation covariances (with each feature's noise). The first matches' inliers are
    chosen as the 1-point RANSAC does (``ransac``: its threshold, then its rescue gate for the
    others once conditioned on those). ``floor_px`` is added in quadrature
    to each posterior ellipse's axes (the linearisation's error). None when fewer than
    ``min_inliers`` first matches agree: the rest keep their prior regions."""
    m = len(pred.ks)
    first = np.asarray(first, np.intp)
    rest = np.setdiff1d(np.arange(m), first)
    pf, pr = pred.take(first), pred.take(rest)
    J = cross_covariance(state, pf, pf)
    k = len(first)
    for i in range(k):
        J[2 * i:2 * i + 2, 2 * i:2 * i + 2] = S[first[i]]
    if not np.isfinite(J).all():
        return None
    inl = first_inliers(J, S[first], pf.uv, z_first, ransac.threshold_px)
    if inl.sum() < 2:
        return None
    inl = inl | _rescued(J, pf.uv, z_first, inl, ransac.rescue_chi2)
    if inl.sum() < min_inliers:
        return None
    rows = _pairs(np.flatnonzero(inl))
    C_RI = cross_covariance(state, pr, pf)[:, rows]            # (2r, 2i)
    try:
        shift, S_post = _condition(C_RI, J[np.ix_(rows, rows)], (z_first[inl] - pf.uv[inl]).reshape(-1), S[rest])
    except np.linalg.LinAlgError:
        return None
    uv = pr.uv + shift
    S_post = S_post + floor_px ** 2 * np.eye(2)
    det = S_post[:, 0, 0] * S_post[:, 1, 1] - S_post[:, 0, 1] * S_post[:, 1, 0]
    bad = ~(np.isfinite(uv).all(axis=1) & (S_post[:, 0, 0] > 0) & (det > 0))
    uv[bad], S_post[bad] = pr.uv[bad], S[rest][bad]            # kept at the prior
    return GuidedRegions(uv, S_post, inl)
