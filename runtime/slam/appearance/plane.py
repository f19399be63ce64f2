"""The plane a feature's patch lies on, and what it does to the template between views: the
patch's corners as the current view sees them on that plane (the homography's four point pairs),
the template warped by it, and the plane fitted to a feature's map neighbours."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args, project_point_kernel

from ..kernels import compiled_kernel
from ..quaternion import quat_to_rotation

if TYPE_CHECKING:
    from ..map_feature import MapFeature


@compiled_kernel(project_point_kernel)
def plane_corners_kernel(rays0, normal, r0, y, r, R, model, params):
    """Pixels (5, 2) in the current view of the first view's patch corners (rows 0-3) and centre
    (row 4) on the plane through ``y`` with ``normal`` (their world rays ``rays0`` (5, 3) from
    ``r0``); all NaN when the warp is invalid (a ray parallel to the plane, a point behind either
    camera). The centre is where the first view's template centre lands, not ``y``'s projection:
    the estimate of ``y`` drifts off that ray, and centring on it would bias the match by the
    estimate's own error."""
    out = np.full((5, 2), np.nan)
    c = normal[0] * (y[0] - r0[0]) + normal[1] * (y[1] - r0[1]) + normal[2] * (y[2] - r0[2])
    for i in range(5):
        den = normal[0] * rays0[i, 0] + normal[1] * rays0[i, 1] + normal[2] * rays0[i, 2]
        if abs(den) < 1e-6:
            return np.full((5, 2), np.nan)
        lam = c / den
        if not lam > 0:
            return np.full((5, 2), np.nan)
        X0, X1, X2 = r0[0] + lam * rays0[i, 0], r0[1] + lam * rays0[i, 1], r0[2] + lam * rays0[i, 2]
        d0, d1, d2 = X0 - r[0], X1 - r[1], X2 - r[2]
        px = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        py = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        pz = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        res = project_point_kernel(model, params, px, py, pz)
        out[i, 0], out[i, 1] = res[0], res[1]
    return out


def local_plane_normal(Y: np.ndarray, k: int, radius: float, tol: float, min_points: int = 4) -> np.ndarray | None:
    """Unit normal (3,) of the plane fitted (least squares) to point ``k`` of ``Y`` (n, 3), m,
    and the points within ``radius`` m of it, if there are at least ``min_points`` of them and
    they are coplanar: RMS distance from the plane at most ``tol`` m, and spread along two
    directions (the second singular value at least 3 times the smallest). Otherwise None."""
    near = np.flatnonzero(np.linalg.norm(Y - Y[k], axis=1) < radius)
    if len(near) < min_points:
        return None
    _, sv, Vt = np.linalg.svd(Y[near] - Y[near].mean(axis=0), full_matrices=False)
    if sv[-1] / math.sqrt(len(near)) > tol or sv[1] < 3 * sv[-1]:
        return None
    return Vt[-1]


def warped_template(f: MapFeature, x_v: np.ndarray, y: np.ndarray, cam: CameraIntrinsics) -> np.ndarray:
    """The feature's template as the current camera ``x_v`` should see it: the first-view patch
    warped by the homography its plane (through the point ``y`` (3,), normal ``f.normal``)
    induces between the two views (computed through the lens model at the patch's corners).
    Falls back to the stored template when the feature has no patch or the warp degenerates."""
    if f.patch is None or f.normal is None:
        return f.template
    h = f.template.shape[0] // 2
    ph = f.patch.shape[0] // 2
    c0 = np.asarray(f.uv0, float)       # the template's and the patch's exact centre
    src = c0 + np.array([[-h, -h], [h, -h], [h, h], [-h, h], [0, 0]], float)
    model, params = lens_kernel_args(cam)
    uvc = plane_corners_kernel(f.first_view_rays(cam), f.normal, f.r0, y, x_v[:3], quat_to_rotation(x_v[3:7]), model, params)
    if not np.all(np.isfinite(uvc)):
        return f.template
    uv, centre = uvc[:4], uvc[4]
    side = np.linalg.norm(uv[1] - uv[0]) / (2 * h)
    if not 0.5 < side < 2.0:                              # the template is no longer valid
        return f.template
    src_p = (src[:4] - (c0 - ph)).astype(np.float32)
    dst_t = (uv - (centre - h)).astype(np.float32)
    M = cv2.getPerspectiveTransform(src_p, dst_t)
    return cv2.warpPerspective(f.patch, M, (2 * h + 1, 2 * h + 1), flags=cv2.INTER_LINEAR)
