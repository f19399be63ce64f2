"""Scoring against ground truth (trajectory and map metrics), for every runner and benchmark;
the control path never imports it."""

from .maps import MapErrors, map_errors
from .trajectory import (ALIGNMENTS, TrajectoryErrors, align_se3, align_sim3, associate, rotation_angle_rad, rotation_errors_deg,
                         trajectory_errors)

__all__ = ["ALIGNMENTS", "MapErrors", "TrajectoryErrors", "align_se3", "align_sim3", "associate", "map_errors", "rotation_angle_rad",
           "rotation_errors_deg", "trajectory_errors"]
