"""Measurements of the map's features, whatever their kind: the predicted pixel of each, with
its Jacobians with respect to the camera pose (r, q: the 7 columns a measurement touches) and
to the feature's own parameters, dispatched on the feature's kind to its model (features/).

A feature on or behind the camera plane, or outside a lens model's domain, gets ``uv = NaN``
and NaN Jacobians, and ``valid`` is False; nothing is raised here. Whether a valid point falls
inside the image is a separate question (:func:`kinematics.camera.in_image`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args, unproject_jacobian

from .features import INVERSE_DEPTH, MAX_FEATURE_DIM, POINT
from .features import inverse_depth, point
from .kernels import compiled_kernel
from .quaternion import quat_multiply, quat_to_rotation, rotation_derivatives, rotation_derivatives_kernel, rotation_kernel
from .state import POSE_DIM, Q_SLICE, R_SLICE, TD_INDEX, V_SLICE, W_SLICE, State


class Prediction(NamedTuple):
    """Predicted measurements of features ``ks``: uv (m, 2) px, H_c (m, 2, 7) = d(uv)/d(r, q),
    H_f (m, 2, 6) = d(uv)/d(feature), its first ``dim`` columns used, valid (m,) bool, and
    with the IMU's clock offset in the state H_t (m, 2) = d(uv)/d(t_d) px/s (else None)."""

    ks: np.ndarray
    uv: np.ndarray
    H_c: np.ndarray
    H_f: np.ndarray
    valid: np.ndarray
    H_t: np.ndarray | None = None

    def take(self, sel) -> "Prediction":
        """The predictions ``sel`` (indices or a mask)."""
        return Prediction(self.ks[sel], self.uv[sel], self.H_c[sel], self.H_f[sel], self.valid[sel],
                          None if self.H_t is None else self.H_t[sel])


@compiled_kernel(point.h_kernel, inverse_depth.h_kernel)
def h_feature_kernel(kind, x, s, anchor, R, dR, model, lens, uv, H_c, H_f):
    """One feature's measurement, by kind (see features/)."""
    if kind == POINT:
        return point.h_kernel(x, s, anchor, R, dR, model, lens, uv, H_c, H_f)
    if kind == INVERSE_DEPTH:
        return inverse_depth.h_kernel(x, s, anchor, R, dR, model, lens, uv, H_c, H_f)
    uv[:] = np.nan
    return False


@compiled_kernel(h_feature_kernel, rotation_kernel, rotation_derivatives_kernel)
def h_many_kernel(x, kinds, starts, anchors, ks, model, lens):
    """:func:`h_feature_kernel` over the features ``ks`` at the mean ``x``."""
    R = rotation_kernel(x[3], x[4], x[5], x[6])
    dR = rotation_derivatives_kernel(x[3], x[4], x[5], x[6])
    m = ks.shape[0]
    uv = np.empty((m, 2))
    H_c = np.zeros((m, 2, POSE_DIM))
    H_f = np.zeros((m, 2, MAX_FEATURE_DIM))
    valid = np.empty(m, dtype=np.bool_)
    for i in range(m):
        k = ks[i]
        valid[i] = h_feature_kernel(kinds[k], x, starts[k], anchors[k], R, dR, model, lens, uv[i], H_c[i], H_f[i])
    return uv, H_c, H_f, valid


@compiled_kernel(h_feature_kernel, rotation_kernel, rotation_derivatives_kernel)
def uv_many_kernel(x, kinds, starts, anchors, ks, model, lens):
    """Only the predicted pixels (m, 2) of features ``ks`` at the mean ``x`` (NaN: no image)."""
    R = rotation_kernel(x[3], x[4], x[5], x[6])
    dR = rotation_derivatives_kernel(x[3], x[4], x[5], x[6])
    m = ks.shape[0]
    uv = np.empty((m, 2))
    H_c = np.empty((2, POSE_DIM))
    H_f = np.empty((2, MAX_FEATURE_DIM))
    for i in range(m):
        k = ks[i]
        if not h_feature_kernel(kinds[k], x, starts[k], anchors[k], R, dR, model, lens, uv[i], H_c, H_f):
            uv[i, 0] = np.nan
            uv[i, 1] = np.nan
    return uv


def image_velocity(x, H_c: np.ndarray) -> np.ndarray:
    """(m, 2) px/s: how fast the predicted pixels move with the camera's velocity and rate in
    ``x`` (``d uv/dt = d uv/dr v + d uv/dq q_dot``, ``q_dot = q (0, w) / 2``), from the pose
    Jacobians ``H_c`` (m, 2, 7)."""
    q_dot = 0.5 * quat_multiply(x[Q_SLICE], np.r_[0.0, x[W_SLICE]])
    return H_c[:, :, :3] @ x[V_SLICE] + H_c[:, :, 3:7] @ q_dot


def predict(state: State, ks, cam: CameraIntrinsics, x=None) -> Prediction:
    """Predicted measurements of the features ``ks`` of ``state`` (at ``x`` if given, e.g. a
    RANSAC hypothesis or an updated mean with the same layout).

    With the IMU's clock offset ``t_d`` in the state, the camera block runs on the IMU's
    stamps and was propagated to the image's time plus ``t_ref`` (the offset's estimate then),
    so a feature is predicted where it is ``t_d - t_ref`` later: ``uv + (t_d - t_ref) d uv/dt``
    (first order; ``H_t = d uv/dt``)."""
    ks = np.ascontiguousarray(np.asarray(ks, dtype=np.intp).reshape(-1))
    model, lens = lens_kernel_args(cam)
    xs = state.x if x is None else np.ascontiguousarray(x, dtype=float)
    uv, H_c, H_f, valid = h_many_kernel(xs, state.kinds, state.starts, state.anchors, ks, model, lens)
    if not state.has_time_offset:
        return Prediction(ks, uv, H_c, H_f, valid)
    H_t = image_velocity(xs, H_c)
    return Prediction(ks, uv + (xs[TD_INDEX] - state.t_ref) * H_t, H_c, H_f, valid, H_t)


def predict_uv(state: State, ks, cam: CameraIntrinsics, x=None) -> np.ndarray:
    """(m, 2) predicted pixels of features ``ks`` (NaN: no image)."""
    if state.has_time_offset:
        return predict(state, ks, cam, x).uv
    ks = np.ascontiguousarray(np.asarray(ks, dtype=np.intp).reshape(-1))
    model, lens = lens_kernel_args(cam)
    xs = state.x if x is None else np.ascontiguousarray(x, dtype=float)
    return uv_many_kernel(xs, state.kinds, state.starts, state.anchors, ks, model, lens)


def predict_points(x_v, Y, cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points ``Y`` (k, 3) seen from the camera ``x_v``: uv (k, 2) px, d(uv)/d(r, q)
    (k, 2, 7) and valid (k,) (points not in the state, e.g. a particle ray's depths)."""
    Y = np.asarray(Y, float).reshape(-1, 3)
    x = np.ascontiguousarray(np.concatenate([np.asarray(x_v, float)[:POSE_DIM], Y.ravel()]))
    k = len(Y)
    ks = np.arange(k, dtype=np.intp)
    model, lens = lens_kernel_args(cam)
    uv, H_c, _, valid = h_many_kernel(x, np.zeros(k, np.intp), (POSE_DIM + 3 * ks).astype(np.intp),
                                      np.zeros((k, 3, 3)), ks, model, lens)
    return uv, H_c, valid


def ray_from_pixel(x_v, uv, cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The world ray through pixel ``uv``: a feature seen there lies on ``r + lambda d``.

    Returns origin ``r`` (3,), unit direction ``d = R(q) ray_cam / |ray_cam|`` (3,) (world),
    ``dd/dx_v`` (3, len(x_v)) (only the q columns are nonzero) and ``dd/duv`` (3, 2). A pixel
    the lens cannot undistort gives NaN.
    """
    x_v = np.asarray(x_v, dtype=float)
    r, q = x_v[R_SLICE], x_v[Q_SLICE]
    h, J_h = unproject_jacobian(cam, np.asarray(uv, dtype=float).reshape(1, 2))
    h, J_h = h[0], J_h[0]
    nh = float(np.linalg.norm(h))
    ray_c = h / nh
    J_ray = (np.eye(3) - np.outer(ray_c, ray_c)) @ J_h / nh
    R = quat_to_rotation(q)
    dd_dx = np.zeros((3, len(x_v)))
    dd_dx[:, Q_SLICE] = (rotation_derivatives(q) @ ray_c).T
    return r.copy(), R @ ray_c, dd_dx, R @ J_ray


def init_point_from_depth(x_v, uv, depth: float, cam: CameraIntrinsics
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 3D point from a pixel and a depth (MonoSLAM's lambda: distance along the unit ray, m),
    with its Jacobians: y (3,), dy/dx_v (3, len(x_v)), dy/duv (3, 2), dy/ddepth (3,)."""
    r, d, dd_dx, dd_duv = ray_from_pixel(x_v, uv, cam)
    depth = float(depth)
    dy_dx = depth * dd_dx
    dy_dx[:, R_SLICE] += np.eye(3)
    return r + depth * d, dy_dx, depth * dd_duv, d
