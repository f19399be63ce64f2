"""The 2D trackers' one interface (:class:`Tracker`) and their per-frame result.

A tracker is learned on a first image from a region and then fed frames; the planar tracker
(:mod:`.hyperplane`) and mean shift (:mod:`.meanshift`) implement it, and callers (the sequence
runner, the closed loop) use only this interface: no ``if method == ...`` at a call site.
Trackers are built by name through :func:`runtime.vision2d.track.make_tracker`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass
class TrackResult:
    """One frame's output of a tracker.

    polygon : (4, 2) float, pixels: the region's corners (template corners (0,0), (w,0), (w,h),
        (0,h) mapped into the image), OpenCV convention (centre of pixel (0,0) at (0,0)).
    centre : (2,) float, pixels: the template centre mapped into the image.
    lost : True if the track is lost in this frame (polygon is then the last good one).
    residual : the loss criterion's value (hyperplane: RMS normalised intensity error over kept
        samples; mean shift: back-projection mass in the window relative to the first frame's).
    inliers : share of the sampling pattern used (inside the image and not occluded).
    reason : why the track is lost, None otherwise.
    """

    polygon: np.ndarray
    centre: np.ndarray
    lost: bool
    residual: float
    inliers: float = 1.0
    reason: str | None = None


@runtime_checkable
class Tracker(Protocol):
    """A 2D tracker: ``Tracker(image, region, config=None)`` learns the target in ``image`` from
    ``region`` ((x, y, w, h) pixels; the planar tracker also takes 4 corners (4, 2))."""

    def start_result(self) -> TrackResult:
        """The result on the image it was learned from: the start region, not lost."""

    def track(self, image: np.ndarray | None) -> TrackResult:
        """Follow the target into the next image; a loss is reported in the result, not raised."""
