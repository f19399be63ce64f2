"""MonoSLAM's measurement model: where a point feature should appear in the image, with the
Jacobians the EKF needs, and the inverse geometry used to initialise features.

Measurement of feature ``y`` (world, m) from camera ``x_v`` (state.py)::

    P_cam = R(q)^T (y - r)          point in the optical frame (x right, y down, z forward)
    h     = project(cam, P_cam)     pixels, through the camera's lens model (kinematics.camera)

``d(h)/d(P_cam)`` comes from :func:`kinematics.camera.project_jacobian` (any lens model);
``d(P_cam)/dq_i = (dR/dq_i)^T (y - r)`` with :func:`rotation_derivatives` written out
explicitly; ``d(P_cam)/dr = -R^T``, ``d(P_cam)/dy = R^T``; ``h`` does not depend on ``v, w``.
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

from kinematics.camera import CameraIntrinsics, project_jacobian, unproject_jacobian

from .state import CAMERA_DIM, Q_SLICE, R_SLICE, quat_to_rotation, rotation_derivatives


class Projection(NamedTuple):
    """What :func:`h_and_jacobians` returns (unpack as ``uv, H_x, H_y, valid = ...``)."""

    uv: np.ndarray    #: (2,) predicted pixel position (NaN if not valid)
    H_x: np.ndarray   #: (2, 13) d(uv)/d(x_v); columns of v and w are zero
    H_y: np.ndarray   #: (2, 3) d(uv)/d(y)
    valid: bool       #: in front of the camera (Z > 0) and inside the lens model's domain


def _split_camera(x_v):
    x_v = np.asarray(x_v, dtype=float).reshape(-1)
    if x_v.shape != (CAMERA_DIM,):
        raise ValueError(f"x_v must have {CAMERA_DIM} numbers (r, q wxyz, v, w), got {x_v.shape}")
    return x_v[R_SLICE], x_v[Q_SLICE]


def h_and_jacobians_many(x_v, Y, cam: CameraIntrinsics
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`h_and_jacobians` for many features at once, vectorised.

    x_v : (13,) camera block. Y : (N, 3) world points, m.
    Returns uv (N, 2) px, H_x (N, 2, 13), H_y (N, 2, 3), valid (N,) bool.
    """
    r, q = _split_camera(x_v)
    Y = np.asarray(Y, dtype=float).reshape(-1, 3)
    R = quat_to_rotation(q)
    d = Y - r                                   # (N, 3) world offsets
    P_cam = d @ R                               # rows are R^T d
    uv, J_proj = project_jacobian(cam, P_cam)   # (N, 2), (N, 2, 3) d(uv)/d(P_cam)
    # d(P_cam)/dq_i = (dR/dq_i)^T d:  [n, k, i] = sum_j d[n, j] dR[i, j, k]
    dPc_dq = np.einsum("nj,ijk->nki", d, rotation_derivatives(q))
    H_x = np.zeros((len(Y), 2, CAMERA_DIM))
    H_y = J_proj @ R.T                          # d(P_cam)/dy = R^T
    H_x[:, :, R_SLICE] = -H_y                   # d(P_cam)/dr = -R^T
    H_x[:, :, Q_SLICE] = J_proj @ dPc_dq
    valid = (P_cam[:, 2] > 0) & np.isfinite(uv).all(axis=1)
    H_x[~valid] = np.nan
    H_y[~valid] = np.nan
    return uv, H_x, H_y, valid


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
