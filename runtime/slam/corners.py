"""New features (paper, section 4.1): Shi-Tomasi corners (OpenCV) in image regions that hold no
feature yet, each stored with its appearance template (15 x 15 at 640 x 480)."""

from __future__ import annotations

import cv2
import numpy as np

from .search import TEMPLATE_SIZE, extract_template


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey image from grey or RGB uint8."""
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return g.astype(np.float32)


def find_new_corners(image_grey: np.ndarray, occupied_uv: np.ndarray, n: int, min_distance: float = 30.0,
                     border: int = 20, quality: float = 0.01) -> np.ndarray:
    """(k, 2) up to n Shi-Tomasi corners at least ``min_distance`` px from every occupied
    position (existing features, their predictions) and ``border`` px from the image edge,
    strongest first."""
    H, W = image_grey.shape
    # Images 640 wide or more are searched at half resolution (a quarter of the work; a new
    # feature's position only has to be near a corner, its template is what is tracked).
    s = 2 if W >= 640 else 1
    img = image_grey.astype(np.float32)
    if s == 2:
        img = cv2.pyrDown(img)
    h, w = img.shape
    b = int(np.ceil(border / s))
    mask = np.zeros((h, w), np.uint8)
    mask[b:h - b, b:w - b] = 255
    occ = np.asarray(occupied_uv, float).reshape(-1, 2)
    radius = int(np.ceil(min_distance / s))
    for u, v in np.rint(occ[np.isfinite(occ).all(axis=1)] / s).astype(int).tolist():
        cv2.circle(mask, (u, v), radius, 0, -1)
    pts = cv2.goodFeaturesToTrack(img, maxCorners=n, qualityLevel=quality, minDistance=min_distance / s, mask=mask,
                                  blockSize=5 if s == 1 else 3, useHarrisDetector=False)
    if pts is None:
        return np.empty((0, 2))
    return pts.reshape(-1, 2).astype(float) * s        # pyrDown samples input pixel (2x, 2y)


def new_features(image_grey: np.ndarray, occupied_uv: np.ndarray, n: int, size: int = TEMPLATE_SIZE,
                 **kw) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(uv (2,), template (size, size))] for up to n new corners (corners too near the border
    skipped)."""
    out = []
    for uv in find_new_corners(image_grey, occupied_uv, n, border=max(kw.pop("border", 20), size // 2 + 1), **kw):
        t = extract_template(image_grey, uv, size)
        if t is not None and t.std() > 2.0:   # a flat patch cannot be matched
            out.append((np.round(uv), t))
    return out
