"""A feature's template predicted for the current view: the first-view patch warped by the
homography its plane induces between the first view and this one (plane.py gives the corners;
search.py searches with the result, normals.py fits the plane to the looks)."""

from __future__ import annotations

import math

import numpy as np

from ..kernels import compiled_kernel
from .plane import plane_corners_kernel


@compiled_kernel()
def _homography(src, dst):
    """(3, 3) H with dst ~ H src for 4 point pairs (4, 2) (DLT with h33 = 1); NaN if singular."""
    A = np.zeros((8, 8))
    b = np.zeros(8)
    for k in range(4):
        x, y = src[k, 0], src[k, 1]
        u, v = dst[k, 0], dst[k, 1]
        A[2 * k, 0], A[2 * k, 1], A[2 * k, 2] = x, y, 1.0
        A[2 * k, 6], A[2 * k, 7] = -u * x, -u * y
        b[2 * k] = u
        A[2 * k + 1, 3], A[2 * k + 1, 4], A[2 * k + 1, 5] = x, y, 1.0
        A[2 * k + 1, 6], A[2 * k + 1, 7] = -v * x, -v * y
        b[2 * k + 1] = v
    H = np.full((3, 3), np.nan)
    if abs(np.linalg.det(A)) < 1e-12:
        return H
    h = np.linalg.solve(A, b)
    for i in range(8):
        H[i // 3, i % 3] = h[i]
    H[2, 2] = 1.0
    return H


@compiled_kernel()
def _warp(patch, H, t):
    """The (t, t) template whose pixel (a, b) samples ``patch`` bilinearly at H (a, b, 1); None
    flag False if any sample falls outside the patch."""
    p = patch.shape[0]
    out = np.empty((t, t), np.float32)
    for b in range(t):
        for a in range(t):
            w = H[2, 0] * a + H[2, 1] * b + H[2, 2]
            x = (H[0, 0] * a + H[0, 1] * b + H[0, 2]) / w
            y = (H[1, 0] * a + H[1, 1] * b + H[1, 2]) / w
            if not (0.0 <= x <= p - 1.001 and 0.0 <= y <= p - 1.001):
                return out, False
            x0, y0 = int(x), int(y)
            fx, fy = x - x0, y - y0
            out[b, a] = ((1 - fx) * (1 - fy) * patch[y0, x0] + fx * (1 - fy) * patch[y0, x0 + 1]
                         + (1 - fx) * fy * patch[y0 + 1, x0] + fx * fy * patch[y0 + 1, x0 + 1])
    return out, True


@compiled_kernel(_homography, _warp)
def _template_from_corners(patch, corners, t, ou, ov):
    """The (t, t) template whose pixel (a, b) is the current image's (ou + a, ov + b), sampled
    from the first-view ``patch`` through the homography that takes the template's corners in
    the patch to ``corners`` (>= 4, 2) px in the current image; and whether the warp was valid
    (every sample inside the patch)."""
    h = t // 2
    ph = patch.shape[0] // 2
    src = np.empty((4, 2))
    dst = np.empty((4, 2))
    src[0, 0], src[0, 1] = ph - h, ph - h
    src[1, 0], src[1, 1] = ph + h, ph - h
    src[2, 0], src[2, 1] = ph + h, ph + h
    src[3, 0], src[3, 1] = ph - h, ph + h
    for k in range(4):
        dst[k, 0] = corners[k, 0] - ou
        dst[k, 1] = corners[k, 1] - ov
    Hm = _homography(dst, src)
    if not np.isfinite(Hm).all():
        return np.empty((t, t), np.float32), False
    return _warp(patch, Hm, t)


@compiled_kernel(plane_corners_kernel, _template_from_corners)
def warp_kernel(templates, patches, warp, rays0, normals, r0s, ys, r, R, model, lens):
    """Each feature's template predicted for the current camera (r, R): (m, t, t) float32, and
    whether it was warped (m,) (else it is the first-view template)."""
    m, t = templates.shape[0], templates.shape[1]
    h = t // 2
    out = templates.copy()
    done = np.zeros(m, np.bool_)
    for i in range(m):
        if not warp[i]:
            continue
        corners = plane_corners_kernel(rays0[i], normals[i], r0s[i], ys[i], r, R, model, lens)
        if not np.isfinite(corners).all():
            continue
        side = math.hypot(corners[1, 0] - corners[0, 0], corners[1, 1] - corners[0, 1]) / (2 * h)
        if not 0.5 < side < 2.0:                  # the template no longer describes the feature
            continue
        # template pixel (a, b) <-> current image (cu - h + a, cv - h + b) <-> first-view patch
        tpl, inside = _template_from_corners(patches[i], corners, t, corners[4, 0] - h, corners[4, 1] - h)
        if inside:
            out[i] = tpl
            done[i] = True
    return out, done
