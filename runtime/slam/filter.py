"""The EKF's measurement steps over the map: each measured feature's innovation covariance (its
search ellipse), the batch update with any set of features, and adding and converting
features with their full cross-covariance.

The measurement of feature ``k`` depends only on the camera pose (r, q: 7 numbers) and on the
feature's own parameters, so each 2-row block of ``H`` has at most 13 nonzero columns; the
update never forms dense rows of ``H`` (compiled kernels apply its blocks). With
``S = H P H^T + R = L L^T`` (Cholesky) and ``U = P H^T L^-T`` (n, 2m), the update is::

    x <- x + U (L^-1 nu)            (= x + K nu, K = P H^T S^-1)
    P <- P - U U^T                  (= P - K S K^T, a symmetric rank-2m downdate)

then ``q`` is renormalised with its Jacobian and the guard runs. A frame's batches
(:class:`FrameUpdate`) keep ``U`` and form ``P`` once. Pixel covariances ``R_pix`` are
px^2: a scalar variance or (2, 2), the same for every measurement.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.linalg

from kinematics.camera import CameraIntrinsics

from .features import FEATURE_DIMS, INVERSE_DEPTH, POINT
from .features import inverse_depth
from .kernels import compiled_kernel
from .measurement import Prediction, init_point_from_depth, predict
from .motion import apply_quaternion_jacobian
from .quaternion import normalise_quaternion_jacobian
from .state import POSE_DIM, Q_SLICE, TD_INDEX, SlamNumericalError, State, check_covariance, check_mean, mirror_upper

__all__ = ["FeatureNotMeasurable", "UpdateResult", "FrameUpdate", "innovation_covariances", "innovation_nis", "update",
           "add_inverse_depth_feature",
           "add_point_feature", "convert_to_point", "point_conversions"]


class FeatureNotMeasurable(ValueError):
    """A feature asked to be measured has no predicted image point, or its measurement is NaN/Inf."""


class UpdateResult(NamedTuple):
    """What :func:`update` returns: innovations nu (m, 2) px, their covariance S (2m, 2m) px^2
    (measurement i: rows 2i, 2i+1) and the predictions uv (m, 2) px."""

    nu: np.ndarray
    S: np.ndarray
    uv: np.ndarray

    @property
    def nis(self) -> float:
        """Normalised innovation squared ``nu^T S^-1 nu`` (chi-square with 2m dof)."""
        v = self.nu.reshape(-1)
        return float(v @ np.linalg.solve(self.S, v))


def pixel_covariance(R_pix) -> np.ndarray:
    R = np.asarray(R_pix, dtype=float)
    if R.ndim == 0:
        R = float(R) * np.eye(2)
    if R.shape != (2, 2) or not np.isfinite(R).all():
        raise ValueError(f"R_pix must be a finite scalar variance or a (2, 2) covariance in px^2, got {np.shape(R_pix)}")
    return R


@compiled_kernel()
def gather_jacobian(i, ks, kinds, starts, dims, H_c, H_f, idx, h):
    """Measurement ``i``'s two rows of H as dense (2, c) ``h`` over the state entries ``idx[:c]``
    (the camera's 7, then its feature's dim); returns c."""
    k = ks[i]
    d = dims[kinds[k]]
    for j in range(POSE_DIM):
        idx[j] = j
        h[0, j] = H_c[i, 0, j]
        h[1, j] = H_c[i, 1, j]
    for j in range(d):
        idx[POSE_DIM + j] = starts[k] + j
        h[0, POSE_DIM + j] = H_f[i, 0, j]
        h[1, POSE_DIM + j] = H_f[i, 1, j]
    return POSE_DIM + d


@compiled_kernel(gather_jacobian)
def _innovation_kernel(P, kinds, starts, dims, ks, H_c, H_f, Rn):
    """S_i (m, 2, 2) = H_i P_i H_i^T + Rn_i over the (7 + dim) state entries each touches."""
    m = ks.shape[0]
    S = np.empty((m, 2, 2))
    idx = np.empty(13, np.intp)
    h = np.zeros((2, 13))
    for i in range(m):
        c = gather_jacobian(i, ks, kinds, starts, dims, H_c, H_f, idx, h)
        for a in range(2):
            for b in range(a, 2):
                acc = Rn[i, a, b]
                for u in range(c):
                    hu = h[a, u]
                    if hu == 0.0:
                        continue
                    row = idx[u]
                    t = 0.0
                    for w in range(c):
                        t += P[row, idx[w]] * h[b, w]
                    acc += hu * t
                S[i, a, b] = acc
        S[i, 1, 0] = S[i, 0, 1]
    return S


def measurement_noise(R: np.ndarray, r_scale, m: int) -> np.ndarray:
    """(m, 2, 2) each measurement's noise covariance, px^2, from the pixel covariance ``R``
    (2, 2) and ``r_scale``: None (``R`` each), (m,) multiples of ``R``, or (m, 2, 2) shapes
    ``A_i`` in ``R``'s units (``L A_i L^T``, ``R = L L^T``)."""
    if r_scale is None:
        return np.broadcast_to(R, (m, 2, 2)).copy()
    s = np.asarray(r_scale, float)
    if s.ndim <= 1 and s.size == m:
        s = s.reshape(m)
        if not (np.isfinite(s).all() and (s > 0).all()):
            raise ValueError("measurement noise scales must be finite and positive")
        return s[:, None, None] * R
    if s.shape != (m, 2, 2):
        raise ValueError(f"measurement noise shapes must be (m,) or (m, 2, 2), got {s.shape} for m = {m}")
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    if m and not ((s[:, 0, 0] > 0) & (det > 0) & (det < np.inf)).all():      # NaN fails them too
        raise ValueError("measurement noise shapes must be finite and positive definite")
    if R[0, 1] == 0.0 and R[1, 0] == 0.0 and R[0, 0] == R[1, 1]:
        return R[0, 0] * s                        # isotropic: L A L^T = sigma^2 A
    L = np.linalg.cholesky(R)
    return np.ascontiguousarray(L @ s @ L.T)


def innovation_covariances(state: State, pred: Prediction, R_pix, r_scale=None) -> np.ndarray:
    """(m, 2, 2) px^2: each predicted feature's own innovation covariance
    ``H_i P H_i^T + r_scale_i R`` (its search ellipse); NaN for features with no image.
    ``r_scale`` (m,) or (m, 2, 2) : each measurement's noise as a multiple of ``R_pix``
    (:func:`measurement_noise`; default 1)."""
    R = pixel_covariance(R_pix)
    S = _innovation_kernel(state.P, state.kinds, state.starts, FEATURE_DIMS, pred.ks, pred.H_c, pred.H_f,
                           measurement_noise(R, r_scale, len(pred.ks)))
    if pred.H_t is not None and len(pred.ks):
        c = _h_times_kernel(np.ascontiguousarray(state.P[:, TD_INDEX:TD_INDEX + 1]), state.kinds, state.starts,
                            FEATURE_DIMS, pred.ks, pred.H_c, pred.H_f)
        _add_time_offset_terms(S, pred.H_t, c.reshape(-1, 2), float(state.P[TD_INDEX, TD_INDEX]))
    S[~pred.valid] = np.nan
    return S


def cross_covariance(state: State, pred_a: Prediction, pred_b: Prediction) -> np.ndarray:
    """``H_a P H_b^T`` (2 m_a, 2 m_b) px^2: the cross-covariance of two sets of predicted
    measurements (no measurement noise; rows and columns in (u, v) pairs per feature)."""
    HbP = _h_times_kernel(state.P, state.kinds, state.starts, FEATURE_DIMS, pred_b.ks, pred_b.H_c, pred_b.H_f)
    return _h_times_kernel(np.ascontiguousarray(HbP.T), state.kinds, state.starts, FEATURE_DIMS, pred_a.ks,
                           pred_a.H_c, pred_a.H_f)


@compiled_kernel()
def innovation_nis(nu, S):
    """(m,) each innovation's ``nu_i^T S_i^-1 nu_i`` for nu (m, 2) px and S (m, 2, 2) px^2
    (closed form); inf where ``S_i`` is not positive definite or not finite."""
    m = nu.shape[0]
    d2 = np.empty(m)
    for i in range(m):
        a, b, c = S[i, 0, 0], 0.5 * (S[i, 0, 1] + S[i, 1, 0]), S[i, 1, 1]
        det = a * c - b * b
        if not (a > 0.0 and det > 0.0):
            d2[i] = np.inf
            continue
        x, y = nu[i, 0], nu[i, 1]
        d2[i] = (c * x * x - 2.0 * b * x * y + a * y * y) / det
    return d2


def _add_time_offset_terms(S: np.ndarray, H_t: np.ndarray, c: np.ndarray, P_tt: float) -> None:
    """S_i += u c^T + c u^T + P_tt u u^T in place: the clock offset's column of H_i (``u`` =
    H_t[i], (2,)), with ``c`` (m, 2) the rest of H_i times P's clock-offset column."""
    uc = H_t[:, :, None] * c[:, None, :]
    S += uc + np.swapaxes(uc, 1, 2) + P_tt * H_t[:, :, None] * H_t[:, None, :]


@compiled_kernel()
def _pht_kernel(P, U, r, kinds, starts, dims, ks, H_c, H_f):
    """``P H^T`` (n, 2m) for the measurements of features ``ks`` under ``P = P0 - U U^T``
    (``U`` (n, >= r), its first ``r`` columns in use), touching only the (7 + dim) columns of
    ``P0`` each row pair of H has (read as rows: the state keeps ``P0`` exactly symmetric), and
    ``H U`` (2m, r)."""
    n = P.shape[0]
    m = ks.shape[0]
    PHt = np.zeros((n, 2 * m))
    HU = np.zeros((2 * m, r))
    for i in range(m):
        k = ks[i]
        d = dims[kinds[k]]
        s = starts[k]
        for a in range(2):
            col = 2 * i + a
            for u in range(POSE_DIM + d):
                h = H_c[i, a, u] if u < POSE_DIM else H_f[i, a, u - POSE_DIM]
                if h == 0.0:
                    continue
                j = u if u < POSE_DIM else s + u - POSE_DIM
                for row in range(n):
                    PHt[row, col] += P[j, row] * h
                for c in range(r):
                    HU[col, c] += h * U[j, c]
    return PHt, HU


@compiled_kernel()
def _h_times_kernel(A, kinds, starts, dims, ks, H_c, H_f):
    """``H A`` (2m, q) for a matrix ``A`` (n, q) whose rows are state entries."""
    m = ks.shape[0]
    q = A.shape[1]
    out = np.zeros((2 * m, q))
    for i in range(m):
        k = ks[i]
        d = dims[kinds[k]]
        s = starts[k]
        for a in range(2):
            for u in range(POSE_DIM + d):
                h = H_c[i, a, u] if u < POSE_DIM else H_f[i, a, u - POSE_DIM]
                if h == 0.0:
                    continue
                j = u if u < POSE_DIM else s + u - POSE_DIM
                for c in range(q):
                    out[2 * i + a, c] += h * A[j, c]
    return out


@compiled_kernel()
def _lower_inverse(L):
    """L^-1 of a lower-triangular ``L`` (k, k) with a positive diagonal (forward substitution)."""
    k = L.shape[0]
    Linv = np.zeros((k, k))
    for c in range(k):
        Linv[c, c] = 1.0 / L[c, c]
        for i in range(c + 1, k):
            acc = 0.0
            for j in range(c, i):
                acc += L[i, j] * Linv[j, c]
            Linv[i, c] = -acc / L[i, i]
    return Linv


@compiled_kernel()
def _batch_kernel(P, U, r, x, kinds, starts, dims, ks, H_c, H_f, u, td, Rn, nu):
    """One batch of :class:`FrameUpdate` in a single call: ``S`` (2m, 2m), ``U_new = P H^T
    L^-T`` (n, 2m) and the new mean ``x + U_new L^-1 nu``, under ``P = P0 - U U^T`` (``U``
    (n, r)); ``u`` (2m,) H's column of the clock offset at index ``td`` (empty without one).
    Returns ok = False (and nothing else valid) when ``S`` is not finite or not positive
    definite."""
    n = P.shape[0]
    PHt, HU = _pht_kernel(P, U, r, kinds, starts, dims, ks, H_c, H_f)
    mm = PHt.shape[1]
    if u.shape[0]:
        for row in range(n):
            p = P[row, td]
            for c in range(mm):
                PHt[row, c] += p * u[c]
        for c in range(mm):
            for j in range(r):
                HU[c, j] += u[c] * U[td, j]
    if r:
        PHt -= np.dot(U, HU.T)
    S = _h_times_kernel(PHt, kinds, starts, dims, ks, H_c, H_f)
    if u.shape[0]:
        for a in range(mm):
            for b in range(mm):
                S[a, b] += u[a] * PHt[td, b]
    for a in range(mm):
        for b in range(a + 1, mm):
            v = 0.5 * (S[a, b] + S[b, a])
            S[a, b] = v
            S[b, a] = v
    for i in range(mm // 2):
        for a in range(2):
            for b in range(2):
                S[2 * i + a, 2 * i + b] += Rn[i, a, b]
    empty = np.zeros((0, 0))
    if not np.isfinite(S).all():
        return False, S, empty, x
    for a in range(mm):                     # Cholesky's own test: a pivot that is not positive
        if not S[a, a] > 0.0:
            return False, S, empty, x
    L = np.linalg.cholesky(S)
    Linv = _lower_inverse(L)
    U_new = np.dot(PHt, Linv.T)
    return True, S, U_new, x + np.dot(U_new, np.dot(Linv, nu))


@compiled_kernel()
def _commit_check_kernel(P, U, J):
    """Everything :meth:`FrameUpdate.commit`'s guard needs before ``P`` is touched: the
    quaternion's rows (4, n) of ``J (P - U U^T) J'`` (T: the identity but ``J`` on the
    quaternion's block, which it keeps exactly symmetric), and whether ``U`` and those rows are
    finite and no new variance is negative beyond rounding (1e-9 of the largest)."""
    n, k = U.shape
    q0 = Q_SLICE.start
    A = np.empty((4, n))                    # P's quaternion rows less U U^T's
    for a in range(4):
        for c in range(n):
            acc = 0.0
            for j in range(k):
                acc += U[q0 + a, j] * U[c, j]
            A[a, c] = P[q0 + a, c] - acc
    rows = np.dot(J, A)
    qq = np.dot(np.ascontiguousarray(rows[:, q0:q0 + 4]), J.T)
    for a in range(4):
        for b in range(4):
            rows[a, q0 + b] = 0.5 * (qq[a, b] + qq[b, a])
    healthy = np.isfinite(rows).all()
    d_max = 0.0
    d_min = np.inf
    for i in range(n):
        if q0 <= i < q0 + 4:
            d = rows[i - q0, i]
        else:
            acc = 0.0
            for j in range(k):
                healthy &= np.isfinite(U[i, j])
                acc += U[i, j] * U[i, j]
            d = P[i, i] - acc
        d_max = max(d_max, d)
        d_min = min(d_min, d)
    for a in range(4):
        for j in range(k):
            healthy &= np.isfinite(U[q0 + a, j])
    return rows, healthy and d_min >= -1e-9 * max(d_max, 2.2250738585072014e-308)


@compiled_kernel(mirror_upper)
def _mirror_and_set_quaternion_rows(P, rows):
    """After the rank update of P's upper triangle (read in C order): mirror it, then write the
    quaternion's ``rows`` (4, n) and their transposes."""
    mirror_upper(P)
    q0 = Q_SLICE.start
    n = P.shape[0]
    for a in range(4):
        for c in range(n):
            P[q0 + a, c] = rows[a, c]
            P[c, q0 + a] = rows[a, c]


_NO_COLUMN = np.zeros(0)


class FrameUpdate:
    """A frame's EKF updates (one or several batches, e.g. the 1-point RANSAC's low-innovation
    inliers and then its rescued ones), with the covariance kept factored as
    ``P = P0 - U U^T`` until :meth:`commit` forms it once (one symmetric rank update).

    Each batch: ``P H^T = P0 H^T - U (H U)^T`` (H touches 7 + dim columns per measurement),
    ``S = H P H^T + R = L L^T``, ``U_new = P H^T L^-T``, ``x += U_new L^-1 nu``, ``U <- [U U_new]``.
    The mean's quaternion is renormalised after every batch; the covariance's normalisation
    Jacobian is applied once, at commit. Until then the :class:`State` is untouched (read the
    current mean from :attr:`x`).
    """

    def __init__(self, state: State, cam: CameraIntrinsics, R_pix):
        self.state = state
        self.cam = cam
        self.R = pixel_covariance(R_pix)
        self.x = state.x.copy()
        self._U = np.zeros((state.n, 0))
        self.batches = 0

    def variances(self, sl: slice) -> np.ndarray:
        """The current covariance's diagonal over the state's entries ``sl`` (before the
        quaternion's normalisation Jacobian, which only :meth:`commit` applies)."""
        d = np.diag(self.state.P)[sl].copy()
        if self._U.shape[1]:
            d -= np.einsum("ij,ij->i", self._U[sl], self._U[sl])
        return d

    def predict(self, ks) -> Prediction:
        """The features' predictions at the current mean."""
        return predict(self.state, ks, self.cam, x=self.x)

    def innovation_covariances(self, pred: Prediction, r_scale=None) -> np.ndarray:
        """(m, 2, 2) each feature's own ``S_i = H_i P H_i^T + r_scale_i R`` at the current
        covariance."""
        st = self.state
        S = _innovation_kernel(st.P, st.kinds, st.starts, FEATURE_DIMS, pred.ks, pred.H_c, pred.H_f,
                               measurement_noise(self.R, r_scale, len(pred.ks)))
        U = self._U
        if U.shape[1] and len(pred.ks):
            HU = _h_times_kernel(U, st.kinds, st.starts, FEATURE_DIMS, pred.ks, pred.H_c, pred.H_f)
            HU = HU.reshape(len(pred.ks), 2, -1)
            S -= HU @ np.swapaxes(HU, 1, 2)
        if pred.H_t is not None and len(pred.ks):
            # The clock offset's column of P = P0 - U U^T, and H's other columns times it.
            p_t = st.P[:, TD_INDEX] - U @ U[TD_INDEX] if U.shape[1] else st.P[:, TD_INDEX].copy()
            c = _h_times_kernel(np.ascontiguousarray(p_t[:, None]), st.kinds, st.starts, FEATURE_DIMS, pred.ks,
                                pred.H_c, pred.H_f)
            _add_time_offset_terms(S, pred.H_t, c.reshape(-1, 2), float(p_t[TD_INDEX]))
        S[~pred.valid] = np.nan
        return S

    def update(self, ks, z, pred: Prediction | None = None, r_scale=None) -> UpdateResult:
        """One batch with measurements ``z`` (m, 2) px of the distinct features ``ks``
        (``pred``: their predictions at the current mean; ``r_scale``: their noises as
        multiples of ``R``, (m,) or (m, 2, 2), :func:`measurement_noise`). Raises :class:`FeatureNotMeasurable`
        or :class:`SlamNumericalError` and changes nothing when the batch cannot be applied."""
        st = self.state
        ks = np.asarray(ks, dtype=np.intp).reshape(-1)
        m = len(ks)
        z = np.asarray(z, dtype=float).reshape(m, 2)
        if m == 0:
            return UpdateResult(np.zeros((0, 2)), np.zeros((0, 0)), np.zeros((0, 2)))
        if len(set(ks.tolist())) != m:
            raise ValueError(f"update: features {ks.tolist()} are not distinct; measure each once")
        if not np.isfinite(z).all():
            raise FeatureNotMeasurable(f"measurements of features {ks[~np.isfinite(z).all(1)].tolist()} are NaN/Inf")
        if pred is None:
            pred = self.predict(ks)
        if not pred.valid.all():
            raise FeatureNotMeasurable(f"features {ks[~pred.valid].tolist()} have no predicted image point (on or "
                                       f"behind the camera plane, or outside the lens model's domain)")
        r = self._U.shape[1]
        u = _NO_COLUMN if pred.H_t is None else np.ascontiguousarray(pred.H_t.reshape(-1))  # H's clock-offset column
        nu = (z - pred.uv).reshape(-1)
        try:
            ok, S, U_new, x = _batch_kernel(st.P, self._U, r, self.x, st.kinds, st.starts, FEATURE_DIMS, ks, pred.H_c,
                                            pred.H_f, u, TD_INDEX, measurement_noise(self.R, r_scale, m), nu)
        except np.linalg.LinAlgError:
            ok = False
        if not ok:
            raise SlamNumericalError(f"innovation covariance S of features {ks.tolist()} is not positive definite "
                                     f"(or not finite); update refused")
        check_mean(x, "update", st.describe)
        q_unit, _ = normalise_quaternion_jacobian(x[Q_SLICE])
        x[Q_SLICE] = q_unit
        self.x = x
        self._U = np.hstack([self._U, U_new]) if r else U_new
        self.batches += 1
        return UpdateResult(nu.reshape(m, 2), S, pred.uv)

    def commit(self) -> None:
        """Write the mean and ``P = J (P0 - U U^T) J^T`` (J: the quaternion's normalisation
        Jacobian) into the state; checked for NaN/Inf and negative variances. Raises
        :class:`SlamNumericalError` (the state unchanged) if the check fails."""
        st = self.state
        if self._U.shape[1] == 0:
            return
        U, P = self._U, st.P
        _, J = normalise_quaternion_jacobian(self.x[Q_SLICE])
        rows, healthy = _commit_check_kernel(P, U, J)
        if not (P.flags.c_contiguous and healthy):
            P = st.P - U @ U.T                               # the guard names the problem
            apply_quaternion_jacobian(P, J)
            st.P = check_covariance(P, "update", check_psd=False, describe=st.describe)
            st.x = self.x
            return
        # In place: BLAS's rank-2m update of one triangle (P's C buffer read as Fortran order
        # is the same symmetric matrix), mirrored, then the quaternion's rows and columns.
        scipy.linalg.blas.dsyrk(-1.0, U.T, beta=1.0, c=P.T, trans=1, lower=1, overwrite_c=1)
        _mirror_and_set_quaternion_rows(P, rows)
        st.x = self.x


def update(state: State, ks, z, cam: CameraIntrinsics, R_pix, pred: Prediction | None = None,
           r_scale=None) -> UpdateResult:
    """The EKF update with measurements ``z`` (m, 2) px of the distinct features ``ks``, in
    place (a batch: all linearised at the current mean). ``pred``: their predictions at the
    current mean, if already computed. Raises :class:`FeatureNotMeasurable` for a feature with
    no image point or a NaN/Inf measurement, :class:`SlamNumericalError` if ``S`` is not positive
    definite or NaN/Inf would enter the state; the state is then unchanged."""
    fu = FrameUpdate(state, cam, R_pix)
    res = fu.update(ks, z, pred, r_scale)
    fu.commit()
    return res


def add_inverse_depth_feature(state: State, uv, cam: CameraIntrinsics, rho0: float, sigma_rho: float, R_pix) -> int:
    """Start an inverse-depth feature at pixel ``uv`` (undelayed: in the state from now) and
    return its index (see :func:`add_inverse_depth_features`)."""
    ks = add_inverse_depth_features(state, np.asarray(uv, float).reshape(1, 2), cam, rho0, sigma_rho, R_pix)
    if not ks:
        raise FeatureNotMeasurable(f"pixel {np.asarray(uv).tolist()} cannot be unprojected by the {cam.model} lens model")
    return ks[0]


def add_inverse_depth_features(state: State, uvs, cam: CameraIntrinsics, rho0: float, sigma_rho: float,
                               R_pix, rays: tuple[np.ndarray, np.ndarray] | None = None) -> list[int]:
    """Start inverse-depth features at the pixels ``uvs`` (m, 2) (undelayed: in the state from
    now), all at once, and return their indices (pixels the lens cannot unproject are skipped).
    With each feature's ``y = g(x_v, uv)`` and Jacobians ``J_x`` (on r, q), ``J_uv``::

        P_yx = J_x P_pose,:       P_yiyj = J_xi P_pose J_xj^T (+ J_uv R J_uv^T + sigma_rho^2 e e^T for i = j)

    ``rays``: the pixels' ``unproject_jacobian``, if the caller has it (init_from_pixels).
    """
    R = pixel_covariance(R_pix)
    y, A, J_x, J_uv = inverse_depth.init_from_pixels(state.x[:state.cam_dim], uvs, cam, rho0, rays)
    ok = np.isfinite(y).all(axis=1)
    if not ok.any():
        return []
    y, J_x, J_uv = y[ok], J_x[ok], J_uv[ok]
    m = len(y)
    Jp = J_x[:, :, :POSE_DIM].reshape(6 * m, POSE_DIM)                          # (6m, 7)
    P_yx = Jp @ state.P[:POSE_DIM, :]
    P_yy = P_yx[:, :POSE_DIM] @ Jp.T
    for i in range(m):
        blk = slice(6 * i, 6 * i + 6)
        P_yy[blk, blk] += J_uv[i] @ R @ J_uv[i].T
        P_yy[6 * i + 5, 6 * i + 5] += sigma_rho**2
    return state.add_features([INVERSE_DEPTH] * m, y.reshape(-1), P_yy, P_yx, np.repeat(A[None], m, axis=0))


def add_point_feature(state: State, uv, depth: float, var_depth: float, R_pix, cam: CameraIntrinsics) -> int:
    """Add the point seen at pixel ``uv`` at ``depth`` m along its ray (variance ``var_depth``
    m^2) and return its index (the particle initialisation's promotion)."""
    depth, var_depth = float(depth), float(var_depth)
    if not (math.isfinite(depth) and depth > 0):
        raise ValueError(f"depth = {depth!r} must be a positive distance along the ray, m")
    if not (math.isfinite(var_depth) and var_depth >= 0):
        raise ValueError(f"var_depth = {var_depth!r} must be a variance >= 0, m^2")
    R = pixel_covariance(R_pix)
    y, J_x, J_uv, J_d = init_point_from_depth(state.x[:state.cam_dim], uv, depth, cam)
    if not np.isfinite(y).all():
        raise FeatureNotMeasurable(f"pixel {np.asarray(uv).tolist()} cannot be unprojected by the {cam.model} lens model")
    Jp = J_x[:, :POSE_DIM]
    P_yx = Jp @ state.P[:POSE_DIM, :]
    P_yy = P_yx[:, :POSE_DIM] @ Jp.T + J_uv @ R @ J_uv.T + var_depth * np.outer(J_d, J_d)
    return state.add_feature(POINT, y, P_yy, P_yx)


def point_conversions(state: State, ks) -> tuple[list, list]:
    """Inverse-depth features ``ks`` as 3D points: their parameters (3,) and the conversions'
    Jacobians (3, 6), for :meth:`State.edit_features`."""
    ks = [int(k) for k in np.atleast_1d(ks)]
    for k in ks:
        if state.kinds[k] != INVERSE_DEPTH:
            raise ValueError(f"feature {k} is a {state.kinds[k]} feature, not an inverse-depth one")
    conv = [inverse_depth.to_point(state.feature(k), state.anchors[k]) for k in ks]
    return [p for p, _ in conv], [J for _, J in conv]


def convert_to_point(state: State, k) -> None:
    """Turn inverse-depth feature ``k`` (or each of a list) into a 3D point (first-order
    covariance transform, one rebuild of ``P`` for all)."""
    ys, Js = point_conversions(state, k)
    state.convert_features([int(k) for k in np.atleast_1d(k)], POINT, ys, Js)
