"""A 3D point feature: ``y = (X, Y, Z)``, world frame, m.

Measurement from the camera (r, q) (state.py)::

    P_cam = R(q)^T (y - r)          the point in the optical frame
    h     = project(cam, P_cam)     pixels, through the lens model (kinematics.camera)

Jacobians: ``d(P_cam)/dr = -R^T``, ``d(P_cam)/dq_i = (dR/dq_i)^T (y - r)``,
``d(P_cam)/dy = R^T``, chained with the lens kernel's ``d(h)/d(P_cam)``.
"""

from __future__ import annotations

import numpy as np

from ..kernels import compiled_kernel
from ..layout import POINT
from .ray import ray_kernel

KIND = POINT
DIM = 3


@compiled_kernel(ray_kernel)
def h_kernel(x, s, anchor, R, dR, model, lens, uv, H_c, H_f):
    """The point ``x[s:s+3]`` seen from the camera ``x[0:7]``; ``R``, ``dR`` = R(q), dR/dq
    (computed once per camera); ``anchor`` unused. Writes uv (2,) px, ``H_c`` (2, 7) =
    d(uv)/d(r, q) and ``H_f[:, :3]`` = d(uv)/dy, and returns whether the point has an image
    (in front of the camera, inside the lens model's domain); if not, they are NaN."""
    # d = y - r: d(d)/dy = I, so d(uv)/dy is the ray's J R^T itself.
    return ray_kernel(x[s] - x[0], x[s + 1] - x[1], x[s + 2] - x[2], 1.0, R, dR, model, lens, uv, H_c, H_f)


def world_point(y, anchor=None) -> np.ndarray:
    """(3,) the point itself."""
    return np.asarray(y, float).reshape(3).copy()
