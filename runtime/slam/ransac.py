"""1-point RANSAC for the EKF (Civera, Grasa, Davison and Montiel, "1-Point RANSAC for Extended
Kalman Filtering: Application to Real-Time Structure from Motion and Visual Odometry", JFR 2010).

The matches come from the active search, each inside its own 3-sigma ellipse (individually
compatible), yet some are wrong: a repeated texture, a patch on an occluding contour whose
background slides. With the EKF prior, one match is enough to hypothesise the whole state:

1. for a match ``j``, update the mean only, ``x_j = x + K_j (z_j - h_j(x))`` with
   ``K_j = P H_j^T S_j^-1``; predict every other match from ``x_j``; its support is the matches
   within ``threshold_px`` (the low-innovation inliers). The best-supported hypothesis wins;
   the number of hypotheses adapts to the inlier ratio found, ``log(1 - p) / log(1 - w)``;
2. a full EKF update with the low-innovation inliers;
3. each remaining match is predicted again with the updated mean and covariance and rescued
   when its innovation passes the chi-square gate (high-innovation inliers); a second update
   with those.

Here every match is a possible hypothesis and there are tens of them, so the hypotheses are the
matches in a seeded random order, at most ``max_hypotheses`` of them.

A hypothesis's support may weigh its inliers (``votes``): the caller gives each match the chance
that its feature's matches are true ones. New features whose depths are still guesses sit
close together in the image's empty parts and can agree, as a cluster, on a wrong motion that
outnumbers fewer established points spread over the image; weighted, the established points'
consensus wins. The sampling and the adaptive count are Civera et al.'s, by matches.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args

from .features import FEATURE_DIMS
from .filter import FrameUpdate, gather_jacobian, innovation_nis
from .kernels import compiled_kernel
from .measurement import Prediction, h_feature_kernel
from .quaternion import rotation_derivatives_kernel, rotation_kernel
from .config import RansacSettings
from .state import POSE_DIM, SlamNumericalError, State


@dataclass
class RansacResult:
    """Per match (m,): ``low`` (a low-innovation inlier of the best hypothesis), ``rescued``
    (a high-innovation inlier), ``used`` (either, and its update was applied); and the counts."""

    low: np.ndarray
    rescued: np.ndarray
    used: np.ndarray
    hypotheses: int
    refused: bool = False      # the caller's ``accept`` turned the posterior down: nothing applied

    @property
    def n_inliers(self) -> int:
        return int(self.used.sum())

    @property
    def n_outliers(self) -> int:
        return int((~self.used).sum())


@compiled_kernel(h_feature_kernel, rotation_kernel, rotation_derivatives_kernel, gather_jacobian)
def _hypotheses_kernel(x, P, kinds, starts, anchors, dims, ks, z, uv0, H_c, H_f, S, order, threshold, max_hyp,
                       confidence, votes, model, lens):
    """The best 1-point hypothesis's inlier mask (m,) and the number of hypotheses tried: the
    most ``votes`` (m,) among its inliers, then the least cost."""
    n = x.shape[0]
    m = ks.shape[0]
    best = np.zeros(m, dtype=np.bool_)
    best_support = -1.0
    best_cost = np.inf
    n_hyp = max_hyp
    tried = 0
    xj = np.empty(n)
    idx = np.empty(13, np.intp)
    h = np.zeros((2, 13))
    uv = np.empty(2)
    Hc_tmp = np.empty((2, POSE_DIM))
    Hf_tmp = np.empty((2, 6))
    inl = np.zeros(m, dtype=np.bool_)
    th2 = threshold * threshold
    for t in range(order.shape[0]):
        if tried >= n_hyp:
            break
        tried += 1
        j = order[t]
        c = gather_jacobian(j, ks, kinds, starts, dims, H_c, H_f, idx, h)
        # K_j nu_j = P H^T S^-1 nu_j
        s00, s01, s11 = S[j, 0, 0], S[j, 0, 1], S[j, 1, 1]
        det = s00 * s11 - s01 * s01
        if not det > 0:
            continue
        nu0, nu1 = z[j, 0] - uv0[j, 0], z[j, 1] - uv0[j, 1]
        w0 = (s11 * nu0 - s01 * nu1) / det
        w1 = (-s01 * nu0 + s00 * nu1) / det
        for r in range(n):
            acc = 0.0
            for u in range(c):
                acc += P[r, idx[u]] * (h[0, u] * w0 + h[1, u] * w1)
            xj[r] = x[r] + acc
        R = rotation_kernel(xj[3], xj[4], xj[5], xj[6])
        dR = rotation_derivatives_kernel(xj[3], xj[4], xj[5], xj[6])
        count = 0
        support = 0.0
        cost = 0.0
        for i in range(m):
            ki = ks[i]
            ok = h_feature_kernel(kinds[ki], xj, starts[ki], anchors[ki], R, dR, model, lens, uv, Hc_tmp, Hf_tmp)
            e2 = (z[i, 0] - uv[0]) ** 2 + (z[i, 1] - uv[1]) ** 2 if ok else np.inf
            inl[i] = e2 < th2
            if inl[i]:
                count += 1
                support += votes[i]
                cost += e2
            else:
                cost += th2
        if support > best_support or (support == best_support and cost < best_cost):
            best_support = support
            best_cost = cost
            best[:] = inl
            w = count / m
            if w >= 1.0:
                n_hyp = tried
            elif w > 0:
                n_hyp = min(max_hyp, int(math.ceil(math.log(1.0 - confidence) / math.log(1.0 - w))))
    return best, tried


def one_point_ransac(state: State, ks: np.ndarray, z: np.ndarray, cam: CameraIntrinsics, R_pix,
                     pred: Prediction, S: np.ndarray, settings: RansacSettings, rng: np.random.Generator,
                     r_scale: np.ndarray | None = None, votes: np.ndarray | None = None,
                     accept: Callable[[FrameUpdate], bool] | None = None) -> RansacResult:
    """Select the inliers among the matches ``z`` (m, 2) px of the distinct features ``ks`` and
    update the state with them, in place (the three steps of the module docstring).

    ``settings`` : the hypotheses' threshold, number and confidence, and the rescue gate.
    ``pred``, ``S`` : the features' predictions and innovation covariances at the prior (the
    ones the search used). ``r_scale`` (m,) or (m, 2, 2) : each measurement's noise as a multiple
    of ``R_pix`` (filter.measurement_noise; default 1). ``votes`` (m,) : what each match's agreement counts for in choosing
    the hypothesis (default 1 each). An update refused for numerical reasons leaves the state as it was
    and its matches unused. ``accept`` : shown the frame's updates before they are written (the
    posterior mean ``x`` and variances of the FrameUpdate); False leaves the state as it was,
    with ``refused`` set.
    """
    ks = np.asarray(ks, np.intp)
    m = len(ks)
    r_scale = np.ones(m) if r_scale is None else np.asarray(r_scale, float)
    votes = np.ones(m) if votes is None else np.ascontiguousarray(votes, float).reshape(m)
    if not (np.isfinite(votes).all() and (votes > 0).all()):
        raise ValueError("one_point_ransac: votes must be finite and positive")
    low = np.zeros(m, bool)
    rescued = np.zeros(m, bool)
    if m == 0:
        return RansacResult(low, rescued, low.copy(), 0)
    model, lens = lens_kernel_args(cam)
    order = rng.permutation(m).astype(np.intp)
    low, tried = _hypotheses_kernel(state.x, state.P, state.kinds, state.starts, state.anchors, FEATURE_DIMS, ks,
                                    np.ascontiguousarray(z, float), np.ascontiguousarray(pred.uv),
                                    np.ascontiguousarray(pred.H_c), np.ascontiguousarray(pred.H_f),
                                    np.ascontiguousarray(S), order, float(settings.threshold_px),
                                    int(settings.max_hypotheses), float(settings.confidence), votes, model, lens)
    if m == 1:
        low[:] = True                              # one match inside its own ellipse: nothing to vote
    used = np.zeros(m, bool)
    fu = FrameUpdate(state, cam, R_pix)
    if low.any():
        sel = np.flatnonzero(low)
        sub = pred.take(sel)
        try:
            fu.update(ks[sel], z[sel], sub, r_scale[sel])
            used[sel] = True
        except SlamNumericalError:
            return RansacResult(low, rescued, used, tried)
    rest = np.flatnonzero(~low)
    if len(rest) and used.any():
        p2 = fu.predict(ks[rest])
        S2 = fu.innovation_covariances(p2, r_scale[rest])
        nu = z[rest] - p2.uv
        ok = p2.valid & np.isfinite(S2).all(axis=(1, 2))
        d2 = np.where(ok, innovation_nis(np.ascontiguousarray(nu), S2), np.inf)
        good = ok & (d2 < settings.rescue_chi2)
        if good.any():
            sel = rest[good]
            sub = p2.take(good)
            try:
                fu.update(ks[sel], z[sel], sub, r_scale[sel])
                rescued[sel] = True
                used[sel] = True
            except SlamNumericalError:
                pass
    if accept is not None and used.any() and not accept(fu):
        return RansacResult(low, rescued, np.zeros(m, bool), tried, refused=True)
    try:
        fu.commit()
    except SlamNumericalError:
        used[:] = False
        rescued[:] = False
    return RansacResult(low, rescued, used, tried)
