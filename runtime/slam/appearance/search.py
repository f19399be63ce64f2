"""Active search (paper, section 4.1): each feature's template matched only inside the 3-sigma
ellipse of its innovation covariance, by zero-mean normalised cross-correlation (zncc.py) at
every pixel inside it, the best refined to sub-pixel (refine.py). The frame's features are
searched in one compiled pass (a call per frame, not per feature: the per-feature calls into
OpenCV and back cost more than the correlation), each template first warped by the homography
its plane induces (warp.py); a warped template that matches nothing is retried as first seen
(the plane guess may be wrong). :func:`search` is the same compiled search for one template
(the particle rays' and the tests'). Windows too flat to hold a match are excluded by their
variance; templates 11 px or wider (640 x 480 images) are searched coarse to fine."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args

from ..kernels import compiled_kernel
from ..quaternion import quat_to_rotation
from .refine import AFFINE_DAMPING, refine_affine_kernel
from .warp import warp_kernel
from .zncc import (COARSE_LEVEL, COARSE_LEVEL_MOST, COARSE_MIN_TEMPLATE, COARSE_PEAKS, FLAT_VARIANCE,
                   VALLEY_EXHAUSTIVE_MAX_PX, _best_in_grid, _zncc_coarse_to_fine, _zncc_in_ellipse)

if TYPE_CHECKING:
    from ..map_feature import MapFeature


@dataclass(frozen=True)
class Match:
    """uv : (2,) matched image position (template centre), pixels. score : ``2 (1 - ZNCC)`` of
    the best position (0 = identical, 2 = unrelated or none). found : whether the score passed
    the threshold."""

    uv: np.ndarray
    score: float
    found: bool


@compiled_kernel(_zncc_in_ellipse, _zncc_coarse_to_fine, _best_in_grid, refine_affine_kernel)
def _search_one(grey, tpl, uv, S, n2, max_area, max_score):
    """(u, v, score) of the best match of ``tpl`` in the ellipse (NaN, NaN, 2 when none; NaN, NaN,
    inf when the box around the ellipse is over ``max_area``: not searched); only a match scoring at
    most ``max_score`` is refined to sub-pixel (the others are not used)."""
    H, W = grey.shape
    h = tpl.shape[0] // 2
    a, b, c = S[0, 0], S[0, 1], S[1, 1]
    if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c) and np.isfinite(uv[0])
            and np.isfinite(uv[1]) and a * c - b * b > 0):
        return np.nan, np.nan, 2.0
    hu, hv = math.sqrt(n2 * a), math.sqrt(n2 * c)
    if (2 * hu + 1) * (2 * hv + 1) > max_area:
        return np.nan, np.nan, np.inf
    u0, u1 = max(math.floor(uv[0] - hu), h), min(math.ceil(uv[0] + hu), W - 1 - h)
    v0, v1 = max(math.floor(uv[1] - hv), h), min(math.ceil(uv[1] + hv), H - 1 - h)
    if u1 < u0 or v1 < v0:
        return np.nan, np.nan, 2.0
    det = a * c - b * b
    if tpl.shape[0] >= COARSE_MIN_TEMPLATE:
        grid = _zncc_coarse_to_fine(grey, tpl, u0, v0, u1 - u0 + 1, v1 - v0 + 1, uv[0], uv[1], c / det, -b / det,
                                    a / det, n2, COARSE_PEAKS, COARSE_LEVEL, COARSE_LEVEL_MOST, VALLEY_EXHAUSTIVE_MAX_PX)
    else:
        grid = _zncc_in_ellipse(grey, tpl, u0, v0, u1 - u0 + 1, v1 - v0 + 1, uv[0], uv[1], c / det, -b / det,
                                a / det, n2)
    du, dv, s = _best_in_grid(grid)
    if not np.isfinite(du):
        return np.nan, np.nan, 2.0
    u, v = u0 + du, v0 + dv
    if s <= max_score:
        ur, vr, ok = refine_affine_kernel(grey, tpl, u, v, 10, 0.005, AFFINE_DAMPING)
        if ok:
            u, v = ur, vr
    return u, v, s


@compiled_kernel(_search_one)
def search_kernel(grey, tpls, templates, warped, uv, S, n2, max_area, max_score):
    """Every feature's match: z (m, 2) px (NaN: none in its ellipse) and score (m,; inf: its
    ellipse's box over ``max_area``, not searched); a warped
    template (``tpls[i]`` with ``warped[i]``) that matches nothing is retried as first seen
    (``templates[i]``)."""
    m = tpls.shape[0]
    z = np.full((m, 2), np.nan)
    score = np.full(m, 2.0)
    for i in range(m):
        u, v, s = _search_one(grey, tpls[i], uv[i], S[i], n2, max_area, max_score)
        if s > max_score and warped[i]:
            u, v, s = _search_one(grey, templates[i], uv[i], S[i], n2, max_area, max_score)
        z[i, 0], z[i, 1], score[i] = u, v, s
    return z, score



def search(image: np.ndarray, template: np.ndarray, uv_pred: np.ndarray, S: np.ndarray,
           n_sigma: float = 3.0, max_score: float = 0.4, max_area: int = 200_000) -> Match:
    """Best match of ``template`` within the n-sigma ellipse of S around uv_pred in a grey image
    (the frame's search for one template).

    image : (H, W) float32 or uint8 grey. template : (t, t), t odd. S : (2, 2) innovation
    covariance, pixels^2. A match is ``found`` if its score is at most ``max_score``. An ellipse
    wider than ``max_area`` pixels (a lost feature) or outside the image is not searched."""
    grey = np.ascontiguousarray(image, np.float32)
    tpl = np.ascontiguousarray(template, np.float32)
    uv_pred = np.asarray(uv_pred, float)
    u, v, s = _search_one(grey, tpl, uv_pred, np.ascontiguousarray(S, float), n_sigma * n_sigma,
                          float(max_area), float(max_score))
    if not (math.isfinite(u) and math.isfinite(v)):
        return Match(uv_pred.copy(), 2.0, False)
    return Match(np.array([u, v]), float(s), bool(s <= max_score))


def match_features(grey: np.ndarray, features: list[MapFeature], warp: np.ndarray,
                   Y: np.ndarray, x_v: np.ndarray, cam: CameraIntrinsics, uv: np.ndarray, S: np.ndarray,
                   max_score: float, max_area: float, n_sigma: float = 3.0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match the map features ``features`` (m) whose predictions are ``uv`` (m, 2) px with
    innovation covariances ``S`` (m, 2, 2): each warped by its plane (through its point ``Y``
    (m, 3), normal ``MapFeature.normal``) where ``warp`` (m,) says so, retried unwarped when the
    warped template finds nothing. ``grey`` : (H, W) float32. Returns z (m, 2) (NaN: not found),
    score (m,; inf: not searched, the box around its ellipse over ``max_area``), found (m,)."""
    m = len(features)
    if m == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool)
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
    z, score = search_kernel(np.ascontiguousarray(grey, np.float32), tpls, templates, warped,
                             np.ascontiguousarray(uv, float), np.ascontiguousarray(S, float),
                             n_sigma * n_sigma, float(max_area), float(max_score))
    found = score <= max_score
    return z, score, found


def global_matches(image: np.ndarray, templates: list[np.ndarray], max_score: float = 0.2, per_template: int = 4
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The best whole-image matches of each template in a grey float32 image.

    A small corner template is rarely unique in a cluttered scene, so up to ``per_template``
    separated peaks scoring at most ``max_score`` (``2 (1 - ZNCC)``, as in the ellipse search)
    are kept, and PnP-RANSAC decides. Returns uv (m, 2) px of the template centres and
    which (m,) template each belongs to.
    """
    img = image.astype(np.float32, copy=False)
    if not templates:
        return np.zeros((0, 2)), np.zeros(0, np.intp)
    half = templates[0].shape[0] // 2
    # OpenCV's normalised score is rounding noise where the window is flat (a plain sheet, a
    # black frame), and can reach 1 there: such windows cannot hold a feature and are excluded.
    size = (2 * half + 1, 2 * half + 1)
    mean = cv2.boxFilter(img, -1, size, normalize=True, borderType=cv2.BORDER_ISOLATED)
    sq = cv2.boxFilter(img * img, -1, size, normalize=True, borderType=cv2.BORDER_ISOLATED)
    var = (sq - mean * mean)[half:img.shape[0] - half, half:img.shape[1] - half]
    flat = var < FLAT_VARIANCE
    uv, owner = [], []
    for i, t in enumerate(templates):
        ncc = cv2.matchTemplate(img, t.astype(np.float32), cv2.TM_CCOEFF_NORMED)
        ncc[flat | ~np.isfinite(ncc)] = -1.0
        for _ in range(per_template):
            _, best, _, (u, v) = cv2.minMaxLoc(ncc)
            if 2.0 * (1.0 - best) > max_score:
                break
            uv.append((u + half, v + half))
            owner.append(i)
            ncc[max(v - 2 * half, 0):v + 2 * half + 1, max(u - 2 * half, 0):u + 2 * half + 1] = -1.0
    return np.array(uv, float).reshape(-1, 2), np.array(owner, np.intp)
