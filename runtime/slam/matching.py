"""The frame's active search over all the features it measures at once (paper, section 4.1), in
one compiled pass: each feature's template predicted for the current view by the homography its
plane induces (templates.py explains the geometry) and matched by zero-mean normalised
cross-correlation at every pixel inside its 3-sigma ellipse, with a parabolic sub-pixel fit.

The score is ``2 (1 - ZNCC)`` as in search.py (0 for identical patches up to gain and offset,
2 for unrelated ones); a warped template that matches nothing is retried as first seen (the
plane guess may be wrong). The templates are warped in one compiled pass; the correlation is
OpenCV's ``matchTemplate`` over each ellipse's box (faster than compiled loops here); windows
too flat to hold a match are excluded by their variance.

The best position is refined to sub-pixel precision by Gauss-Newton on the template under an
affine warp about its centre (Lucas-Kanade, inverse compositional; the shape is damped towards
the prediction): a parabola through the correlation peak errs by a tenth of a pixel or more with
the sub-pixel phase, and a template predicted with a slightly wrong plane or pose, if only
translated, is pulled off its feature by a few tenths, a bias that grows as the view leaves the
first one (the twin's tracks measured against their true projections; benchmarks/NOTES.md).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args

from .kernels import compiled_kernel
from .quaternion import quat_to_rotation
from .templates import MapFeature, plane_corners_kernel

#: A window flatter than this grey-level variance cannot hold a match (ZNCC is noise there).
FLAT_VARIANCE = 4.0
#: The sub-pixel refinement's damping of the template's shape towards the predicted one
#: (affine Gauss-Newton; larger: closer to translation only).
AFFINE_DAMPING = 1.0


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


@compiled_kernel()
def _best_in_ellipse(ncc, roi, u0, v0, h, uv, S, n2):
    """The least score ``2 (1 - ZNCC)`` among the window positions inside the ellipse ``n2`` of
    S at uv (``ncc`` (nv, nu): OpenCV's TM_CCOEFF_NORMED of the template over ``roi``, the
    image from pixel (u0 - h, v0 - h), so that ncc[j, i] is the window centred on (u0 + i,
    v0 + j)), flat windows excluded, with a parabolic sub-pixel fit through the neighbours in
    each direction when both are inside. Returns (u, v, score); score 2 if none."""
    nv, nu = ncc.shape
    # The windows' sums and sums of squares from the region's own integral images (the region
    # is what matchTemplate read: a few thousand pixels, not the whole image).
    rh, rw = roi.shape
    ii = np.zeros((rh + 1, rw + 1))
    ii2 = np.zeros((rh + 1, rw + 1))
    for y in range(rh):
        row = 0.0
        row2 = 0.0
        for x in range(rw):
            g = np.float64(roi[y, x])
            row += g
            row2 += g * g
            ii[y + 1, x + 1] = ii[y, x + 1] + row
            ii2[y + 1, x + 1] = ii2[y, x + 1] + row2
    a, b, c = S[0, 0], S[0, 1], S[1, 1]
    det = a * c - b * b
    iaa, iab, ibb = c / det, -b / det, a / det
    t = 2 * h + 1
    n = t * t
    grid = np.full((nv, nu), np.inf)
    best, bi, bj = np.inf, -1, -1
    for j in range(nv):
        dv = v0 + j - uv[1]
        for i in range(nu):
            du = u0 + i - uv[0]
            if iaa * du * du + 2.0 * iab * du * dv + ibb * dv * dv > n2:
                continue
            sw = ii[j + t, i + t] - ii[j, i + t] - ii[j + t, i] + ii[j, i]
            sw2 = ii2[j + t, i + t] - ii2[j, i + t] - ii2[j + t, i] + ii2[j, i]
            if sw2 - sw * sw / n < FLAT_VARIANCE * n:
                continue
            s = 2.0 * (1.0 - ncc[j, i])
            grid[j, i] = s
            if s < best:
                best, bi, bj = s, i, j
    if bi < 0:
        return np.nan, np.nan, 2.0
    su = sv = 0.0
    if 0 < bi < nu - 1 and np.isfinite(grid[bj, bi - 1]) and np.isfinite(grid[bj, bi + 1]):
        su = _parabola(grid[bj, bi - 1], best, grid[bj, bi + 1])
    if 0 < bj < nv - 1 and np.isfinite(grid[bj - 1, bi]) and np.isfinite(grid[bj + 1, bi]):
        sv = _parabola(grid[bj - 1, bi], best, grid[bj + 1, bi])
    return u0 + bi + su, v0 + bj + sv, best


@compiled_kernel()
def refine_affine_kernel(img, tpl, u, v, iterations, tol, reg):
    """Sub-pixel refinement of a match at (u, v) px by Gauss-Newton on the zero-mean, unit-norm
    template under an affine warp about its centre (inverse compositional; ``reg`` damps the
    linear part towards the identity): the template's shape is fitted to the image too, so a
    template predicted with a slightly wrong warp does not pull its centre off the feature.
    Returns (u, v, ok): ok False if it leaves the image, diverges or moves over a pixel."""
    H, W = img.shape
    t = tpl.shape[0]
    h = t // 2
    T = tpl.astype(np.float64)
    T = T - T.mean()
    nt = math.sqrt((T * T).sum())
    if nt < 1e-9:
        return u, v, False
    T /= nt
    n = t * t
    SD = np.empty((n, 6))
    k = 0
    for b in range(t):
        for a in range(t):
            a0, a1 = max(a - 1, 0), min(a + 1, t - 1)
            b0, b1 = max(b - 1, 0), min(b + 1, t - 1)
            gx = (T[b, a1] - T[b, a0]) / (a1 - a0)
            gy = (T[b1, a] - T[b0, a]) / (b1 - b0)
            x, y = a - h, b - h
            SD[k, 0], SD[k, 1], SD[k, 2], SD[k, 3], SD[k, 4], SD[k, 5] = gx * x, gy * x, gx * y, gy * y, gx, gy
            k += 1
    Hs = SD.T @ SD
    for i in range(4):
        Hs[i, i] += reg
    if abs(np.linalg.det(Hs)) < 1e-18:
        return u, v, False
    Hinv = np.linalg.inv(Hs)
    A = np.eye(2)                     # the current warp: x_img = A x + (u, v)
    cu, cv = u, v
    Wv = np.empty(n)
    for _ in range(iterations):
        k = 0
        ok = True
        for b in range(t):
            for a in range(t):
                x, y = a - h, b - h
                px = A[0, 0] * x + A[0, 1] * y + cu
                py = A[1, 0] * x + A[1, 1] * y + cv
                if not (0.0 <= px < W - 1 and 0.0 <= py < H - 1):
                    ok = False
                    break
                ix, iy = int(px), int(py)
                fx, fy = px - ix, py - iy
                Wv[k] = ((1 - fx) * (1 - fy) * img[iy, ix] + fx * (1 - fy) * img[iy, ix + 1]
                         + (1 - fx) * fy * img[iy + 1, ix] + fx * fy * img[iy + 1, ix + 1])
                k += 1
            if not ok:
                break
        if not ok:
            return u, v, False
        Wv -= Wv.mean()
        nw = math.sqrt((Wv * Wv).sum())
        if nw < 1e-9:
            return u, v, False
        g = np.zeros(6)
        k = 0
        for b in range(t):
            for a in range(t):
                e = Wv[k] / nw - T[b, a]
                for i in range(6):
                    g[i] += SD[k, i] * e
                k += 1
        dp = Hinv @ g
        # Inverse compositional: W <- W o W(dp)^-1, W(dp) = [[1 + p0, p2], [p1, 1 + p3]] x + (p4, p5)
        D = np.array([[1.0 + dp[0], dp[2]], [dp[1], 1.0 + dp[3]]])
        dd = 1.0 / (D[0, 0] * D[1, 1] - D[0, 1] * D[1, 0])
        Di = np.array([[D[1, 1] * dd, -D[0, 1] * dd], [-D[1, 0] * dd, D[0, 0] * dd]])
        ti = -(Di @ np.array([dp[4], dp[5]]))
        cu, cv = A[0, 0] * ti[0] + A[0, 1] * ti[1] + cu, A[1, 0] * ti[0] + A[1, 1] * ti[1] + cv
        A = A @ Di
        if abs(cu - u) > 1.0 or abs(cv - v) > 1.0 or not (0.5 < abs(np.linalg.det(A)) < 2.0):
            return u, v, False
        if dp[4] * dp[4] + dp[5] * dp[5] < tol * tol and abs(dp[0]) + abs(dp[1]) + abs(dp[2]) + abs(dp[3]) < tol:
            break
    return cu, cv, True


@compiled_kernel()
def _parabola(a, b, c):
    d = a - 2 * b + c
    return 0.0 if abs(d) < 1e-12 else min(max(0.5 * (a - c) / d, -0.5), 0.5)


@compiled_kernel(plane_corners_kernel, _homography, _warp)
def warp_kernel(templates, patches, warp, rays0, normals, r0s, ys, r, R, model, lens):
    """Each feature's template predicted for the current camera (r, R): (m, t, t) float32, and
    whether it was warped (m,) (else it is the first-view template)."""
    m, t = templates.shape[0], templates.shape[1]
    h = t // 2
    ph = patches.shape[1] // 2
    out = templates.copy()
    done = np.zeros(m, np.bool_)
    src = np.empty((4, 2))
    dst = np.empty((4, 2))
    for i in range(m):
        if not warp[i]:
            continue
        corners = plane_corners_kernel(rays0[i], normals[i], r0s[i], ys[i], r, R, model, lens)
        if not np.isfinite(corners).all():
            continue
        side = math.hypot(corners[1, 0] - corners[0, 0], corners[1, 1] - corners[0, 1]) / (2 * h)
        if not 0.5 < side < 2.0:                  # the template no longer describes the feature
            continue
        cu, cv = corners[4, 0], corners[4, 1]
        # template pixel (a, b) <-> current image (cu - h + a, cv - h + b) <-> first-view patch
        src[0, 0], src[0, 1] = ph - h, ph - h
        src[1, 0], src[1, 1] = ph + h, ph - h
        src[2, 0], src[2, 1] = ph + h, ph + h
        src[3, 0], src[3, 1] = ph - h, ph + h
        for k in range(4):
            dst[k, 0] = corners[k, 0] - (cu - h)
            dst[k, 1] = corners[k, 1] - (cv - h)
        Hm = _homography(dst, src)
        if not np.isfinite(Hm).all():
            continue
        tpl, inside = _warp(patches[i], Hm, t)
        if inside:
            out[i] = tpl
            done[i] = True
    return out, done


def _search(grey, tpl, uv, S, n2, max_area, max_score):
    """(u, v, score) of the best match of ``tpl`` in the ellipse (NaN, NaN, 2 when none); only a
    match scoring at most ``max_score`` is refined to sub-pixel (the others are not used)."""
    H, W = grey.shape
    h = tpl.shape[0] // 2
    a, b, c = float(S[0, 0]), float(S[0, 1]), float(S[1, 1])
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c) and math.isfinite(uv[0])
            and math.isfinite(uv[1]) and a * c - b * b > 0):
        return np.nan, np.nan, 2.0
    hu, hv = math.sqrt(n2 * a), math.sqrt(n2 * c)
    if (2 * hu + 1) * (2 * hv + 1) > max_area:
        return np.nan, np.nan, 2.0
    u0, u1 = max(math.floor(uv[0] - hu), h), min(math.ceil(uv[0] + hu), W - 1 - h)
    v0, v1 = max(math.floor(uv[1] - hv), h), min(math.ceil(uv[1] + hv), H - 1 - h)
    if u1 < u0 or v1 < v0:
        return np.nan, np.nan, 2.0
    roi = grey[v0 - h:v1 + h + 1, u0 - h:u1 + h + 1]
    ncc = cv2.matchTemplate(roi, tpl, cv2.TM_CCOEFF_NORMED)
    u, v, s = _best_in_ellipse(ncc, roi, u0, v0, h, uv, S, n2)
    if np.isfinite(u) and s <= max_score:
        ur, vr, ok = refine_affine_kernel(grey, tpl, u, v, 10, 0.005, AFFINE_DAMPING)
        if ok:
            u, v = ur, vr
    return u, v, s


def match_features(grey: np.ndarray, features: list[MapFeature], warp: np.ndarray,
                   Y: np.ndarray, x_v: np.ndarray, cam: CameraIntrinsics, uv: np.ndarray, S: np.ndarray,
                   max_score: float, max_area: float, n_sigma: float = 3.0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match the map features ``features`` (m) whose predictions are ``uv`` (m, 2) px with
    innovation covariances ``S`` (m, 2, 2): each warped by its plane (through its point ``Y``
    (m, 3), normal ``MapFeature.normal``) where ``warp`` (m,) says so, retried unwarped when the
    warped template finds nothing. ``grey`` : (H, W) float32. Returns z (m, 2) (NaN: not found),
    score (m,), found (m,)."""
    m = len(features)
    z = np.full((m, 2), np.nan)
    score = np.full(m, 2.0)
    if m == 0:
        return z, score, np.zeros(0, bool)
    t = features[0].template.shape[0]
    ph = max((f.patch.shape[0] for f in features if f.patch is not None), default=t)
    templates = np.empty((m, t, t), np.float32)
    patches = np.zeros((m, ph, ph), np.float32)
    rays0 = np.zeros((m, 5, 3))
    normals = np.zeros((m, 3))
    r0s = np.zeros((m, 3))
    use = np.asarray(warp, bool).copy()
    for i, f in enumerate(features):
        templates[i] = f.template
        r0s[i] = f.r0
        if use[i] and f.patch is not None and f.normal is not None and f.patch.shape[0] == ph:
            patches[i] = f.patch
            normals[i] = f.normal
            rays0[i] = f.first_view_rays(cam)
        else:
            use[i] = False
    model, lens = lens_kernel_args(cam)
    tpls, warped = warp_kernel(templates, patches, use, rays0, normals, r0s, np.ascontiguousarray(Y, float),
                               np.ascontiguousarray(x_v[:3], float), quat_to_rotation(x_v[3:7]), model, lens)
    n2 = n_sigma * n_sigma
    for i in range(m):
        u, v, s = _search(grey, tpls[i], uv[i], S[i], n2, max_area, max_score)
        if s > max_score and warped[i]:
            u, v, s = _search(grey, templates[i], uv[i], S[i], n2, max_area, max_score)
        z[i], score[i] = (u, v), s
    found = score <= max_score
    return z, score, found
