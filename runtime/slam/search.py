"""Active search (paper, section 4.1): match a feature's template only inside the 3-sigma
ellipse of its innovation covariance, by normalised sum-of-squared differences.

The search window is the ellipse's bounding box; OpenCV's ``matchTemplate`` scores every
position in it at once, positions outside the ellipse are masked out, and the best score is
refined to sub-pixel precision by fitting a parabola through its neighbours in each direction.
The score is the SSD of the two patches each normalised to zero mean and unit variance, which
is 2 (1 - ZNCC) with ZNCC OpenCV's ``TM_CCOEFF_NORMED``: 0 for identical patches up to a gain
and offset (lighting changes), 2 for unrelated ones, 4 for inverted ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .kernels import compiled_kernel

TEMPLATE_SIZE = 15          # pixels, as in MonoSLAM
HALF = TEMPLATE_SIZE // 2


@dataclass(frozen=True)
class Match:
    """uv : (2,) matched image position (template centre), pixels. score : normalised SSD of the
    best position (0 = identical, 2 = unrelated). found : whether the score passed the threshold."""

    uv: np.ndarray
    score: float
    found: bool


def ellipse_box(uv: np.ndarray, S: np.ndarray, n_sigma: float = 3.0) -> tuple[int, int, int, int]:
    """Integer bounding box (u0, v0, u1, v1), inclusive, of the n-sigma ellipse of S (2, 2) at uv."""
    hu = n_sigma * math.sqrt(max(float(S[0, 0]), 0.0))
    hv = n_sigma * math.sqrt(max(float(S[1, 1]), 0.0))
    u, v = float(uv[0]), float(uv[1])
    return math.floor(u - hu), math.floor(v - hv), math.ceil(u + hu), math.ceil(v + hv)


def extract_template(image: np.ndarray, uv, size: int = TEMPLATE_SIZE) -> np.ndarray | None:
    """The size x size (odd) grey patch centred exactly on uv (bilinear at a sub-pixel uv, so
    a match of it reports where uv's content is), or None near the border."""
    half = size // 2
    u, v = float(uv[0]), float(uv[1])
    h, w = image.shape[:2]
    if not (half <= u <= w - 1 - half and half <= v <= h - 1 - half):
        return None
    if u == int(u) and v == int(v):
        return image[int(v) - half:int(v) + half + 1, int(u) - half:int(u) + half + 1].astype(np.float32).copy()
    return cv2.getRectSubPix(image.astype(np.float32, copy=False), (size, size), (u, v))


@compiled_kernel()
def parabola_offset(a: float, b: float, c: float) -> float:
    """Offset of the extremum of a parabola through (-1, a), (0, b), (1, c), clamped to +-0.5:
    the sub-pixel step of a best score ``b`` between its neighbours' ``a`` and ``c``. The one
    definition, for this search and the compiled ZNCC search (matching.py)."""
    d = a - 2 * b + c
    return 0.0 if abs(d) < 1e-12 else min(max(0.5 * (a - c) / d, -0.5), 0.5)


def search(image: np.ndarray, template: np.ndarray, uv_pred: np.ndarray, S: np.ndarray,
           n_sigma: float = 3.0, max_score: float = 0.4, max_area: int = 200_000) -> Match:
    """Best match of ``template`` within the n-sigma ellipse of S around uv_pred in a grey image.

    image : (H, W) float32 or uint8 grey. template : (t, t), t odd. S : (2, 2) innovation covariance,
    pixels^2. A match is ``found`` if its normalised SSD is at most ``max_score``. An ellipse
    wider than ``max_area`` pixels (a lost feature) or outside the image is not searched.
    """
    img = image if image.dtype == np.float32 else image.astype(np.float32)
    H, W = img.shape[:2]
    miss = Match(np.asarray(uv_pred, float), 2.0, False)
    if not (math.isfinite(S[0, 0]) and math.isfinite(S[0, 1]) and math.isfinite(S[1, 1])
            and math.isfinite(uv_pred[0]) and math.isfinite(uv_pred[1])):
        return miss
    u0, v0, u1, v1 = ellipse_box(uv_pred, S, n_sigma)
    if (u1 - u0 + 1) * (v1 - v0 + 1) > max_area:
        return miss
    half = template.shape[0] // 2
    u0, v0 = max(u0, half), max(v0, half)
    u1, v1 = min(u1, W - 1 - half), min(v1, H - 1 - half)
    if u1 < u0 or v1 < v0:
        return miss
    a, b, c = float(S[0, 0]), float(S[0, 1]), float(S[1, 1])
    det = a * c - b * b
    if not det > 0:
        return miss
    window = img[v0 - half:v1 + half + 1, u0 - half:u1 + half + 1]
    t = template if template.dtype == np.float32 else template.astype(np.float32)
    ncc = cv2.matchTemplate(window, t, cv2.TM_CCOEFF_NORMED)
    i, j, best, du, dv = _best_in_ellipse(ncc, float(u0 - uv_pred[0]), float(v0 - uv_pred[1]),
                                          c / det, -b / det, a / det, n_sigma * n_sigma)
    if not math.isfinite(best):
        return miss
    uv = np.array([u0 + i + du, v0 + j + dv])
    return Match(uv, best, best <= max_score)


@compiled_kernel(parabola_offset)
def _best_in_ellipse(ncc, du0, dv0, iaa, iab, ibb, n2):
    """Least score ``2 (1 - ncc)`` over the window positions inside the ellipse
    ``(p - uv)^T S^-1 (p - uv) <= n2`` (``S^-1 = [[iaa, iab], [iab, ibb]]``; position (i, j) of
    the window is at offset (du0 + i, dv0 + j) from uv), and its sub-pixel refinement by a
    parabola through the neighbours in each direction (when both are inside too).
    Returns (i, j, score, du, dv); score is inf when no position is inside."""
    nj, ni = ncc.shape
    best, bi, bj = np.inf, -1, -1
    for j in range(nj):
        dv = dv0 + j
        for i in range(ni):
            du = du0 + i
            if iaa * du * du + 2.0 * iab * du * dv + ibb * dv * dv <= n2:
                sc = 2.0 * (1.0 - ncc[j, i])
                if sc < best:
                    best, bi, bj = sc, i, j
    if bi < 0:
        return 0, 0, np.inf, 0.0, 0.0

    def inside(i, j):
        du, dv = du0 + i, dv0 + j
        return 0 <= i < ni and 0 <= j < nj and iaa * du * du + 2.0 * iab * du * dv + ibb * dv * dv <= n2

    su = sv = 0.0
    if inside(bi - 1, bj) and inside(bi + 1, bj):
        su = parabola_offset(2.0 * (1.0 - ncc[bj, bi - 1]), best, 2.0 * (1.0 - ncc[bj, bi + 1]))
    if inside(bi, bj - 1) and inside(bi, bj + 1):
        sv = parabola_offset(2.0 * (1.0 - ncc[bj - 1, bi]), best, 2.0 * (1.0 - ncc[bj + 1, bi]))
    return bi, bj, best, su, sv
