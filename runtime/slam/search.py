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


def extract_template(image: np.ndarray, uv) -> np.ndarray | None:
    """The 15 x 15 grey patch centred on the nearest pixel to uv, or None near the border."""
    u, v = int(round(float(uv[0]))), int(round(float(uv[1])))
    h, w = image.shape[:2]
    if u - HALF < 0 or v - HALF < 0 or u + HALF >= w or v + HALF >= h:
        return None
    return image[v - HALF:v + HALF + 1, u - HALF:u + HALF + 1].astype(np.float32).copy()


def _parabola(a: float, b: float, c: float) -> float:
    """Offset of the extremum of a parabola through (-1, a), (0, b), (1, c), clamped to +-0.5."""
    d = a - 2 * b + c
    return 0.0 if abs(d) < 1e-12 else min(max(0.5 * (a - c) / d, -0.5), 0.5)


def search(image: np.ndarray, template: np.ndarray, uv_pred: np.ndarray, S: np.ndarray,
           n_sigma: float = 3.0, max_score: float = 0.4, max_area: int = 200_000) -> Match:
    """Best match of ``template`` within the n-sigma ellipse of S around uv_pred in a grey image.

    image : (H, W) float32 or uint8 grey. template : (15, 15). S : (2, 2) innovation covariance,
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
    u0, v0 = max(u0, HALF), max(v0, HALF)
    u1, v1 = min(u1, W - 1 - HALF), min(v1, H - 1 - HALF)
    if u1 < u0 or v1 < v0:
        return miss
    a, b, c = float(S[0, 0]), float(S[0, 1]), float(S[1, 1])
    det = a * c - b * b
    if not det > 0:
        return miss
    window = img[v0 - HALF:v1 + HALF + 1, u0 - HALF:u1 + HALF + 1]
    t = template if template.dtype == np.float32 else template.astype(np.float32)
    scores = 2.0 * (1.0 - cv2.matchTemplate(window, t, cv2.TM_CCOEFF_NORMED))
    # Mask positions outside the ellipse: (p - uv)^T S^-1 (p - uv) > n^2, with the 2x2 inverse
    # written out (S^-1 = [[c, -b], [-b, a]] / det).
    du = np.arange(u0, u1 + 1) - float(uv_pred[0])
    dv = (np.arange(v0, v1 + 1) - float(uv_pred[1]))[:, None]
    m2 = (c * du * du - 2.0 * b * du * dv + a * dv * dv) / det
    scores[m2 > n_sigma**2] = np.inf
    j, i = np.unravel_index(np.argmin(scores), scores.shape)
    best = float(scores[j, i])
    if not math.isfinite(best):
        return miss
    nj, ni = scores.shape
    du = _parabola(scores[j, i - 1], best, scores[j, i + 1]) if 0 < i < ni - 1 \
        and math.isfinite(scores[j, i - 1]) and math.isfinite(scores[j, i + 1]) else 0.0
    dv = _parabola(scores[j - 1, i], best, scores[j + 1, i]) if 0 < j < nj - 1 \
        and math.isfinite(scores[j - 1, i]) and math.isfinite(scores[j + 1, i]) else 0.0
    uv = np.array([u0 + i + du, v0 + j + dv])
    return Match(uv, best, best <= max_score)
