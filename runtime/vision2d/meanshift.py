"""Mean-shift colour tracking (paper, section 3, item 3; Comaniciu, Ramesh and Meer [5]), with
OpenCV's CamShift: the object is a hue-saturation histogram learned from the first window; each
frame is back-projected through it (each pixel's likelihood of being object colour) and CamShift
climbs to the mode of that likelihood, adapting the window's size and angle. Shape is ignored,
which is what makes it robust to 3D deformation (hands, the paper notes).

The track is lost when the back-projection mass inside the window drops below a share of the
first frame's (the colour is no longer there), or the window collapses; the loss is reported and
the next frame is searched in the last good window, enlarged.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .hyperplane import check_region
from .tracker import TrackResult


@dataclass(frozen=True)
class MeanShiftConfig:
    """Settings of :class:`MeanShiftTracker`.

    bins : (hue, saturation) histogram bins (OpenCV hue spans 0..180).
    s_min, v_min, v_max : pixels below this saturation or outside this value range (0..255) have
        no reliable hue; they are left out of the histogram and of the back projection.
    lost_mass : the track is lost when the mean back projection in the window falls below this
        share of the first frame's.
    search_growth : after a loss, the last good window is enlarged by this factor for the search.
    max_iterations, epsilon : CamShift's stopping rule (iterations, window shift in px).
    """

    bins: tuple[int, int] = (30, 32)
    s_min: int = 60
    v_min: int = 32
    v_max: int = 255
    lost_mass: float = 0.25
    search_growth: float = 1.5
    max_iterations: int = 10
    epsilon: float = 1.0


def _hsv(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"mean shift needs an (H, W, 3) uint8 RGB colour image, got shape {image.shape} "
                         f"{image.dtype}; it tracks colour, so grey images cannot be used")
    return cv2.cvtColor(image, cv2.COLOR_RGB2HSV)


class MeanShiftTracker:
    """CamShift colour tracker.

    ``MeanShiftTracker(image, window, config=None)``: image (H, W, 3) uint8 RGB, window (x, y, w, h)
    pixels around the object in it. ``track(image) -> TrackResult``: polygon (4, 2) the corners
    of the rotated box, centre (2,) px, residual = back-projection mass in the window relative to
    the first frame's (1 = as much object colour as at the start).
    """

    def __init__(self, image: np.ndarray, window, config: MeanShiftConfig | None = None):
        self.config = cfg = config or MeanShiftConfig()
        image = np.asarray(image)
        quad = check_region(window, image.shape[1], image.shape[0], min_size=4.0)
        if np.asarray(window).shape != (4,):
            raise ValueError("mean shift starts from a window (x, y, w, h), not a quadrilateral")
        hsv = _hsv(image)
        x0, y0 = np.floor(quad.min(0)).astype(int)
        x1, y1 = np.ceil(quad.max(0)).astype(int)
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, image.shape[1]), min(y1, image.shape[0])
        self.window = (int(x0), int(y0), int(x1 - x0), int(y1 - y0))
        roi = hsv[y0:y1, x0:x1]
        mask = self._mask(roi)
        if mask.mean() < 0.05 * 255:
            raise ValueError(f"the start window {tuple(window)} holds almost no saturated colour "
                             f"(saturation >= {cfg.s_min}); mean shift tracks colour: choose a coloured object "
                             f"or use the planar tracker")
        self.hist = cv2.calcHist([roi], [0, 1], mask, list(cfg.bins), [0, 180, 0, 256])
        cv2.normalize(self.hist, self.hist, 0, 255, cv2.NORM_MINMAX)
        self.mass0 = self._mass(self._back_projection(hsv), self.window)
        if self.mass0 <= 0:
            raise ValueError("the start window's colour histogram does not back-project into it")
        self.box = ((x0 + 0.5 * (x1 - x0), y0 + 0.5 * (y1 - y0)), (float(x1 - x0), float(y1 - y0)), 0.0)
        self.search = self.window

    def _mask(self, hsv: np.ndarray) -> np.ndarray:
        c = self.config
        return cv2.inRange(hsv, np.array([0, c.s_min, c.v_min]), np.array([180, 255, c.v_max]))

    def _back_projection(self, hsv: np.ndarray) -> np.ndarray:
        bp = cv2.calcBackProject([hsv], [0, 1], self.hist, [0, 180, 0, 256], 1)
        return cv2.bitwise_and(bp, self._mask(hsv))   # unreliable hues carry no evidence

    @staticmethod
    def _mass(bp: np.ndarray, window) -> float:
        x, y, w, h = window
        patch = bp[y:y + h, x:x + w]
        return float(patch.mean()) / 255.0 if patch.size else 0.0

    def start_result(self) -> TrackResult:
        """The start window as a result (residual 1: all of the start's object colour)."""
        return self._result(False, 1.0, None)

    def _result(self, lost: bool, residual: float, reason: str | None) -> TrackResult:
        poly = cv2.boxPoints(self.box).astype(np.float64)
        return TrackResult(poly, np.array(self.box[0], float), lost, residual, 1.0, reason)

    def track(self, image: np.ndarray | None) -> TrackResult:
        """Follow the colour into ``image`` ((H, W, 3) uint8 RGB). A grey or missing image, or
        too little object colour in the window, is reported as a loss (the box stays)."""
        cfg = self.config
        if image is None:
            return self._result(True, float("nan"), "no image")
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3:
            return self._result(True, float("nan"), "not a colour image")
        H, W = image.shape[:2]
        bp = self._back_projection(_hsv(image))
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, cfg.max_iterations, cfg.epsilon)
        box, window = (None, None)
        if self._mass(bp, self.search) > 0:
            box, window = cv2.CamShift(bp, self.search, crit)
        if window is None or window[2] < 2 or window[3] < 2:
            return self._lost(W, H, 0.0, "no object colour near the last position (window collapsed)")
        mass = self._mass(bp, window) / self.mass0
        if mass < cfg.lost_mass:
            return self._lost(W, H, mass, f"object colour in the window at {100 * mass:.0f}% of the start "
                                          f"(below {100 * cfg.lost_mass:.0f}%)")
        self.box, self.window, self.search = box, tuple(int(v) for v in window), tuple(int(v) for v in window)
        return self._result(False, mass, None)

    def _lost(self, W: int, H: int, mass: float, reason: str) -> TrackResult:
        x, y, w, h = self.window
        g = self.config.search_growth
        nw, nh = int(w * g), int(h * g)
        nx, ny = int(x + 0.5 * (w - nw)), int(y + 0.5 * (h - nh))
        nx, ny = min(max(nx, 0), W - 2), min(max(ny, 0), H - 2)
        self.search = (nx, ny, max(2, min(nw, W - nx)), max(2, min(nh, H - ny)))
        return self._result(True, mass, reason)
