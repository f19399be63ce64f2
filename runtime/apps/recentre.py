"""Path A's slow visual outer loop: the attitude the head holds is turned, a little each frame,
towards where the software fovea wants to look, so that the fovea stays inside the image.

Path A holds the camera's attitude from the IMU: it cancels rotation, not the parallax of the
wearer's translation. The fovea (runtime.vision2d.stabilise) takes the image motion that is
left, but a wearer sitting down before a near background shifts it by more than the image has
room for, and a clamped fovea shows the head's motion unreduced. Here the fovea's wanted centre,
measured on each image (tracked corners, gyro-aided), becomes a rotation that brings the optic
axis onto it, of which the fraction ``1 - exp(-gain dt)`` is added to the held attitude: an
integrator of the fovea's offset, so the head follows the background's apparent drift (time
constant ``1 / gain``) while the IMU loop goes on cancelling the fast rotation.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics

from ..vision2d.stabilise import StabiliseSettings, Stabiliser, bearings

#: Seconds of IMU samples kept for the fovea's gyro-aided tracking (its reference frame is
#: normally the previous image; a few frames more cover a flagged one).
_IMU_KEEP_S = 1.0


class Recentring:
    """The outer loop's state: feed each fresh image with :meth:`correction`.

    camera : the intrinsics. gain_per_s : 1 / the time constant, > 0. settings : the fovea's
    tracker settings (runtime.vision2d.stabilise)."""

    def __init__(self, camera: CameraIntrinsics, gain_per_s: float, settings: StabiliseSettings | None = None):
        if not (math.isfinite(gain_per_s) and gain_per_s > 0):
            raise ValueError(f"recentring gain {gain_per_s!r} /s must be positive")
        self.camera = camera
        self.gain = float(gain_per_s)
        # The window's size does not move its wanted centre; a quarter of the image leaves it room.
        fovea = (max(16, camera.width // 4), max(16, camera.height // 4))
        self.fovea = Stabiliser(camera, fovea, settings)
        self._imu = np.zeros((0, 7))
        self._t_prev: float | None = None
        self.offset_px = np.full(2, np.nan)    # the last wanted centre's offset from the image centre

    def correction(self, t: float, image: np.ndarray, imu_rows) -> np.ndarray:
        """(3, 3) R_cam_newcam: the turn to apply to the held attitude (``R_world_cam @ it``) after
        the image at ``t`` s; ``imu_rows`` (k, 7) ``t w a`` since the previous call. Identity while
        the fovea has no wanted centre (the first image, a lost view)."""
        rows = np.asarray(imu_rows, float).reshape(-1, 7)
        self._imu = np.vstack([self._imu, rows])
        self._imu = self._imu[self._imu[:, 0] >= t - _IMU_KEEP_S]
        gyro = (self._imu[:, 0], self._imu[:, 1:4]) if len(self._imu) >= 2 else None
        res = self.fovea.step(t, image, gyro)
        dt = 0.0 if self._t_prev is None else t - self._t_prev
        self._t_prev = t
        wanted = res.window.wanted
        c = np.array([(self.camera.width - 1) / 2.0, (self.camera.height - 1) / 2.0])
        self.offset_px = wanted - c
        if dt <= 0 or not np.isfinite(wanted).all():
            return np.eye(3)
        d = bearings(self.camera, wanted[None])[0]
        if not np.isfinite(d).all():
            return np.eye(3)
        axis = np.cross([0.0, 0.0, 1.0], d)
        s = float(np.linalg.norm(axis))
        if s < 1e-12:
            return np.eye(3)
        angle = math.atan2(s, float(d[2])) * (1.0 - math.exp(-self.gain * dt))
        return Rotation.from_rotvec(axis / s * angle).as_matrix()
