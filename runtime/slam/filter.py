"""The EKF steps of MonoSLAM: measurement update (a batch of features, or one at a time as
MonoSLAM does, largest innovation covariance first), the ordering of measurements, and adding a
point feature with its full cross-covariance.

The measurement of feature ``k`` depends only on the camera block and on feature ``k``, so each
2-row block of ``H`` has 16 nonzero columns. The update never forms dense n-wide rows of ``H``:
it gathers the columns it touches (the camera's 13 and each measured feature's 3, ``c`` in
all), keeps ``H`` as a compact (2m, c) matrix ``Hc`` with their index list ``idx``, and uses
``P H^T = P[:, idx] Hc^T``. The covariance update is the Joseph form
``(I - K H) P (I - K H)^T + K R K^T``, evaluated in O(n^2 m) with the same trick.

For a running system, :class:`SequentialUpdate` does a frame's sequential updates (ellipse at
the current mean -> search -> update, feature after feature) in O(n) each, keeping the
covariance as a low-rank correction that :meth:`SequentialUpdate.commit` applies once per frame;
its results equal :func:`innovation_covariances` + :func:`update_one` to rounding. The
functions :func:`update`, :func:`update_one` and :func:`innovation_covariances` remain the
reference (and the batch update).

The prediction lives in motion.py (:func:`runtime.slam.motion.predict`); it is re-exported
here so that ``from runtime.slam.filter import predict, update`` works.

Pixel covariances ``R_pix`` are in px^2: a scalar (isotropic variance), a (2, 2) matrix for
every measurement, or an (m, 2, 2) array, one per measurement (``SlamConfig.R_pix`` is
``sigma_pixel^2 I``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.linalg

from kinematics.camera import CameraIntrinsics, lens_kernel_args

from .measurement import h_and_jacobians_many, h_point_kernel, init_point_from_depth
from .motion import apply_quaternion_jacobian, normalise_quaternion_jacobian, normalise_quaternion_kernel, predict
from .state import (
    CAMERA_DIM,
    CAMERA_SLICE,
    DEFAULT_CONFIG,
    FEATURE_DIM,
    Q_SLICE,
    SlamConfig,
    SlamNumericalError,
    State,
    _describe_index,
    check_covariance,
    check_mean,
    compiled_kernel,
    feature_indices,
    feature_start,
    rotation_derivatives_kernel,
    rotation_kernel,
)

__all__ = ["predict", "update", "update_one", "innovation_covariances", "measurement_order",
           "add_point_feature", "UpdateResult", "FeatureNotMeasurable", "SequentialUpdate", "Innovation"]


class FeatureNotMeasurable(ValueError):
    """A feature asked to be measured projects to no image point (behind the camera, or
    outside the lens model's domain), or its measurement is NaN/Inf."""


class UpdateResult(NamedTuple):
    """What :func:`update` returns: the innovations and their covariance, e.g. for gating."""

    nu: np.ndarray   #: (m, 2) innovation z - h, px
    S: np.ndarray    #: (2m, 2m) innovation covariance, px^2 (measurement i: rows 2i, 2i+1)
    uv: np.ndarray   #: (m, 2) predicted measurements h, px

    @property
    def nis(self) -> float:
        """Normalised innovation squared ``nu^T S^-1 nu`` (chi-square with 2m dof)."""
        v = self.nu.reshape(-1)
        return float(v @ np.linalg.solve(self.S, v))


def _pixel_covariances(R_pix, m: int) -> np.ndarray:
    R = np.asarray(R_pix, dtype=float)
    if R.ndim == 0:
        R = float(R) * np.eye(2)
    if R.shape == (2, 2):
        R = np.broadcast_to(R, (m, 2, 2))
    if R.shape != (m, 2, 2):
        raise ValueError(f"R_pix must be a scalar variance, a (2, 2) or an ({m}, 2, 2) covariance "
                         f"in px^2, got shape {np.shape(R_pix)}")
    if not np.isfinite(R).all():
        raise ValueError("R_pix has NaN/Inf")
    return R


def _feature_list(state: State, k_list) -> np.ndarray:
    ks = np.asarray(k_list, dtype=np.intp).reshape(-1)
    if ks.size and (ks.min() < 0 or ks.max() >= state.n_features):
        bad = ks[(ks < 0) | (ks >= state.n_features)]
        raise IndexError(f"features {bad.tolist()} do not exist (the map has {state.n_features})")
    return ks


def _predict_measurements(state: State, ks: np.ndarray, cam: CameraIntrinsics):
    """uv (m, 2), Hc (2m, c), idx (c,) for the features ks; FeatureNotMeasurable if any has
    no image."""
    m = len(ks)
    uv, H_x, H_y, valid = h_and_jacobians_many(state.x_v, state.features[ks], cam)
    if not valid.all():
        bad = ks[~valid]
        raise FeatureNotMeasurable(f"features {bad.tolist()} have no predicted image point (on or "
                                   f"behind the camera plane, or outside the lens model's domain); "
                                   f"do not measure them")
    uniq, pos = np.unique(ks, return_inverse=True)
    idx = np.concatenate([np.arange(CAMERA_DIM), feature_indices(uniq).reshape(-1)])
    Hc = np.zeros((2 * m, len(idx)))
    Hc[:, :CAMERA_DIM] = H_x.reshape(2 * m, CAMERA_DIM)
    rows = np.arange(2 * m)[:, None]
    cols = (CAMERA_DIM + FEATURE_DIM * np.repeat(pos, 2))[:, None] + np.arange(FEATURE_DIM)
    Hc[rows, cols] = H_y.reshape(2 * m, FEATURE_DIM)
    return uv, Hc, idx


def update(state: State, k_list, z, cam: CameraIntrinsics, R_pix,
           cfg: SlamConfig = DEFAULT_CONFIG) -> UpdateResult:
    """EKF update with measurements ``z`` (m, 2) px of the features ``k_list`` (m,), in place.

    ``S = H P H^T + R``, ``K = P H^T S^-1`` (Cholesky of ``S``), ``x += K nu``, Joseph-form
    covariance; then ``q`` is renormalised with its Jacobian and the guard runs. All features
    are linearised at the same prior (a batch update). Raises :class:`FeatureNotMeasurable`
    for a feature with no predicted image point, :class:`SlamNumericalError` if ``S`` is not
    positive definite or NaN/Inf would enter the state; the state is then unchanged.
    Returns :class:`UpdateResult` (innovations, S, predictions).
    """
    ks = _feature_list(state, k_list)
    m = len(ks)
    z = np.asarray(z, dtype=float).reshape(m, 2)
    if not np.isfinite(z).all():
        raise FeatureNotMeasurable(f"measurements of features {ks[~np.isfinite(z).all(1)].tolist()} "
                                   f"are NaN/Inf")
    R_blocks = _pixel_covariances(R_pix, m)
    if m == 0:
        return UpdateResult(np.zeros((0, 2)), np.zeros((0, 0)), np.zeros((0, 2)))
    R = np.zeros((2 * m, 2 * m))
    for i in range(m):
        R[2 * i:2 * i + 2, 2 * i:2 * i + 2] = R_blocks[i]

    uv, Hc, idx = _predict_measurements(state, ks, cam)
    nu = (z - uv).reshape(-1)
    P = state.P
    PHt = P[:, idx] @ Hc.T                      # (n, 2m) = P H^T
    S = Hc @ PHt[idx, :] + R
    S = 0.5 * (S + S.T)
    try:
        if not np.isfinite(S).all():
            raise np.linalg.LinAlgError
        S_chol = scipy.linalg.cho_factor(S, check_finite=False)
    except np.linalg.LinAlgError:
        raise SlamNumericalError(f"innovation covariance S of features {ks.tolist()} is not positive "
                                 f"definite (or not finite); update refused") from None
    K = scipy.linalg.cho_solve(S_chol, PHt.T, check_finite=False).T  # (n, 2m)

    x = state.x + K @ nu
    # Joseph form with H kept compact: A = (I - K H) P, then A (I - K H)^T + K R K^T.
    A = P - K @ PHt.T
    P_new = A - (A[:, idx] @ Hc.T) @ K.T + K @ R @ K.T

    check_mean(x, "update")
    q_unit, J = normalise_quaternion_jacobian(x[Q_SLICE])
    x[Q_SLICE] = q_unit
    apply_quaternion_jacobian(P_new, J)
    state.P = check_covariance(P_new, "update", cfg)
    state.x = x
    return UpdateResult(nu.reshape(m, 2), S, uv)


def update_one(state: State, k: int, z, cam: CameraIntrinsics, R_pix,
               cfg: SlamConfig = DEFAULT_CONFIG) -> UpdateResult:
    """:func:`update` with one feature ``k`` and one measurement ``z`` (2,) px: MonoSLAM's
    sequential update (use :func:`measurement_order` for the order)."""
    return update(state, [k], np.asarray(z, dtype=float).reshape(1, 2), cam, R_pix, cfg)


def innovation_covariances(state: State, k_list, cam: CameraIntrinsics, R_pix
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each feature's own predicted measurement and 2x2 innovation covariance (its search
    region), vectorised: ``S_i = H_i P_i H_i^T + R_i`` over the 16 state entries it touches.

    Returns uv (m, 2) px, S (m, 2, 2) px^2 and valid (m,) bool; invalid features (no image
    point) get NaN.
    """
    ks = _feature_list(state, k_list)
    m = len(ks)
    R_blocks = _pixel_covariances(R_pix, m)
    uv, H_x, H_y, valid = h_and_jacobians_many(state.x_v, state.features[ks], cam)
    H = np.concatenate([H_x, H_y], axis=2)                       # (m, 2, 16)
    idx = np.concatenate([np.broadcast_to(np.arange(CAMERA_DIM), (m, CAMERA_DIM)),
                          feature_indices(ks)], axis=1)          # (m, 16)
    P_blocks = state.P[idx[:, :, None], idx[:, None, :]]        # (m, 16, 16)
    S = H @ P_blocks @ np.swapaxes(H, 1, 2) + R_blocks
    return uv, 0.5 * (S + np.swapaxes(S, 1, 2)), valid


def measurement_order(state: State, k_list, cam: CameraIntrinsics, R_pix) -> np.ndarray:
    """The features of ``k_list`` that have an image point, most uncertain first (largest
    ``det S``, i.e. the largest search ellipse), as MonoSLAM measures them."""
    ks = _feature_list(state, k_list)
    _, S, valid = innovation_covariances(state, ks, cam, R_pix)
    det = np.linalg.det(S[valid]) if valid.any() else np.zeros(0)
    return ks[valid][np.argsort(-det, kind="stable")]


# ---------------------------------------------------------------------------------------------
# MonoSLAM's sequential update, one frame at a time
# ---------------------------------------------------------------------------------------------

class Innovation(NamedTuple):
    """What :meth:`SequentialUpdate.innovation` returns (unpack as ``uv, S, valid = ...``)."""

    uv: np.ndarray   #: (2,) predicted measurement h at the current mean, px (NaN if not valid)
    S: np.ndarray    #: (2, 2) innovation covariance H P H^T + R, px^2: the search ellipse
    valid: bool      #: the feature has a predicted image point (see measurement.py)


class _Linearisation(NamedTuple):
    """One feature's measurement model at the current mean, kept for the update that follows."""

    k: int
    version: int      # SequentialUpdate._version it was computed at
    uv: np.ndarray    # (2,) px
    PHt: np.ndarray   # (2, n) (P H^T)^T at the current covariance
    S: np.ndarray     # (2, 2) px^2
    valid: bool


#: Rows of U^T allocated at first (8 updates); doubled when more are needed.
_INITIAL_COLUMNS = 16

# Outcomes of _update_kernel.
_ACCEPTED, _S_NOT_PD, _MEAN_NOT_FINITE, _Q_ZERO, _P_NOT_FINITE, _NEGATIVE_VARIANCE = range(6)


@compiled_kernel(h_point_kernel, rotation_kernel, rotation_derivatives_kernel)
def _linearise_kernel(x, s, model, lens, M, P0, Ut, m, R_pix):
    """Feature ``x[s:s+3]``'s measurement at the mean ``x`` (n,) and its ``P H^T`` and ``S``
    under ``P = T P0 T^T - U U^T`` (see :class:`SequentialUpdate`; ``M`` (4, 4) is T's q block,
    ``Ut`` holds ``U^T`` in its first ``m`` rows).

    Returns uv (2,) px, PHt (2, n) = (P H^T)^T, S (2, 2) = H P H^T + R_pix (symmetrised) and
    valid (False: no image point; then all NaN).
    """
    n = x.shape[0]
    R = rotation_kernel(x[3], x[4], x[5], x[6])
    dR = rotation_derivatives_kernel(x[3], x[4], x[5], x[6])
    uv = np.empty(2)
    H_x = np.zeros((2, CAMERA_DIM))
    H_y = np.empty((2, FEATURE_DIM))
    PHt = np.zeros((2, n))
    S = np.empty((2, 2))
    if not h_point_kernel(x, R, dR, x[s], x[s + 1], x[s + 2], model, lens, uv, H_x, H_y):
        PHt[:] = np.nan
        S[:] = np.nan
        return uv, PHt, S, False
    # (P H^T)^T = H P = (H T) P0 T^T - (H U) U^T. H T is H with its q columns times M; (H T) P0
    # needs only the 16 rows of P0 that H touches (camera and feature k).
    HT = H_x.copy()
    for a in range(2):
        for j in range(4):
            HT[a, 3 + j] = (H_x[a, 3] * M[0, j] + H_x[a, 4] * M[1, j]
                            + H_x[a, 5] * M[2, j] + H_x[a, 6] * M[3, j])
    for i in range(CAMERA_DIM + FEATURE_DIM):
        row = i if i < CAMERA_DIM else s + i - CAMERA_DIM
        h0 = HT[0, i] if i < CAMERA_DIM else H_y[0, i - CAMERA_DIM]
        h1 = HT[1, i] if i < CAMERA_DIM else H_y[1, i - CAMERA_DIM]
        if h0 == 0.0 and h1 == 0.0:
            continue                      # the v, w columns of H
        for j in range(n):
            PHt[0, j] += h0 * P0[row, j]
            PHt[1, j] += h1 * P0[row, j]
    # ... T^T on the right mixes the q columns by M^T ...
    for a in range(2):
        p0, p1, p2, p3 = PHt[a, 3], PHt[a, 4], PHt[a, 5], PHt[a, 6]
        for i in range(4):
            PHt[a, 3 + i] = p0 * M[i, 0] + p1 * M[i, 1] + p2 * M[i, 2] + p3 * M[i, 3]
    # ... and the low-rank part: H U is (2, m), over the same 16 entries of each column of U.
    for r in range(m):
        hu0 = 0.0
        hu1 = 0.0
        for i in range(CAMERA_DIM):
            hu0 += H_x[0, i] * Ut[r, i]
            hu1 += H_x[1, i] * Ut[r, i]
        for c in range(FEATURE_DIM):
            hu0 += H_y[0, c] * Ut[r, s + c]
            hu1 += H_y[1, c] * Ut[r, s + c]
        for j in range(n):
            PHt[0, j] -= hu0 * Ut[r, j]
            PHt[1, j] -= hu1 * Ut[r, j]
    # S = H (P H^T) + R
    for a in range(2):
        for b in range(2):
            acc = R_pix[a, b]
            for i in range(CAMERA_DIM):
                acc += PHt[a, i] * H_x[b, i]
            for c in range(FEATURE_DIM):
                acc += PHt[a, s + c] * H_y[b, c]
            S[a, b] = acc
    off = 0.5 * (S[0, 1] + S[1, 0])
    S[0, 1] = off
    S[1, 0] = off
    return uv, PHt, S, True


@compiled_kernel(normalise_quaternion_kernel)
def _update_kernel(x, PHt, S, uv, z0, z1, M, P0_qq, Ut, m, d, psd_rel_tol):
    """One accepted-or-refused update of :class:`SequentialUpdate` (see there for the maths).

    x (n,) mean; PHt (2, n), S (2, 2), uv (2,) from :func:`_linearise_kernel` at this mean;
    (z0, z1) the measurement, px; M (4, 4), P0_qq (4, 4), Ut (>= m + 2, n) and d (n,) = diag P
    describe the covariance. If the update is acceptable, writes the new x, M, d and U (rows m,
    m + 1 of Ut; q columns of rows 0..m+1 times J) in place and returns (_ACCEPTED, -1, 0, nu0,
    nu1); otherwise writes nothing and returns (outcome, index, value, nu0, nu1).
    """
    n = x.shape[0]
    nu0, nu1 = z0 - uv[0], z1 - uv[1]
    # S = L L^T, L = [[l00, 0], [l10, l11]]
    s00, s10, s11 = S[0, 0], S[1, 0], S[1, 1]
    if not (s00 > 0 and np.isfinite(s00)):
        return _S_NOT_PD, -1, s00, nu0, nu1
    l00 = math.sqrt(s00)
    l10 = s10 / l00
    t = s11 - l10 * l10
    if not (t > 0 and np.isfinite(t)):
        return _S_NOT_PD, -1, t, nu0, nu1
    l11 = math.sqrt(t)
    w0 = nu0 / l00                        # L^-1 nu
    w1 = (nu1 - l10 * w0) / l11
    # New columns of U: K L = P H^T L^-T; the mean moves by K nu = (K L)(L^-1 nu); the
    # diagonal of P loses the squares of the new columns.
    U_new = np.empty((2, n))
    x_new = np.empty(n)
    d_new = np.empty(n)
    for j in range(n):
        u0 = PHt[0, j] / l00
        u1 = (PHt[1, j] - l10 * u0) / l11
        U_new[0, j] = u0
        U_new[1, j] = u1
        x_new[j] = x[j] + (w0 * u0 + w1 * u1)
        d_new[j] = d[j] - (u0 * u0 + u1 * u1)
    for j in range(n):
        if not np.isfinite(x_new[j]):
            return _MEAN_NOT_FINITE, j, x_new[j], nu0, nu1
    # Renormalise q, and P <- T_J P T_J^T on the factors: M <- J M, U[q] <- J U[q].
    q_unit, J, ok = normalise_quaternion_kernel(x_new[3], x_new[4], x_new[5], x_new[6])
    if not ok:
        return _Q_ZERO, 3, 0.0, nu0, nu1
    for i in range(4):
        x_new[3 + i] = q_unit[i]
    M_new = np.zeros((4, 4))
    for i in range(4):
        for j in range(4):
            for k in range(4):
                M_new[i, j] += J[i, k] * M[k, j]
    Uq = np.zeros((m + 2, 4))
    for r in range(m + 2):
        for i in range(4):
            for j in range(4):
                Uq[r, i] += J[i, j] * (Ut[r, 3 + j] if r < m else U_new[r - m, 3 + j])
    for i in range(4):                    # diag of P_qq = M P0_qq M^T - U[q] U[q]^T
        acc = 0.0
        for j in range(4):
            for k in range(4):
                acc += M_new[i, j] * P0_qq[j, k] * M_new[i, k]
        for r in range(m + 2):
            acc -= Uq[r, i] * Uq[r, i]
        d_new[3 + i] = acc
    # The guard of check_covariance (without the PSD test), on the diagonal.
    d_max = -np.inf
    i_min = 0
    for j in range(n):
        if not np.isfinite(d_new[j]):
            return _P_NOT_FINITE, j, d_new[j], nu0, nu1
        d_max = max(d_max, d_new[j])
        if d_new[j] < d_new[i_min]:
            i_min = j
    if d_new[i_min] < -psd_rel_tol * max(d_max, 2.2250738585072014e-308):
        return _NEGATIVE_VARIANCE, i_min, d_new[i_min], nu0, nu1
    # Accepted. (Element loops, not slice assignments: numba compiles each array-to-array
    # assignment with a shape-mismatch error path that costs seconds of compile time.)
    for j in range(n):
        x[j] = x_new[j]
        d[j] = d_new[j]
        Ut[m, j] = U_new[0, j]
        Ut[m + 1, j] = U_new[1, j]
    for i in range(4):
        for j in range(4):
            M[i, j] = M_new[i, j]
    for r in range(m + 2):
        for i in range(4):
            Ut[r, 3 + i] = Uq[r, i]
    return _ACCEPTED, -1, 0.0, nu0, nu1


class SequentialUpdate:
    """MonoSLAM's sequential measurement update over one frame, O(n) per feature.

    Each feature is predicted, searched for and updated in turn, every update linearising at the
    mean and covariance left by the ones before it. The results equal a loop of
    :func:`innovation_covariances` + :func:`update_one` (each of which renormalises ``q``) to
    rounding, but without the n x n work per feature:

    * the covariance is kept as ``P = T P0 T^T - U U^T``: ``P0`` (n, n) is the state's
      covariance when this object was made (never copied or modified), ``T`` is the identity
      except a 4x4 block ``M`` on ``q``, the product of the quaternion-normalisation Jacobians
      applied so far, and ``U`` (n, 2 m) grows by two columns per update. An update with
      ``S = L L^T`` (Cholesky) and gain ``K = P H^T S^-1`` removes ``K S K^T = (K L)(K L)^T``
      from ``P``, so its two new columns are ``K L = P H^T L^-T``. ``P H^T`` needs only the 16
      rows of ``P0`` that ``H`` touches (the camera's 13 and the feature's 3) plus ``U``:
      O(n (32 + 4 m)) per feature instead of the Joseph form's O(n^2).
    * the mean is updated at once (``x += K nu``) and ``q`` renormalised after every update, as
      :func:`update` does: ``q <- q / |q|`` and ``P <- J P J^T`` on the ``q`` block, with ``J`` the
      normalisation Jacobian. On the factored ``P`` that is ``M <- J M`` and ``U[q] <- J U[q]``
      (4 rows), O(m), so nothing is approximated. (Deferring the normalisation to the end of the
      frame would give the same ``S`` and ``K`` -- ``h`` is invariant to the scale of ``q``
      because ``R(s q) = s^2 R(q)`` and projection ignores the scale of ``P_cam``, so
      ``H_q q = 0`` -- but the mean would then differ from :func:`update`'s at second order in
      each step.)
    * the diagonal of ``P`` is tracked (O(n) per update) so that each update is refused, as
      :func:`update` with ``check_psd=False`` refuses it, if it would produce a NaN/Inf or a
      negative variance.
    * :meth:`commit` forms ``P`` once (one ``U U^T`` product), symmetrises and checks it with
      ``cfg`` (:func:`check_covariance`), and writes mean and covariance into the state.

    The per-feature work runs in two compiled kernels (numba) around the measurement model's own
    kernel (:func:`runtime.slam.measurement.h_point_kernel`).

    Numerically this is the ``P - K S K^T`` form, not the Joseph form :func:`update` uses. The
    two agree to rounding for ellipses of searchable size (search.py refuses boxes over 200 000
    px^2, i.e. ``S / R`` up to ~1e4); when ``H P H^T`` exceeds ``R`` by many more orders of
    magnitude (``S ~ 1e17 px^2`` in a diverged simulation) rounding can leave ``P`` slightly
    indefinite where the Joseph form still passes the per-frame PSD check.

    Until :meth:`commit` the :class:`State` is untouched: it keeps the mean and covariance it had
    when this object was made, so read the current mean from :attr:`x`, :attr:`x_v` and
    :meth:`feature`. A frame whose :meth:`commit` is never called leaves no trace. The state must
    not be changed by anything else (predict, update_one, adding or removing features) while this
    object is in use; it checks and raises RuntimeError if it was.

    state : the filter state (mean and covariance after the prediction).
    cam : intrinsics and lens model.
    R_pix : pixel measurement covariance, px^2: a scalar variance or (2, 2).
    cfg : the filter's parameters; ``cfg.psd_rel_tol`` sets the negative-variance tolerance, and
        :meth:`commit` runs :func:`check_covariance` with ``cfg`` (with ``check_psd`` if set).
    """

    def __init__(self, state: State, cam: CameraIntrinsics, R_pix, cfg: SlamConfig = DEFAULT_CONFIG):
        self.state = state
        self.cam = cam
        self.cfg = cfg
        self._R = np.array(_pixel_covariances(R_pix, 1)[0])
        self._model, self._lens = lens_kernel_args(cam)
        # The arrays themselves: State replaces (never resizes) them when anything changes it,
        # so identity tells whether the state was touched behind this object's back.
        self._x0, self._P0_given = state.x, state.P
        self._P0 = np.ascontiguousarray(state.P)       # the layout the kernels are compiled for
        self._x = state.x.copy()
        n = state.n
        self._M = np.eye(4)                            # accumulated normalisation Jacobians on q
        self._Ut = np.empty((_INITIAL_COLUMNS, n))     # U^T: rows 0.._m-1 in use
        self._m = 0
        self._d = np.diag(self._P0).copy()             # diag P, for the refusals
        self._P0_qq = self._P0[Q_SLICE, Q_SLICE].copy()
        self._version = 0                              # bumped by every applied update
        self._lin: _Linearisation | None = None
        self._done = False

    # -- the current mean ------------------------------------------------------------------
    @property
    def x(self) -> np.ndarray:
        """(n,) the current mean, after the updates applied so far (a copy)."""
        return self._x.copy()

    @property
    def x_v(self) -> np.ndarray:
        """(13,) the current camera block (a copy)."""
        return self._x[CAMERA_SLICE].copy()

    def feature(self, k: int) -> np.ndarray:
        """(3,) the current world position of feature ``k``, m (a copy)."""
        s = feature_start(self._feature_index(k))
        return self._x[s:s + FEATURE_DIM].copy()

    @property
    def features(self) -> np.ndarray:
        """(N, 3) the current world positions of all features, m (a copy)."""
        return self._x[CAMERA_DIM:].reshape(-1, FEATURE_DIM).copy()

    @property
    def n_updates(self) -> int:
        """Updates applied so far."""
        return self._m // 2

    def covariance(self) -> np.ndarray:
        """(n, n) the current covariance ``T P0 T^T - U U^T`` (a new array, O(n^2 m); for
        inspection: :meth:`commit` forms it once per frame)."""
        P = self._P0.copy()
        apply_quaternion_jacobian(P, self._M)
        if self._m:
            Ut = self._Ut[:self._m]
            P -= Ut.T @ Ut
        return P

    # -- the per-feature steps -------------------------------------------------------------
    def innovation(self, k: int) -> Innovation:
        """Feature ``k``'s predicted measurement and 2x2 innovation covariance at the current
        mean and covariance (after the updates already applied): its search region. An
        :meth:`update` of the same feature right after reuses this linearisation."""
        lin = self._linearise(self._feature_index(k))
        return Innovation(lin.uv.copy(), lin.S.copy(), lin.valid)

    def update(self, k: int, z) -> UpdateResult:
        """Update with measurement ``z`` (2,) px of feature ``k``; returns :class:`UpdateResult`
        (as :func:`update_one`).

        Raises :class:`FeatureNotMeasurable` if ``z`` is NaN/Inf or the feature has no predicted
        image point, :class:`SlamNumericalError` if ``S`` is not positive definite or the update
        would put NaN/Inf or a negative variance into the state; nothing changes then.
        """
        k = self._feature_index(k)
        z = np.asarray(z, dtype=float).reshape(2)
        z0, z1 = float(z[0]), float(z[1])
        if not (math.isfinite(z0) and math.isfinite(z1)):
            raise FeatureNotMeasurable(f"measurement {z.tolist()} of feature {k} is NaN/Inf")
        lin = self._linearise(k)
        if not lin.valid:
            raise FeatureNotMeasurable(f"feature {k} has no predicted image point (on or behind the camera "
                                       f"plane, or outside the lens model's domain); do not measure it")
        m = self._m
        if m + 2 > len(self._Ut):
            grown = np.empty((2 * len(self._Ut), len(self._x)))
            grown[:m] = self._Ut[:m]
            self._Ut = grown
        outcome, i, value, nu0, nu1 = _update_kernel(self._x, lin.PHt, lin.S, lin.uv, z0, z1, self._M,
                                                     self._P0_qq, self._Ut, m, self._d, self.cfg.psd_rel_tol)
        if outcome != _ACCEPTED:
            raise SlamNumericalError(self._refusal(k, outcome, i, value))
        self._m = m + 2
        self._version += 1
        self._lin = None                  # lin's arrays are no longer shared: hand them out
        return UpdateResult(np.array([[nu0, nu1]]), lin.S, lin.uv.reshape(1, 2))

    def commit(self) -> None:
        """Write the mean and covariance into the state: ``P = T P0 T^T - U U^T`` (one product),
        symmetrised and checked by :func:`check_covariance` with ``cfg``. Call once, at the end of
        the frame's updates; afterwards this object cannot be used. If the check fails,
        :class:`SlamNumericalError` is raised and the state keeps the mean and covariance it had
        before this frame's updates."""
        self._check_state()
        self._done = True
        if self._m == 0:
            return
        P = check_covariance(self.covariance(), "the frame's sequential updates", self.cfg)
        self.state.P = P
        self.state.x = self._x

    # -- internals -------------------------------------------------------------------------
    def _check_state(self) -> None:
        if self._done:
            raise RuntimeError("this SequentialUpdate was committed; make a new one for the next frame")
        if self.state.x is not self._x0 or self.state.P is not self._P0_given:
            raise RuntimeError("the state was changed (predict, update_one, add or remove feature) while a "
                               "SequentialUpdate was in use; commit it first, or make a new one")

    def _feature_index(self, k) -> int:
        self._check_state()
        k = int(k)
        n_features = (len(self._x) - CAMERA_DIM) // FEATURE_DIM
        if not 0 <= k < n_features:
            raise IndexError(f"feature {k} does not exist (the map has {n_features})")
        return k

    def _linearise(self, k: int) -> _Linearisation:
        """Feature ``k``'s h, ``P H^T`` and ``S`` at the current mean and covariance (cached until
        the next update)."""
        lin = self._lin
        if lin is None or lin.k != k or lin.version != self._version:
            uv, PHt, S, valid = _linearise_kernel(self._x, feature_start(k), self._model, self._lens, self._M,
                                                  self._P0, self._Ut, self._m, self._R)
            lin = self._lin = _Linearisation(k, self._version, uv, PHt, S, valid)
        return lin

    @staticmethod
    def _refusal(k: int, outcome: int, i: int, value: float) -> str:
        if outcome == _S_NOT_PD:
            return f"innovation covariance S of feature {k} is not positive definite (or not finite); update refused"
        if outcome == _MEAN_NOT_FINITE:
            return f"update of feature {k} would put NaN/Inf into the mean at index {i} ({_describe_index(i)}); refused"
        if outcome == _Q_ZERO:
            return f"update of feature {k} would make the quaternion zero or not finite; refused"
        if outcome == _P_NOT_FINITE:
            return (f"update of feature {k} would put NaN/Inf into the covariance at P[{i},{i}] "
                    f"({_describe_index(i)}); refused")
        return (f"update of feature {k} would give a negative variance P[{i},{i}] = {value:.3g} "
                f"({_describe_index(i)}); refused")


def add_point_feature(state: State, uv, depth: float, var_depth: float, R_pix,
                      cam: CameraIntrinsics, cfg: SlamConfig = DEFAULT_CONFIG) -> int:
    """Add the point seen at pixel ``uv`` at ``depth`` m along its ray (MonoSLAM's lambda,
    variance ``var_depth`` m^2, pixel covariance ``R_pix`` px^2 (2, 2) or scalar) and return its
    index ``k``.

    With ``y = r + depth d(q, uv)`` and its Jacobians ``J_x``, ``J_uv``, ``J_d`` from
    :func:`init_point_from_depth`::

        P_yy = J_x P_xx J_x^T + J_uv R J_uv^T + J_d var_d J_d^T
        P_yx = J_x P_xx,  P_y,features = J_x P_x,features
    """
    depth, var_depth = float(depth), float(var_depth)
    if not (math.isfinite(depth) and depth > 0):
        raise ValueError(f"depth = {depth!r} must be a positive distance along the ray, m")
    if not (math.isfinite(var_depth) and var_depth >= 0):
        raise ValueError(f"var_depth = {var_depth!r} must be a variance >= 0, m^2")
    R = _pixel_covariances(R_pix, 1)[0]
    y, J_x, J_uv, J_d = init_point_from_depth(state.x_v, uv, depth, cam)
    if not np.isfinite(y).all():
        raise FeatureNotMeasurable(f"pixel {np.asarray(uv).tolist()} cannot be unprojected by the "
                                   f"{cam.model} lens model")
    P_yx = J_x @ state.P[CAMERA_SLICE, :]                     # (3, n): camera and features
    P_yy = P_yx[:, CAMERA_SLICE] @ J_x.T + J_uv @ R @ J_uv.T + var_depth * np.outer(J_d, J_d)
    return state.add_feature(y, P_yy, P_yx, cfg)
