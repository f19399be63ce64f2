"""What every feature model's measurement ends in: a world-frame vector ``d`` (the feature
relative to the camera centre, up to a positive scale) seen by the camera (r, q)::

    P_cam = R(q)^T d                 the vector in the optical frame
    h     = project(cam, P_cam)      pixels, through the lens model (kinematics.camera)

with ``d(P_cam)/dq_i = (dR/dq_i)^T d`` and, for ``d = scale (y - r) + ...``,
``d(P_cam)/dr = -scale R^T``. The feature models chain their own ``d(d)/d(feature)`` onto
``J R^T`` (J: the lens kernel's ``d(h)/d(P_cam)``).
"""

from __future__ import annotations

import numpy as np

from kinematics.camera import project_point_kernel

from ..kernels import compiled_kernel


@compiled_kernel(project_point_kernel)
def ray_kernel(d0, d1, d2, scale, R, dR, model, lens, uv, H_c, JR):
    """Project ``d`` (world frame) through the camera with rotation ``R`` (3, 3) and its
    quaternion derivatives ``dR`` (4, 3, 3). Writes uv (2,) px, ``H_c`` (2, 7) =
    d(uv)/d(r, q) with ``d(d)/dr = -scale I``, and ``JR[:, :3]`` = J R^T = d(uv)/d(d) (``JR``
    (2, >= 3): the caller's feature Jacobian, which it then completes). Returns whether ``d``
    has an image (in front of the camera, inside the lens model's domain); if not, ``H_c`` and
    ``JR`` are NaN."""
    X = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
    Y = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
    Z = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
    u, v, j00, j01, j02, j10, j11, j12 = project_point_kernel(model, lens, X, Y, Z)
    uv[0], uv[1] = u, v
    if not (Z > 0 and np.isfinite(u) and np.isfinite(v)):
        H_c[:, :] = np.nan
        JR[:, :] = np.nan
        return False
    for a in range(2):
        ja0, ja1, ja2 = (j00, j01, j02) if a == 0 else (j10, j11, j12)
        for c in range(3):
            h = ja0 * R[c, 0] + ja1 * R[c, 1] + ja2 * R[c, 2]
            JR[a, c] = h
            H_c[a, c] = -scale * h
        for i in range(4):
            H_c[a, 3 + i] = (ja0 * (d0 * dR[i, 0, 0] + d1 * dR[i, 1, 0] + d2 * dR[i, 2, 0])
                             + ja1 * (d0 * dR[i, 0, 1] + d1 * dR[i, 1, 1] + d2 * dR[i, 2, 1])
                             + ja2 * (d0 * dR[i, 0, 2] + d1 * dR[i, 1, 2] + d2 * dR[i, 2, 2]))
    return True
