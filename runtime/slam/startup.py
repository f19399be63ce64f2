"""Start-up from the known target, with no ground truth anywhere.

``target.toml``'s pixels are a person's clicks: a few pixels off. The start-up finds each known
point in the first image itself (the strongest corner within ``click_search_px`` of the click,
refined to sub-pixel precision by OpenCV's ``cornerSubPix``), then checks that the refined
points make one consistent camera pose (PnP through the lens model, small reprojection error),
and refuses with a message naming the problem when they do not.

The camera's starting uncertainty is what the target can tell: the pose's covariance is
``sigma^2 (J^T J)^-1`` with ``J`` the reprojection Jacobian with respect to the pose (rotation
as a small rotation in the camera frame, position in the world frame) and ``sigma`` the refined
corners' pixel accuracy. A small, far, nearly frontal planar target leaves this covariance long
along the rotation-translation ambiguity, so the natural features can correct it; and a planar
target has two PnP poses (IPPE's pair, the planar pose ambiguity): when the second explains the
corners nearly as well (likelihood ratio under ``ambiguity_ratio``), both are kept as hypotheses
until the map separates them (system.py).

The same target is sought again later when the pose has drifted beyond its corners' search
ellipses: near its prediction (:func:`find_quadrilateral`) or anywhere in the image
(:func:`locate_target`), for system.py's re-acquisition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, in_image, project, project_jacobian, undistort
from kinematics.transforms import rotation_angle, skew

from ..sequence import Target
from .prior import camera_prior, pose_covariance
from .quaternion import quat_from_rotation


class SlamStartError(ValueError):
    """The target cannot start SLAM (not found, not consistent, degenerate); the message says
    why and what to check."""


@dataclass(frozen=True)
class RefinedTarget:
    """xyz (n, 3) world, m; uv (n, 2) the refined pixels; moved_px (n,) how far each moved from
    its click."""

    xyz: np.ndarray
    uv: np.ndarray
    moved_px: np.ndarray


@dataclass(frozen=True)
class PoseHypothesis:
    """A camera pose from the target: R_world_cam (3, 3), r (3,) optical centre (world, m),
    cov (6, 6) of (small rotation in the camera frame, rad; position, m), and its reprojection
    chi-square (sum of squared residuals over sigma^2) and RMS residual, px."""

    R_world_cam: np.ndarray
    r: np.ndarray
    cov: np.ndarray
    chi2: float
    rms_px: float

    def camera_prior(self, v_sigma: float, w_sigma: float, cam_dim: int = 13) -> tuple[np.ndarray, np.ndarray]:
        """The camera block (at rest) and its covariance for this pose: position and quaternion
        from ``cov`` (rotation mapped by dq/dtheta), velocities with the given standard
        deviations, any further entries (bias states) left zero for the caller."""
        q = quat_from_rotation(self.R_world_cam)
        return camera_prior(cam_dim, self.r, q, pose_covariance(q, self.cov), v_sigma, w_sigma)


def refine_clicks(grey: np.ndarray, target: Target, search_px: float) -> RefinedTarget:
    """Each clicked pixel moved to the corner it was meant for: the strongest Shi-Tomasi corner
    within ``search_px`` of the click, refined by ``cornerSubPix``. Raises
    :class:`SlamStartError` for a click with no corner near it or off the image."""
    img = np.ascontiguousarray(grey, np.float32)
    H, W = img.shape
    r = int(math.ceil(search_px))
    pad = r + 6
    refined, moved = [], []
    for i, (u, v) in enumerate(np.asarray(target.uv, float)):
        if not (np.isfinite(u) and np.isfinite(v)):
            raise SlamStartError(f"target.toml: point {i}'s uv is not a number; give its pixel in the first frame")
        u0, v0 = int(round(u)), int(round(v))
        if u0 - pad < 0 or v0 - pad < 0 or u0 + pad >= W or v0 + pad >= H:
            raise SlamStartError(f"target.toml: point {i} at pixel ({u:.1f}, {v:.1f}) is at or beyond the image border; "
                                 "the whole target must be in view in the first frame")
        win = img[v0 - pad:v0 + pad + 1, u0 - pad:u0 + pad + 1]
        resp = cv2.cornerMinEigenVal(win, blockSize=5, ksize=3)
        yy, xx = np.mgrid[-pad:pad + 1, -pad:pad + 1]
        resp[(xx + u0 - u) ** 2 + (yy + v0 - v) ** 2 > search_px ** 2] = 0.0
        j = int(np.argmax(resp))
        peak = resp.flat[j]
        # A corner must stand out from the window's edges and flat parts (a click on a plain
        # surface or an edge gives a weak response).
        if not peak > 0 or peak < 4.0 * np.median(cv2.cornerMinEigenVal(win, blockSize=5, ksize=3)) + 1e-3:
            raise SlamStartError(f"target.toml: no corner within {search_px:g} px of point {i}'s click at "
                                 f"({u:.1f}, {v:.1f}); click the target's corner in the first frame")
        cy, cx = divmod(j, resp.shape[1])
        p = np.array([[[u0 - pad + cx, v0 - pad + cy]]], np.float32)
        cv2.cornerSubPix(img, p, (4, 4), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 0.01))
        q = p.reshape(2).astype(float)
        d = float(np.hypot(q[0] - u, q[1] - v))
        if not d <= search_px + 1.0:
            raise SlamStartError(f"target.toml: point {i}'s corner could not be located near its click at "
                                 f"({u:.1f}, {v:.1f}) (the refinement wandered {d:.1f} px); click closer to it")
        refined.append(q)
        moved.append(d)
    return RefinedTarget(np.asarray(target.xyz, float), np.array(refined), np.array(moved))


#: Edge refinement of a printed quadrilateral's corners (:func:`refine_by_edges`): edge points
#: sampled along each side (away from the corners), the search either side of the side, px,
#: the least edge points a side needs, and the farthest a corner may move from its corner fit, px.
EDGE_SAMPLES, EDGE_SEARCH_PX, EDGE_MIN_POINTS, EDGE_MAX_SHIFT_PX = 24, 3.0, 10, 1.5


def _sample(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at (..., 2) pixel positions (NaN outside). Not cv2.remap:
    OpenCV 4 quantises its linear weights to 1/32 px (5.0 no longer does), coarser than the
    edge fit's hundredths of a pixel."""
    h, w = img.shape
    x, y = pts[..., 0], pts[..., 1]
    ok = (x >= 0) & (y >= 0) & (x <= w - 1.001) & (y <= h - 1.001)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = x - x0, y - y0
    v = ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
         + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])
    return np.where(ok, v, np.nan)


def _edge_points(img: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel edge points along each side from pixel a[i] to b[i] (a, b (s, 2)): points
    (s, EDGE_SAMPLES, 2) and which are kept (s, EDGE_SAMPLES). At each of EDGE_SAMPLES places
    between 15% and 85% of the way, the strongest grey-level step across the side within
    EDGE_SEARCH_PX; places where the step is weak or turns the other way than along the rest of
    its side are left out, and so is every place of a side shorter than 8 px."""
    d = b - a
    L = np.linalg.norm(d, axis=1)
    n = np.column_stack([-d[:, 1], d[:, 0]]) / np.maximum(L, 1e-12)[:, None]
    steps = np.arange(-EDGE_SEARCH_PX, EDGE_SEARCH_PX + 1e-9, 0.25)
    base = a[:, None, :] + np.linspace(0.15, 0.85, EDGE_SAMPLES)[None, :, None] * d[:, None, :]   # (s, k, 2)
    g = np.gradient(_sample(img, base[:, :, None, :] + steps[None, None, :, None] * n[:, None, None, :]), axis=2)
    finite = np.isfinite(g)
    ok = finite.all(axis=2)                                                  # (s, k)
    g = np.where(finite, g, 0.0)
    sign = np.sign((g * ok[:, :, None]).sum(axis=(1, 2)))                 # dark to light or light to dark
    g = np.where(finite, g * sign[:, None, None], -np.inf)
    j = np.argmax(g, axis=2)
    peak = np.take_along_axis(g, j[:, :, None], axis=2)[:, :, 0]
    strong = ok & (peak > 0.5 * np.max(np.where(ok, peak, -np.inf), axis=1, keepdims=True))
    # The step's centre: the centroid of the derivative within 1.5 px of its peak (a bilinear
    # profile's derivative is flat-topped, so a parabola through the peak cannot place it),
    # taken again about the first centroid so that which end of a flat top the argmax chose
    # does not move it.
    pos = np.maximum(g, 0.0)
    t = steps[j]
    for _ in range(2):
        wgt = np.where(np.abs(steps - t[:, :, None]) <= 1.5, pos, 0.0)
        t = (wgt * steps).sum(axis=2) / np.maximum(wgt.sum(axis=2), 1e-12)
    keep = strong & (L >= 8.0)[:, None]
    return base + t[:, :, None] * n[:, None, :], keep


def _fit_lines(xy: np.ndarray, keep: np.ndarray) -> np.ndarray | None:
    """The lines (s, 3) ``l . (x, y, 1) = 0`` with unit normals through each side's kept points
    (xy (s, k, 2), keep (s, k)) by total least squares, once more without the points beyond 3
    robust sigmas; None if a side has fewer than EDGE_MIN_POINTS."""
    keep = keep & np.isfinite(xy).all(axis=2)
    xy = np.where(keep[:, :, None], xy, 0.0)
    for _ in range(2):
        cnt = keep.sum(axis=1)
        if cnt.min() < EDGE_MIN_POINTS:
            return None
        c = (xy * keep[:, :, None]).sum(axis=1) / cnt[:, None]
        dxy = (xy - c[:, None, :]) * keep[:, :, None]
        sxx, syy, sxy = (dxy[:, :, 0] ** 2).sum(1), (dxy[:, :, 1] ** 2).sum(1), (dxy[:, :, 0] * dxy[:, :, 1]).sum(1)
        ang = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)         # each scatter's major axis; the normal is across it
        nrm = np.column_stack([-np.sin(ang), np.cos(ang)])
        r = np.abs(np.einsum("skj,sj->sk", dxy, nrm))
        srt = np.sort(np.where(keep, r, np.inf), axis=1)        # each side's median (nanmedian is slow)
        rows = np.arange(len(srt))
        mad = 0.5 * (srt[rows, (cnt - 1) // 2] + srt[rows, cnt // 2])
        inside = keep & (r <= 3.0 * 1.4826 * mad[:, None] + 1e-12)
        if (inside == keep).all():
            break
        keep = inside
    return np.column_stack([nrm, -(nrm * c).sum(axis=1)])


def refine_by_edges(cam: CameraIntrinsics, grey: np.ndarray, uv: np.ndarray,
                    max_shift_px: float = EDGE_MAX_SHIFT_PX) -> np.ndarray | None:
    """The corners of a printed quadrilateral (uv (4, 2) in order round it, from a corner fit)
    as the intersections of its sides, each fitted to the sub-pixel edge points along it: the
    whole edge's evidence, not a corner window's (cornerSubPix leaves 0.1-0.4 px on the twin's
    blurred, noisy frames). Sides are straight in undistorted coordinates: edge points are
    undistorted, the lines fitted and intersected there, the corners projected back. None when
    the points are not a convex quadrilateral, a side's edge is not found, or a corner would
    move more than ``max_shift_px`` (the corner fit is then kept)."""
    uv = np.asarray(uv, float)
    if uv.shape != (4, 2):
        return None
    nxt = uv[[1, 2, 3, 0]]
    e = nxt - uv                                              # side i: from corner i to i + 1
    e2 = e[[1, 2, 3, 0]]
    cross = e[:, 0] * e2[:, 1] - e[:, 1] * e2[:, 0]
    if not ((cross > 0).all() or (cross < 0).all()):
        return None
    # Only the quadrilateral's neighbourhood is read (the whole frame's conversion would cost
    # more than the fit).
    h, w = grey.shape[:2]
    pad = EDGE_SEARCH_PX + 2.0
    lo = np.maximum(np.floor(uv.min(axis=0) - pad), 0).astype(int)
    hi = np.minimum(np.ceil(uv.max(axis=0) + pad).astype(int) + 1, (w, h))
    if (hi - lo).min() < 2:
        return None
    img = np.asarray(grey[lo[1]:hi[1], lo[0]:hi[0]], np.float64)
    pts, keep = _edge_points(img, uv - lo, nxt - lo)
    xy = undistort(cam, (pts + lo).reshape(-1, 2)).reshape(pts.shape)
    lines = _fit_lines(xy, keep)
    if lines is None:
        return None
    l1, l2 = lines[[3, 0, 1, 2]], lines                        # side i-1 ends where side i begins
    p = np.cross(l1, l2)
    if (np.abs(p[:, 2]) < 1e-12).any():
        return None
    out = project(cam, np.column_stack([p[:, :2] / p[:, 2:], np.ones(4)]))
    if not np.isfinite(out).all() or np.linalg.norm(out - uv, axis=1).max() > max_shift_px:
        return None
    return out


def _dark_quadrilaterals(grey: np.ndarray, lo: np.ndarray, hi: np.ndarray, min_area: float, max_area: float
                         ) -> list[np.ndarray]:
    """The dark convex quadrilaterals (each (4, 2) px, image coordinates) of an Otsu threshold of
    ``grey``'s window [lo, hi), with areas in [min_area, max_area] px^2."""
    win = np.clip(np.asarray(grey[lo[1]:hi[1], lo[0]:hi[0]], np.float32), 0, 255).astype(np.uint8)
    _, dark = cv2.threshold(win, 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(dark, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    quads = []
    for c in contours:
        if not min_area <= cv2.contourArea(c) <= max_area:
            continue
        poly = cv2.approxPolyDP(c, 0.04 * cv2.arcLength(c, True), True)
        if len(poly) == 4 and cv2.isContourConvex(poly):
            quads.append(poly.reshape(4, 2).astype(float) + lo)
    return quads


def _subpixel(grey: np.ndarray, quad: np.ndarray) -> np.ndarray:
    p = quad.reshape(-1, 1, 2).astype(np.float32)
    cv2.cornerSubPix(np.ascontiguousarray(grey, np.float32), p, (3, 3), (-1, -1),
                     (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 0.01))
    return p.reshape(4, 2).astype(float)


def find_quadrilateral(grey: np.ndarray, uv_pred: np.ndarray, search_px: float) -> np.ndarray | None:
    """The printed (dark) quadrilateral near a prediction of its corners ``uv_pred`` (4, 2), in
    the same order: the dark regions of an Otsu threshold around it, outlined, reduced to
    convex quadrilaterals of about the predicted area, the one whose corners lie nearest the
    prediction (each within ``search_px``), its corners refined by ``cornerSubPix``. None when
    there is none. For re-acquiring the target when its corners' templates miss (the pose has
    drifted further than their search ellipses)."""
    uv_pred = np.asarray(uv_pred, float)
    if uv_pred.shape != (4, 2) or not np.isfinite(uv_pred).all():
        return None
    h, w = grey.shape[:2]
    lo = np.maximum(np.floor(uv_pred.min(axis=0) - search_px - 4), 0).astype(int)
    hi = np.minimum(np.ceil(uv_pred.max(axis=0) + search_px + 4).astype(int) + 1, (w, h))
    if (hi - lo).min() < 16:
        return None
    d1, d2 = uv_pred[2] - uv_pred[0], uv_pred[3] - uv_pred[1]
    area = 0.5 * abs(d1[0] * d2[1] - d1[1] * d2[0])          # a quadrilateral's, from its diagonals
    best, best_d = None, np.inf
    for q in _dark_quadrilaterals(grey, lo, hi, 0.4 * area, 2.5 * area):
        for order in (q, q[::-1]):                      # either direction round, any first corner
            for k in range(4):
                d = np.linalg.norm(np.roll(order, -k, axis=0) - uv_pred, axis=1)
                if d.max() <= search_px and d.sum() < best_d:
                    best, best_d = np.roll(order, -k, axis=0), d.sum()
    return None if best is None else _subpixel(grey, best)


@dataclass(frozen=True)
class Sighting:
    """A dark quadrilateral fitted as the target: R_world_cam (3, 3), r (3,) m, the corners uv
    (4, 2) px in the target's order, and how print-like it is (:func:`print_contrast`)."""

    R_world_cam: np.ndarray
    r: np.ndarray
    uv: np.ndarray
    contrast: float


def locate_target(grey: np.ndarray, cam: CameraIntrinsics, xyz: np.ndarray, R_near: np.ndarray,
                  max_turn_rad: float, max_rms_px: float, min_area_px: float, max_quads: int = 4) -> list[Sighting]:
    """The printed rectangle ``xyz`` (4, 3) sought anywhere in the image, with no prediction of
    where: the dark convex quadrilaterals of at least ``min_area_px``, the ``max_quads`` most
    print-like (dark inside, light around), each in its four cyclic corner orders (the winding
    the target shows from ``R_near``'s side) fitted by planar PnP; per quadrilateral the pose kept that fits within ``max_rms_px`` with its rotation
    nearest ``R_near`` (R_world_cam, the filter's) and within ``max_turn_rad`` of it, which also
    settles the rectangle's half-turn symmetry. Any dark rectangle of about the right shape fits
    some pose (four corners leave two residual degrees of freedom), so these are candidates for
    the caller to confirm, the most print-like first."""
    h, w = grey.shape[:2]
    quads = _dark_quadrilaterals(grey, np.zeros(2, int), np.array([w, h]), min_area_px, 0.5 * w * h)
    ranked = sorted(((print_contrast(grey, q), q) for q in quads), key=lambda c: -c[0])
    # Seen from the side R_near looks at it from, the corners wind one way round in the image:
    # each quadrilateral is taken in that direction, leaving its four cyclic orders.
    centre = xyz.mean(axis=0)
    virtual = (xyz - (centre - R_near[:, 2])) @ R_near
    winding = np.sign(_signed_area(virtual[:, :2] / virtual[:, 2:3]))
    found = []
    for contrast, q in ranked[:max_quads]:
        q = _subpixel(grey, q)
        if np.sign(_signed_area(q)) != winding:
            q = q[::-1].copy()
        xy = undistort(cam, q)
        if not np.isfinite(xy).all():
            continue
        best, best_turn = None, max_turn_rad
        for k in range(4):
            idx = np.roll(np.arange(4), -k)
            for R_wc, r in _planar_poses(xyz, xy[idx]):
                turn = rotation_angle(R_near, R_wc)
                if turn >= best_turn or np.any((xyz - r) @ R_wc[:, 2] <= 0):
                    continue
                res = _pose_residuals(cam, xyz, q[idx], R_wc, r)
                if np.isfinite(res).all() and np.sqrt(np.mean(res**2)) * math.sqrt(2) <= max_rms_px:
                    best, best_turn = Sighting(R_wc, r, q[idx], contrast), turn
        if best is not None:
            found.append(best)
    return found


def _signed_area(p: np.ndarray) -> float:
    """The shoelace area of a polygon (n, 2), positive one way round."""
    return 0.5 * float(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))


def print_contrast(grey: np.ndarray, quad: np.ndarray) -> float:
    """How much a quadrilateral (4, 2) px looks printed: the step from its inside to a ring
    around it over their spread, ``(mean_ring - mean_in) / (sd_in + sd_ring + 1)`` (grey
    levels); a flat dark print on a light card scores over ten, a dark patch of texture a few."""
    h, w = grey.shape[:2]
    size = max(np.ptp(quad[:, 0]), np.ptp(quad[:, 1]))
    pad = max(2, int(round(0.06 * size)))
    lo = np.maximum(np.floor(quad.min(axis=0)).astype(int) - 2 * pad, 0)
    hi = np.minimum(np.ceil(quad.max(axis=0)).astype(int) + 2 * pad + 1, (w, h))
    win = np.asarray(grey[lo[1]:hi[1], lo[0]:hi[0]], np.float32)
    mask = np.zeros(win.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(quad - lo).astype(np.int32), 1)
    kernel = np.ones((2 * pad + 1, 2 * pad + 1), np.uint8)
    inner = cv2.erode(mask, kernel).astype(bool)
    ring = cv2.dilate(mask, kernel).astype(bool) & ~mask.astype(bool)
    if inner.sum() < 4 or ring.sum() < 4:
        return 0.0
    a, b = win[inner], win[ring]
    return float((b.mean() - a.mean()) / (a.std() + b.std() + 1.0))


def _pose_residuals(cam: CameraIntrinsics, xyz, uv, R_wc, r) -> np.ndarray:
    P_cam = (xyz - r) @ R_wc
    return (project(cam, P_cam) - uv).reshape(-1)


def pose_jacobians(cam: CameraIntrinsics, Y: np.ndarray, R_world_cam: np.ndarray, r: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of world points ``Y`` (n, 3) from the camera at (R_world_cam, r), and their
    Jacobians: (n, 2) uv px, (n, 2, 6) d(uv)/d(theta, r) with theta a small rotation in the
    camera frame (R = R_world_cam Exp(theta)) and r the world position, (n, 2, 3) d(uv)/dY."""
    P_cam = (Y - r) @ R_world_cam
    uv, J_c = project_jacobian(cam, P_cam)
    J_y = J_c @ R_world_cam.T
    J_pose = np.concatenate([J_c @ skew(P_cam), -J_y], axis=2)
    return uv, J_pose, J_y


def pose_hypotheses(cam: CameraIntrinsics, xyz: np.ndarray, uv: np.ndarray, sigma_px: float,
                    ambiguity_ratio: float) -> list[PoseHypothesis]:
    """The camera poses the target's points ``xyz`` (n, 3) seen at ``uv`` (n, 2) admit, best
    first: one, or two for a planar target whose second IPPE pose fits within the likelihood
    ratio ``ambiguity_ratio`` (``exp((chi2_2 - chi2_1) / 2)``) of the first."""
    xy = undistort(cam, uv)
    if not np.isfinite(xy).all():
        raise SlamStartError("target.toml: a target point's pixel has no ray through the lens model")
    if len(xyz) < 4:
        raise SlamStartError(f"target.toml has {len(xyz)} points; SLAM needs at least 4 known points")
    c = xyz - xyz.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[1] < 1e-3 * max(sv[0], 1e-12):
        raise SlamStartError("target.toml: the known points are (nearly) on a line; give 4 or more points spanning a plane")
    planar = sv[2] < 1e-3 * sv[0]
    solve = _planar_poses if planar else _general_pose
    raw = solve(xyz, xy)
    if not raw:
        raise SlamStartError("target.toml: PnP found no camera pose for the target points; check xyz and uv")
    hyps = []
    for R_wc, r in raw:
        res = _pose_residuals(cam, xyz, uv, R_wc, r)
        if not np.isfinite(res).all() or np.any((xyz - r) @ R_wc[:, 2] <= 0):
            continue
        chi2 = float(res @ res) / sigma_px**2
        hyps.append(PoseHypothesis(R_wc, r, _sampled_covariance(cam, xyz, uv, R_wc, r, sigma_px, solve), chi2,
                                   float(np.sqrt(np.mean(res**2)) * math.sqrt(2))))
    if not hyps:
        raise SlamStartError("target.toml: PnP found no camera pose in front of the target points; check xyz and uv")
    hyps.sort(key=lambda h: h.chi2)
    best = hyps[0]
    return [best] + [h for h in hyps[1:] if 0.5 * (h.chi2 - best.chi2) < math.log(ambiguity_ratio)]


def _planar_poses(xyz: np.ndarray, xy: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both IPPE poses (R_world_cam, r) of coplanar points ``xyz`` seen at normalised ``xy``."""
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(xyz.astype(np.float64), xy.astype(np.float64), np.eye(3), None,
                                                 flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return []
    return [_pose(rv, tv) for rv, tv in zip(rvecs, tvecs)]


def _general_pose(xyz: np.ndarray, xy: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    try:
        ok, rvec, tvec = cv2.solvePnP(xyz.astype(np.float64), xy.astype(np.float64), np.eye(3), None,
                                      flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return []
    return [_pose(rvec, tvec)] if ok else []


def _pose(rvec, tvec) -> tuple[np.ndarray, np.ndarray]:
    R_cw, _ = cv2.Rodrigues(np.asarray(rvec, float))
    return R_cw.T, -R_cw.T @ np.asarray(tvec, float).ravel()


#: Draws of pixel noise for a start pose's covariance, and their fixed seed (repeatable starts).
COVARIANCE_DRAWS, COVARIANCE_SEED = 100, 12345


def _sampled_covariance(cam: CameraIntrinsics, xyz, uv, R_wc, r, sigma_px: float, solve) -> np.ndarray:
    """(6, 6) covariance of (small rotation in the camera frame, rad; position, m) of the pose
    the target's pixels give, by propagating their noise ``sigma_px`` through PnP itself: the
    pixels are perturbed, the pose solved again and the solution nearest (R_wc, r) kept. The
    reprojection Jacobian's ``sigma^2 (J^T J)^-1`` is this covariance to first order, but a
    small, far, nearly frontal target's pose depends on its pixels far from linearly (the
    rotation-translation ambiguity), and there the linear covariance is several times too
    small, and PnP flips between the two planar poses from one draw to the next; the sampled
    covariance (each draw's best-fitting pose, about this one) holds the spread PnP really has.
    The draws' seed is fixed, so a start is repeatable."""
    rng = np.random.default_rng(COVARIANCE_SEED)
    dR, dr = [], []
    for _ in range(COVARIANCE_DRAWS):
        xy = undistort(cam, uv + rng.normal(0.0, sigma_px, uv.shape))
        if not np.isfinite(xy).all():
            continue
        best, best_e = None, np.inf
        for R2, r2 in solve(xyz, xy):          # the pose PnP would pick from these pixels
            e = _pose_residuals(cam, xyz, uv, R2, r2)
            e = float(e @ e) if np.isfinite(e).all() else np.inf
            if e < best_e:
                best, best_e = (R2, r2), e
        if best is not None:
            dR.append(R_wc.T @ best[0])
            dr.append(best[1] - r)
    # The rotations converted together: one scipy call instead of one per draw and pose.
    D = np.hstack([Rotation.from_matrix(np.array(dR)).as_rotvec(), np.array(dr)]) if dR else np.zeros((0, 6))
    J = pose_jacobians(cam, xyz, R_wc, r)[1].reshape(-1, 6)
    linear = sigma_px**2 * np.linalg.pinv(J.T @ J)
    if len(D) < 20:
        return linear
    cov = D.T @ D / len(D)                 # about the hypothesis itself: spread and bias together
    return 0.5 * (cov + cov.T) + 1e-3 * linear


def corners_by_edges(cam: CameraIntrinsics, grey: np.ndarray, uv: np.ndarray, search_px: float
                     ) -> np.ndarray | None:
    """A printed quadrilateral's corners from its sides (:func:`refine_by_edges`) when they may be
    pixels away from ``uv`` (4, 2): the corner fit of a small, obliquely seen target's acute
    corner sits up to a few pixels inside it, and so does a template's match cut from a far view.
    Where the 1.5 px fit fails, the sides may move a corner up to ``search_px``; they are then
    fitted again from the corners they gave, and that second fit, sampled along the sides
    themselves, must agree within EDGE_MAX_SHIFT_PX. None: the sides were not found (the caller
    keeps ``uv``)."""
    edged = refine_by_edges(cam, grey, uv)
    if edged is not None:
        return edged
    edged = refine_by_edges(cam, grey, uv, max_shift_px=search_px)
    return None if edged is None else refine_by_edges(cam, grey, edged)


def start_hypotheses(cam: CameraIntrinsics, grey: np.ndarray, target: Target, search_px: float, sigma_px: float,
                     max_rms_px: float, ambiguity_ratio: float) -> tuple[RefinedTarget, list[PoseHypothesis]]:
    """Refine the clicks, fit the poses and check them: the refined target and the pose
    hypotheses (best first). Raises :class:`SlamStartError` if the corners do not make one
    consistent pose (RMS residual above ``max_rms_px``) or leave the image."""
    ref = refine_clicks(grey, target, search_px) if search_px > 0 else \
        RefinedTarget(np.asarray(target.xyz, float), np.asarray(target.uv, float), np.zeros(len(target.xyz)))
    if search_px > 0 and len(ref.uv) == 4:
        edged = corners_by_edges(cam, grey, ref.uv, search_px)     # a printed quadrilateral's sides
        if edged is not None:
            ref = RefinedTarget(ref.xyz, edged, np.linalg.norm(edged - np.asarray(target.uv, float), axis=1))
    hyps = pose_hypotheses(cam, ref.xyz, ref.uv, sigma_px, ambiguity_ratio)
    best = hyps[0]
    if best.rms_px > max_rms_px:
        raise SlamStartError(f"target.toml: the target's corners, found in the first image, do not fit one camera pose "
                             f"(reprojection RMS {best.rms_px:.1f} px > {max_rms_px:g}); check that the points' order "
                             "in xyz matches their clicks and that xyz is the printed target's geometry")
    P_cam = (ref.xyz - best.r) @ best.R_world_cam
    if not in_image(cam, project(cam, P_cam)).all():
        raise SlamStartError("target.toml: the target's points do not all project into the first image")
    return ref, hyps
