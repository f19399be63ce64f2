"""A feature's patches: the template cut exactly at a sub-pixel position, the larger first-view
patch kept for warping, and the shape of a match's noise that the template's gradients allow."""

from __future__ import annotations

import math

import cv2
import numpy as np

TEMPLATE_SIZE = 15          # pixels, as in MonoSLAM
HALF = TEMPLATE_SIZE // 2


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


def patch_half(template_px: int) -> int:
    """Half-size of the stored first-view patch: room to warp the template (20 for 15 px)."""
    return 3 * (template_px // 2) - 1


def first_view_patch(image: np.ndarray, uv, half: int) -> np.ndarray | None:
    """The (2 half + 1)^2 patch centred exactly on uv (see extract_template), or None
    near the border."""
    return extract_template(image, uv, 2 * half + 1)


#: A match's noise variance along its template's weakest gradient direction is at most this
#: many times that across its strongest: an edge's position along itself, 10 px standard
#: deviation for a 1 px pixel noise.
MAX_NOISE_ELONGATION = 100.0


def match_noise_shape(template: np.ndarray, max_ratio: float = MAX_NOISE_ELONGATION) -> np.ndarray:
    """(2, 2) the shape of a match's noise covariance in the template's image axes (u, v), as a
    multiple of the pixel noise's variance. A match places a template only as well as its
    gradients constrain it (the aperture problem): the Cramer-Rao bound of an SSD match is
    ``sigma_n^2 M^-1``, ``M`` the sum of ``g g^T`` over the template (its structure tensor).
    Scaled so that the direction of the strongest gradients keeps the pixel noise (variance 1)
    and the weakest gets the ratio of M's eigenvalues, at most ``max_ratio``: a corner stays
    near isotropic, an edge's match is uncertain along the edge. A flat template: ``max_ratio I``."""
    t = np.asarray(template, float)
    gu = 0.5 * (t[1:-1, 2:] - t[1:-1, :-2])       # central differences inside the border
    gv = 0.5 * (t[2:, 1:-1] - t[:-2, 1:-1])
    a, b, c = float(np.vdot(gu, gu)), float(np.vdot(gu, gv)), float(np.vdot(gv, gv))
    half_gap = math.hypot(0.5 * (a - c), b)
    w_max, w_min = 0.5 * (a + c) + half_gap, 0.5 * (a + c) - half_gap
    if not (math.isfinite(w_max) and w_max > 0):
        return max_ratio * np.eye(2)
    ratio = min(w_max / max(w_min, w_max / max_ratio), max_ratio)
    # The strongest direction, (cos, sin) of the angle 0.5 atan2(2b, a - c); the weakest across it.
    angle = 0.5 * math.atan2(2.0 * b, a - c)
    strong = np.array([math.cos(angle), math.sin(angle)])
    weak = np.array([-strong[1], strong[0]])
    return np.outer(strong, strong) + ratio * np.outer(weak, weak)
