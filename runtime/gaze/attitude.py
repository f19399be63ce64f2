"""The camera's attitude from its IMU alone (Path A of the paper's Fig. 2b): gyro integration
with a slow accelerometer correction towards gravity (Mahony's complementary filter).

The gyro gives the rotation accurately over seconds; the accelerometer gives the direction of
gravity, but only on average, because the wearer's own accelerations (steps, sitting down) add
to it. So the gravity correction is slow (``gain`` 1/s, a time constant of seconds) and skipped
while the specific force's magnitude is far from g. Yaw is not observable from gravity and
drifts with the gyro's noise; the paper's Path A only needs the camera referred to gravity.

IMU rows follow the twin and ``imu.txt``: ``[t, wx, wy, wz, ax, ay, az]`` in the camera's
optical frame (rad/s, m/s^2), the accelerometer giving specific force (``R^T (a - g)``, which
is ``+9.81`` along world up at rest).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

G = 9.81


def _rotation_with_up(up_cam: np.ndarray) -> np.ndarray:
    """A camera-to-world rotation (3, 3) whose world z is ``up_cam`` (camera frame) and whose
    yaw is chosen so the optic axis points along world +x when it can (the yaw is arbitrary)."""
    z = up_cam / np.linalg.norm(up_cam)
    fwd = np.array([0.0, 0.0, 1.0]) - z * z[2]
    if np.linalg.norm(fwd) < 1e-6:
        fwd = np.array([1.0, 0.0, 0.0]) - z * z[0]
    x = fwd / np.linalg.norm(fwd)
    y = np.cross(z, x)
    return np.vstack([x, y, z])           # rows: world axes in camera coordinates -> R_world_cam


class AttitudeFilter:
    """Complementary filter for R_world_cam (3, 3) from IMU rows.

    Parameters
    ----------
    R_world_cam : initial attitude; default: levelled from the first accelerometer sample.
    gain : rad/s of correction per unit of gravity-direction error (the time constant is 1/gain).
    accel_gate : skip the correction when | |f| - g | > accel_gate * g.
    """

    def __init__(self, R_world_cam: np.ndarray | None = None, gain: float = 0.3, accel_gate: float = 0.1):
        self.R = None if R_world_cam is None else np.asarray(R_world_cam, float).copy()
        self.gain = float(gain)
        self.accel_gate = float(accel_gate)
        self.t = None
        self.omega_cam = np.zeros(3)     # the latest angular rate, camera frame, rad/s

    def update(self, imu: np.ndarray) -> np.ndarray | None:
        """Fold in rows (k, 7); returns the current R_world_cam (None before any sample)."""
        imu = np.asarray(imu, float).reshape(-1, 7)
        for t, *row in imu:
            w, f = np.array(row[:3]), np.array(row[3:])
            if not (np.isfinite(w).all() and np.isfinite(f).all() and np.isfinite(t)):
                continue                   # a bad sample is dropped, not integrated
            if self.R is None:
                self.R = _rotation_with_up(f)
                self.t = t
                self.omega_cam = w
                continue
            dt = t - self.t if self.t is not None else 0.0
            self.t = t
            if dt <= 0:
                continue
            correction = np.zeros(3)
            nf = np.linalg.norm(f)
            if abs(nf - G) < self.accel_gate * G:
                up_pred = self.R[2]                       # world up in the camera frame
                # Rotating the estimate about f x up_pred turns the predicted up onto the measured.
                correction = self.gain * np.cross(f / nf, up_pred)
            self.R = self.R @ Rotation.from_rotvec((w + correction) * dt).as_matrix()
            self.omega_cam = w
        return None if self.R is None else self.R.copy()
