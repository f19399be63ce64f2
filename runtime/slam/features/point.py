"""A 3D point feature: ``y = (X, Y, Z)``, world frame, m.

Measurement from the camera (r, q) (state.py)::

    P_cam = R(q)^T (y - r)          the point in the optical frame
    h     = project(cam, P_cam)     pixels, through the lens model (kinematics.camera)

Jacobians: ``d(P_cam)/dr = -R^T``, ``d(P_cam)/dq_i = (dR/dq_i)^T (y - r)``,
``d(P_cam)/dy = R^T``, chained with the lens kernel's ``d(h)/d(P_cam)``.
"""

from __future__ import annotations

import numpy as np

from kinematics.camera import project_point_kernel

from ..kernels import compiled_kernel
from . import POINT

KIND = POINT
DIM = 3


@compiled_kernel(project_point_kernel)
def h_kernel(x, s, anchor, R, dR, model, lens, uv, H_c, H_f):
    """The point ``x[s:s+3]`` seen from the camera ``x[0:7]``; ``R``, ``dR`` = R(q), dR/dq
    (computed once per camera); ``anchor`` unused. Writes uv (2,) px, ``H_c`` (2, 7) =
    d(uv)/d(r, q) and ``H_f[:, :3]`` = d(uv)/dy, and returns whether the point has an image
    (in front of the camera, inside the lens model's domain); if not, they are NaN."""
    d0, d1, d2 = x[s] - x[0], x[s + 1] - x[1], x[s + 2] - x[2]
    X = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
    Y = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
    Z = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
    u, v, j00, j01, j02, j10, j11, j12 = project_point_kernel(model, lens, X, Y, Z)
    uv[0], uv[1] = u, v
    if not (Z > 0 and np.isfinite(u) and np.isfinite(v)):
        H_c[:, :] = np.nan
        H_f[:, :] = np.nan
        return False
    for a in range(2):
        ja0, ja1, ja2 = (j00, j01, j02) if a == 0 else (j10, j11, j12)
        for c in range(3):
            h = ja0 * R[c, 0] + ja1 * R[c, 1] + ja2 * R[c, 2]
            H_f[a, c] = h
            H_c[a, c] = -h
        for i in range(4):
            H_c[a, 3 + i] = (ja0 * (d0 * dR[i, 0, 0] + d1 * dR[i, 1, 0] + d2 * dR[i, 2, 0])
                             + ja1 * (d0 * dR[i, 0, 1] + d1 * dR[i, 1, 1] + d2 * dR[i, 2, 1])
                             + ja2 * (d0 * dR[i, 0, 2] + d1 * dR[i, 1, 2] + d2 * dR[i, 2, 2]))
    return True


def world_point(y, anchor=None) -> np.ndarray:
    """(3,) the point itself."""
    return np.asarray(y, float).reshape(3).copy()
