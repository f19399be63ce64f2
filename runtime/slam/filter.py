"""The EKF steps of MonoSLAM: measurement update (a batch of features, or one at a time as
MonoSLAM does, largest innovation covariance first), the ordering of measurements, and adding a
point feature with its full cross-covariance.

The measurement of feature ``k`` depends only on the camera block and on feature ``k``, so each
2-row block of ``H`` has 16 nonzero columns. The update never forms dense n-wide rows of ``H``:
it gathers the columns it touches (the camera's 13 and each measured feature's 3, ``c`` in
all), keeps ``H`` as a compact (2m, c) matrix ``Hc`` with their index list ``idx``, and uses
``P H^T = P[:, idx] Hc^T``. The covariance update is the Joseph form
``(I - K H) P (I - K H)^T + K R K^T``, evaluated in O(n^2 m) with the same trick.

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

from kinematics.camera import CameraIntrinsics

from .measurement import h_and_jacobians_many, init_point_from_depth
from .motion import apply_quaternion_jacobian, normalise_quaternion_jacobian, predict
from .state import (
    CAMERA_DIM,
    CAMERA_SLICE,
    DEFAULT_CONFIG,
    FEATURE_DIM,
    Q_SLICE,
    SlamConfig,
    SlamNumericalError,
    State,
    check_covariance,
    check_mean,
    feature_indices,
)

__all__ = ["predict", "update", "update_one", "innovation_covariances", "measurement_order",
           "add_point_feature", "UpdateResult", "FeatureNotMeasurable"]


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
