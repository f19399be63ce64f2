"""MonoSLAM's measurement model: where a point feature should appear in the image, with the
Jacobians the EKF needs, and the inverse geometry used to initialise features.

Measurement of feature ``y`` (world, m) from camera ``x_v`` (state.py)::

    P_cam = R(q)^T (y - r)          point in the optical frame (x right, y down, z forward)
    h     = project(cam, P_cam)     pixels, through the camera's lens model (kinematics.camera)

``d(h)/d(P_cam)`` comes from the lens kernel behind :func:`kinematics.camera.project_jacobian`
(:func:`kinematics.camera.project_point_kernel`, any lens model);
``d(P_cam)/dq_i = (dR/dq_i)^T (y - r)`` with :func:`rotation_derivatives` written out
explicitly; ``d(P_cam)/dr = -R^T``, ``d(P_cam)/dy = R^T``; ``h`` does not depend on ``v, w``.
The model is written once, as the compiled (numba) one-point kernel :func:`h_point_kernel`,
which the vectorised functions loop over points and the EKF's sequential update
(filter.SequentialUpdate) calls once per measured feature at the current mean.
The quaternion enters through the homogeneous formula for ``R(q)``, so Jacobians with respect to
``q`` are derivatives in R^4 (state.py explains; ``H_q q = 0`` because projection ignores the
scale of ``P_cam``).

Points with no image
--------------------
A feature on or behind the camera plane (``Z <= 0`` in the optical frame), or outside a
radial-sqrt lens's domain, gets ``uv = NaN`` and NaN Jacobians, and the flag ``valid`` is
False; nothing is raised here. :func:`runtime.slam.filter.update` refuses to use such a feature.
Whether a valid point falls inside the image is a separate question
(:func:`kinematics.camera.in_image`).

Image measurement noise ``R`` is a (2, 2) covariance in px^2 (``SlamConfig.R_pix``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args, project_point_kernel, unproject_jacobian

from .state import (CAMERA_DIM, Q_SLICE, R_SLICE, compiled_kernel, quat_to_rotation, rotation_derivatives,
                    rotation_derivatives_kernel, rotation_kernel)


class Projection(NamedTuple):
    """What :func:`h_and_jacobians` returns (unpack as ``uv, H_x, H_y, valid = ...``)."""

    uv: np.ndarray    #: (2,) predicted pixel position (NaN if not valid)
    H_x: np.ndarray   #: (2, 13) d(uv)/d(x_v); columns of v and w are zero
    H_y: np.ndarray   #: (2, 3) d(uv)/d(y)
    valid: bool       #: in front of the camera (Z > 0) and inside the lens model's domain


def _camera_block(x_v) -> np.ndarray:
    """``x_v`` as a C-contiguous (13,) float64 array (the layout the kernel is compiled for)."""
    x_v = np.ascontiguousarray(np.asarray(x_v, dtype=np.float64).reshape(-1))
    if x_v.shape != (CAMERA_DIM,):
        raise ValueError(f"x_v must have {CAMERA_DIM} numbers (r, q wxyz, v, w), got {x_v.shape}")
    return x_v


def _split_camera(x_v):
    x_v = _camera_block(x_v)
    return x_v[R_SLICE], x_v[Q_SLICE]


@compiled_kernel(project_point_kernel)
def h_point_kernel(x_v, R, dR, y0, y1, y2, model, lens, uv, H_x, H_y):
    """The measurement model for one point, compiled (numba); the one implementation behind
    :func:`h_and_jacobians_many` and the EKF's per-feature path (filter.SequentialUpdate).

    x_v (13,) camera block; R = R(q) (3, 3) and dR = dR/dq (4, 3, 3) of its quaternion
    (:func:`runtime.slam.state.rotation_kernel`, computed once per camera); (y0, y1, y2) the world
    point, m; the camera as :func:`kinematics.camera.lens_kernel_args`. Writes uv (2,) px,
    H_x (2, 13) and H_y (2, 3) (NaN when not valid; the v, w columns of H_x are left as given)
    and returns valid: in front of the camera and inside the lens model's domain.
    """
    d0, d1, d2 = y0 - x_v[0], y1 - x_v[1], y2 - x_v[2]          # world offset y - r, m
    # P_cam = R^T (y - r), optical frame, m
    X = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
    Y = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
    Z = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
    u, v, j00, j01, j02, j10, j11, j12 = project_point_kernel(model, lens, X, Y, Z)  # d(uv)/d(P_cam)
    uv[0], uv[1] = u, v
    if not (Z > 0 and np.isfinite(u) and np.isfinite(v)):
        H_x[:, :7] = np.nan
        H_y[:, :] = np.nan
        return False
    for a in range(2):
        ja0, ja1, ja2 = (j00, j01, j02) if a == 0 else (j10, j11, j12)
        for c in range(3):
            # d(P_cam)/dy = R^T, d(P_cam)/dr = -R^T
            h = ja0 * R[c, 0] + ja1 * R[c, 1] + ja2 * R[c, 2]
            H_y[a, c] = h
            H_x[a, c] = -h
        for i in range(4):
            # d(P_cam)/dq_i = (dR/dq_i)^T (y - r)
            H_x[a, 3 + i] = (ja0 * (d0 * dR[i, 0, 0] + d1 * dR[i, 1, 0] + d2 * dR[i, 2, 0])
                             + ja1 * (d0 * dR[i, 0, 1] + d1 * dR[i, 1, 1] + d2 * dR[i, 2, 1])
                             + ja2 * (d0 * dR[i, 0, 2] + d1 * dR[i, 1, 2] + d2 * dR[i, 2, 2]))
    return True


@compiled_kernel(h_point_kernel, rotation_kernel, rotation_derivatives_kernel)
def _h_many_kernel(x_v, Y, model, lens):
    """:func:`h_point_kernel` over the rows of Y (N, 3); see :func:`h_and_jacobians_many`."""
    R = rotation_kernel(x_v[3], x_v[4], x_v[5], x_v[6])                # camera -> world
    dR = rotation_derivatives_kernel(x_v[3], x_v[4], x_v[5], x_v[6])   # (4, 3, 3) dR/dq_i
    n = Y.shape[0]
    uv = np.empty((n, 2))
    H_x = np.zeros((n, 2, CAMERA_DIM))
    H_y = np.empty((n, 2, 3))
    valid = np.empty(n, dtype=np.bool_)
    for i in range(n):
        valid[i] = h_point_kernel(x_v, R, dR, Y[i, 0], Y[i, 1], Y[i, 2], model, lens, uv[i], H_x[i], H_y[i])
        if not valid[i]:
            H_x[i] = np.nan      # every column, as documented for invalid points
    return uv, H_x, H_y, valid


def h_and_jacobians_many(x_v, Y, cam: CameraIntrinsics
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`h_and_jacobians` for many features at once (one compiled loop over the points).

    x_v : (13,) camera block. Y : (N, 3) world points, m.
    Returns uv (N, 2) px, H_x (N, 2, 13), H_y (N, 2, 3), valid (N,) bool.
    """
    x_v = _camera_block(x_v)
    Y = np.ascontiguousarray(np.asarray(Y, dtype=np.float64).reshape(-1, 3))
    model, lens = lens_kernel_args(cam)
    return _h_many_kernel(x_v, Y, model, lens)


def h_and_jacobians(x_v, y, cam: CameraIntrinsics) -> Projection:
    """Predicted image position of one feature and its Jacobians.

    x_v : (13,) camera block; y : (3,) world point, m; cam : intrinsics and lens model.
    Returns :class:`Projection` ``(uv (2,), H_x (2, 13), H_y (2, 3), valid)``; see the module
    docstring for invalid points (NaN, ``valid = False``).
    """
    uv, H_x, H_y, valid = h_and_jacobians_many(x_v, np.asarray(y, dtype=float).reshape(1, 3), cam)
    return Projection(uv[0], H_x[0], H_y[0], bool(valid[0]))


def innovation_covariance(P, H, R_meas) -> np.ndarray:
    """``S = H P H^T + R`` for a dense ``H`` (m, n), ``P`` (n, n), ``R`` (m, m); symmetrised.

    (The filter itself never forms dense rows of ``H``; see filter.update.)
    """
    H = np.atleast_2d(np.asarray(H, dtype=float))
    S = H @ np.asarray(P, dtype=float) @ H.T + np.asarray(R_meas, dtype=float)
    return 0.5 * (S + S.T)


def ray_from_pixel(x_v, uv, cam: CameraIntrinsics
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The world ray through pixel ``uv``: a feature seen there lies on ``r + lambda d``.

    Returns origin ``r`` (3,) (the optical centre), unit direction ``d = R(q) ray_cam`` (3,)
    in the world frame (unit for a unit ``q``), ``dd/dx_v`` (3, 13) (only the ``q`` columns are
    nonzero; derivative of the homogeneous ``R(q)`` in R^4) and ``dd/duv`` (3, 2) per pixel.
    ``ray_cam`` comes from :func:`kinematics.camera.unproject_jacobian`; a pixel the lens
    cannot undistort gives NaN.
    """
    r, q = _split_camera(x_v)
    ray_c, J_ray = unproject_jacobian(cam, np.asarray(uv, dtype=float).reshape(1, 2))
    ray_c, J_ray = ray_c[0], J_ray[0]
    R = quat_to_rotation(q)
    d = R @ ray_c
    dd_dx = np.zeros((3, CAMERA_DIM))
    dd_dx[:, Q_SLICE] = (rotation_derivatives(q) @ ray_c).T    # column i = dR/dq_i ray_cam
    return r.copy(), d, dd_dx, R @ J_ray


def init_point_from_depth(x_v, uv, depth: float, cam: CameraIntrinsics
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 3D point from a pixel and a depth, with the Jacobians that carry its uncertainty.

    ``depth`` is MonoSLAM's lambda: the distance (m) from the optical centre along the unit ray
    (not the optical-axis Z). ``y = r + depth * d`` with ``d`` from :func:`ray_from_pixel`.
    Returns y (3,), dy/dx_v (3, 13), dy/duv (3, 2), dy/ddepth (3,).
    """
    r, d, dd_dx, dd_duv = ray_from_pixel(x_v, uv, cam)
    depth = float(depth)
    dy_dx = depth * dd_dx
    dy_dx[:, R_SLICE] += np.eye(3)
    return r + depth * d, dy_dx, depth * dd_duv, d
