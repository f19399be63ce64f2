"""New features (paper, section 4.1): Shi-Tomasi corners (OpenCV) in image regions that hold no
feature yet, each stored with its appearance template (15 x 15 at 640 x 480)."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from .appearance import TEMPLATE_SIZE, extract_template

#: Images at least this wide are searched for corners at half resolution (find_new_corners).
HALF_RESOLUTION_FROM_WIDTH = 320


def grey8(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image from grey or RGB uint8 (a quarter the size of :func:`grey`'s)."""
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey image from grey or RGB uint8."""
    return grey8(image).astype(np.float32)


def find_new_corners(image_grey: np.ndarray, occupied_uv: np.ndarray, n: int, min_distance: float = 30.0,
                     border: int = 20, quality: float = 0.01) -> np.ndarray:
    """(k, 2) up to n Shi-Tomasi corners at least ``min_distance`` px from every occupied
    position (existing features, their predictions) and ``border`` px from the image edge,
    strongest first."""
    H, W = image_grey.shape
    # Images 320 wide or more are searched at half resolution: at full resolution the detector
    # takes a bare surface's grain and the sensor's noise for corners that match nowhere else
    # (benchmarks/NOTES.md), and it is a quarter of the work. A new feature's position only has
    # to be near a corner: its template is what is tracked.
    s = 2 if W >= HALF_RESOLUTION_FROM_WIDTH else 1
    img = np.asarray(image_grey, np.float32)
    if s == 2:
        img = cv2.pyrDown(img)
    h, w = img.shape
    b = int(np.ceil(border / s))
    mask = np.zeros((h, w), np.uint8)
    mask[b:h - b, b:w - b] = 255
    occ = np.asarray(occupied_uv, float).reshape(-1, 2) / s
    radius = int(np.ceil(min_distance / s))
    # Only discs that reach the image: a point near the camera's plane predicts pixels far out
    # (1e12), which no integer type holds.
    near = np.isfinite(occ).all(axis=1) & (np.abs(occ - [w / 2, h / 2]) <= [w / 2 + radius, h / 2 + radius]).all(axis=1)
    for u, v in np.rint(occ[near]).astype(int).tolist():
        cv2.circle(mask, (u, v), radius, 0, -1)
    # Only the border's inside is searched: the detector gets that part of the image and a frame
    # of 4 px, as far as a masked-in pixel's response and its 3 x 3 non-maximum test reach (Sobel
    # 1 px, the block 2 px, the neighbour 1 px), so its corners are those of the whole image.
    block = 5 if s == 1 else 3
    m = max(0, b - (block // 2 + 2))
    pts = cv2.goodFeaturesToTrack(img[m:h - m, m:w - m], maxCorners=n, qualityLevel=quality,
                                  minDistance=min_distance / s, mask=mask[m:h - m, m:w - m], blockSize=block,
                                  useHarrisDetector=False)
    if pts is None:
        return np.empty((0, 2))
    return (pts.reshape(-1, 2).astype(float) + m) * s        # pyrDown samples input pixel (2x, 2y)


#: Immerkaer's noise kernel: the difference of two Laplacians, blind to a local plane; on noise
#: of standard deviation sigma its response has standard deviation 6 sigma (sqrt of 36).
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def noise_sigma(image_grey: np.ndarray, step: int = 2) -> float:
    """The image noise's standard deviation, grey levels (Immerkaer, "Fast noise variance
    estimation", 1996, with the median absolute response instead of the mean, so that edges and
    texture, a minority of pixels, do not count): ``1.4826 median|I * N| / 6`` over every
    ``step``-th row and column. An 8-bit image's response is a whole number, so the median is
    interpolated within its unit bin (the grouped-data median) rather than jumping a level."""
    r = cv2.filter2D(np.asarray(image_grey, np.float32), cv2.CV_32F, _NOISE_KERNEL)[1:-1:step, 1:-1:step]
    a = np.rint(np.abs(r)).astype(np.intp).ravel()
    if a.size == 0:
        return 0.0
    counts = np.bincount(a)
    upto = np.cumsum(counts)
    below = upto - counts                                 # responses under each whole value
    k = int(np.searchsorted(upto, a.size / 2.0))
    median = max(k - 0.5 + (a.size / 2.0 - below[k]) / counts[k], 0.0)
    return float(1.4826 * median / 6.0)


def min_template_std(sigma_noise: float, match_score: float) -> float:
    """The least standard deviation (grey levels) a new feature's template needs for image noise
    alone not to fail its match. Two copies of a template of signal variance s^2, each with
    noise sigma^2, score ``2 (1 - ZNCC) = 2 sigma^2 / (s^2 + sigma^2)`` in expectation, where
    s^2 + sigma^2 is the template's measured variance; below ``std = sigma sqrt(2 /
    match_score)`` (2.8 sigma at 0.25) noise alone reaches the threshold. Never below 2 (a flat
    patch)."""
    return max(2.0, sigma_noise * np.sqrt(2.0 / max(match_score, 1e-9)))


def new_features(image_grey: np.ndarray, occupied_uv: np.ndarray, n: int, size: int = TEMPLATE_SIZE,
                 min_std: float = 2.0, prefer: Callable[[np.ndarray], np.ndarray] | None = None,
                 take: int | None = None, **kw) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(uv (2,), template (size, size))] for up to n new corners whose templates have a standard
    deviation above ``min_std`` grey levels (see :func:`min_template_std`); corners too near the
    border skipped. ``prefer``: a test of pixels (k, 2) -> (k,) bool; given, the first ``take``
    of those candidates it passes, or the first ``take`` of all when it passes none (templates
    are cut only as far as that needs)."""
    corners = find_new_corners(image_grey, occupied_uv, n, border=max(kw.pop("border", 20), size // 2 + 1), **kw)
    uvs = np.round(corners)
    preferred_mask = prefer(uvs) if prefer is not None and len(uvs) else None
    out, preferred = [], []
    for i, uv in enumerate(corners):
        t = extract_template(image_grey, uv, size)
        if t is not None and cv2.meanStdDev(t)[1][0, 0] > min_std:     # numpy's std (ddof 0), without its overhead
            out.append((uvs[i], t))
            if preferred_mask is not None and preferred_mask[i]:
                preferred.append(out[-1])
                if len(preferred) == take:
                    break
    if prefer is None:
        return out
    return preferred if preferred else out[:take]
