"""Visual (and inertial) stabilisation with a software fovea (paper, section 3 item 1, Fig. 4).

:mod:`.estimator` is the stabiliser: corners tracked by Lucas-Kanade, the rotation-only fit,
the gyro's prediction, the fovea window and :class:`Stabiliser`, frame by frame.
:mod:`.runner` runs it over a sequence folder and writes its files and report
(:func:`stabilise_sequence`). Import the names from ``runtime.vision2d.stabilise``.
"""

from .estimator import (FEW_CORNERS_PREV, FEW_INLIERS, FEW_TRACKS, OK, FlowSettings, FoveaWindow, RotationResult,
                        StabiliseSettings, Stabiliser, StepResult, angular_residuals, bearings, check_fovea, crop_fovea,
                        detect_corners, fit_rotation, follow_reference, fovea_window, frame_rotation, gyro_rotation,
                        kabsch, predict_pixels, to_grey, track_points)
from .runner import StabiliseResult, residual_motion, stabilise_sequence

__all__ = [
    "FEW_CORNERS_PREV", "FEW_INLIERS", "FEW_TRACKS", "OK", "FlowSettings", "FoveaWindow", "RotationResult",
    "StabiliseResult", "StabiliseSettings", "Stabiliser", "StepResult", "angular_residuals", "bearings", "check_fovea",
    "crop_fovea", "detect_corners", "fit_rotation", "follow_reference", "fovea_window", "frame_rotation",
    "gyro_rotation", "kabsch", "predict_pixels", "residual_motion", "stabilise_sequence", "to_grey", "track_points",
]
