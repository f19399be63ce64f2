"""The records a sequence holds: trajectories, IMU and joint logs, target points and frames,
each validated when built (shapes, finite values, increasing times, unit quaternions, rigid
transforms); :class:`SequenceError` for what cannot be used. No file I/O here: reading and
writing are :mod:`.textfiles`, :mod:`.reader` and :mod:`.writer`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

# Column layouts of the text files (the '#' header line each writer puts at the top).
TRAJECTORY_COLUMNS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
IMU_COLUMNS = ("timestamp", "wx", "wy", "wz", "ax", "ay", "az")
JOINT_COLUMNS = ("timestamp", "q_elevation", "q_pan", "q_cyclotorsion")

#: A quaternion read from a file is normalised if its norm is within this of 1; further off
#: it is an error (a typo or a wrong column order), not rounding.
QUATERNION_NORM_TOL = 1e-3
#: A rotation matrix given to a writer must be orthonormal to this (max abs of R^T R - I).
ROTATION_TOL = 1e-6
#: TUM RGB-D: a depth PNG holds metres x 5000 (0.2 mm steps, up to 13.1 m).
#: The kind (kinematics.outdir) of a folder a SequenceWriter writes on its own (wvr sim record).
RECORDING = "sim record"

DEPTH_SCALE = 5000.0
#: target.toml needs at least this many points (enough for a unique camera pose from a plane).
MIN_TARGET_POINTS = 4


class SequenceError(ValueError):
    """A sequence, trajectory, log or target file (or array) that cannot be used; a one-line
    message naming the file, the line or field and the fix."""


# ---------------------------------------------------------------------------------------------
# Checked arrays
# ---------------------------------------------------------------------------------------------

def _as_times(t, name: str = "t") -> np.ndarray:
    """(N,) float array of finite, strictly increasing times, seconds."""
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1:
        raise SequenceError(f"{name} must have shape (N,), got {t.shape}")
    if not np.isfinite(t).all():
        raise SequenceError(f"{name}[{int(np.flatnonzero(~np.isfinite(t))[0])}] is not finite; times are seconds")
    if t.size > 1 and not (np.diff(t) > 0).all():
        i = int(np.flatnonzero(~(np.diff(t) > 0))[0]) + 1
        raise SequenceError(f"{name}[{i}] = {float(t[i])!r} is not after {name}[{i - 1}] = {float(t[i - 1])!r}; "
                            f"times must be strictly increasing")
    return t


def _as_columns(a, n: int, dim: int, name: str) -> np.ndarray:
    """(n, dim) finite float array."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n, dim):
        raise SequenceError(f"{name} must have shape ({n}, {dim}), got {a.shape}")
    if not np.isfinite(a).all():
        raise SequenceError(f"{name} has non-finite values in row {int(np.flatnonzero(~np.isfinite(a).all(1))[0])}")
    return a


def _unit_quaternions(q: np.ndarray, where) -> np.ndarray:
    """Normalise (N, 4) quaternions within QUATERNION_NORM_TOL of unit length; else an error.

    where(i) names row i in the message (a file line, or an array index).
    """
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= QUATERNION_NORM_TOL))
    if bad.size:
        i = int(bad[0])
        raise SequenceError(f"{where(i)}: quaternion (qx qy qz qw) has norm {norm[i]:.6g}, not 1; "
                            f"check the column order (tx ty tz qx qy qz qw) or normalise it")
    return q / norm[:, None]


def _rotations_from_T(T: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) rigid transforms -> positions (N, 3) and unit quaternions xyzw (N, 4).

    Refuses matrices that are not rigid (scipy would silently orthonormalise them, hiding a
    wrong matrix).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise SequenceError(f"{name} must have shape (N, 4, 4), got {T.shape}")
    if not np.isfinite(T).all():
        raise SequenceError(f"{name} has non-finite values")
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bottom = np.abs(T[:, 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = np.flatnonzero((err > ROTATION_TOL) | (np.linalg.det(R) <= 0) | (bottom > 0))
    if bad.size:
        i = int(bad[0])
        raise SequenceError(f"{name}[{i}] is not a rigid transform (rotation block not orthonormal "
                            f"with det +1, or last row not [0 0 0 1]); pass camera-to-world poses")
    return T[:, :3, 3].copy(), Rotation.from_matrix(R).as_quat()


# ---------------------------------------------------------------------------------------------
# Records
# ---------------------------------------------------------------------------------------------

@dataclass
class Trajectory:
    """A camera-to-world trajectory (TUM convention).

    t : (N,) float, seconds, strictly increasing.
    p_world_cam : (N, 3) float, metres: the optical centre in the world frame.
    q_xyzw : (N, 4) float, unit quaternions (x y z w) rotating optical-frame axes to world axes.
    """

    t: np.ndarray
    p_world_cam: np.ndarray
    q_xyzw: np.ndarray

    def __post_init__(self):
        self.t = _as_times(self.t)
        n = len(self.t)
        self.p_world_cam = _as_columns(self.p_world_cam, n, 3, "p_world_cam")
        self.q_xyzw = _unit_quaternions(_as_columns(self.q_xyzw, n, 4, "q_xyzw"),
                                        lambda i: f"q_xyzw[{i}]")

    @classmethod
    def from_T_world_cam(cls, t, T_world_cam) -> "Trajectory":
        """From times (N,) s and camera-to-world transforms (N, 4, 4)."""
        p, q = _rotations_from_T(T_world_cam, "T_world_cam")
        return cls(t, p, q)

    def __len__(self) -> int:
        return len(self.t)

    def R_world_cam(self) -> np.ndarray:
        """(N, 3, 3) rotations taking optical-frame vectors to world vectors."""
        if len(self) == 0:
            return np.zeros((0, 3, 3))
        return Rotation.from_quat(self.q_xyzw).as_matrix()

    def T_world_cam(self) -> np.ndarray:
        """(N, 4, 4) homogeneous camera-to-world transforms (metres)."""
        T = np.zeros((len(self), 4, 4))
        T[:, :3, :3] = self.R_world_cam()
        T[:, :3, 3] = self.p_world_cam
        T[:, 3, 3] = 1.0
        return T

    def interpolate(self, times) -> "Trajectory":
        """The trajectory at other times: positions linear, orientations by slerp.

        times : (M,) float, seconds, strictly increasing, each within [t[0], t[-1]].
        Returns a Trajectory of M poses (so its times must increase, as every Trajectory's do).
        Times outside the recorded range are refused rather than extrapolated (a pose guessed
        past the data would look measured).
        """
        times = _as_times(np.atleast_1d(np.asarray(times, dtype=np.float64)), "times")
        if len(self) == 0:
            raise SequenceError("cannot interpolate an empty trajectory")
        outside = np.flatnonzero((times < self.t[0]) | (times > self.t[-1]))
        if outside.size:
            ti = float(times[int(outside[0])])
            raise SequenceError(f"time {ti!r} s is outside the trajectory's range "
                                f"[{float(self.t[0])!r}, {float(self.t[-1])!r}] s; ask only for "
                                f"times within it")
        if len(self) == 1:  # Slerp needs two key times; the only valid time is t[0] itself
            return Trajectory(times, np.repeat(self.p_world_cam, len(times), 0),
                              np.repeat(self.q_xyzw, len(times), 0))
        p = np.column_stack([np.interp(times, self.t, self.p_world_cam[:, k]) for k in range(3)])
        q = Slerp(self.t, Rotation.from_quat(self.q_xyzw))(times).as_quat()
        return Trajectory(times, p, q)

    def at(self, t: float) -> np.ndarray:
        """(4, 4) T_world_cam interpolated at time t (seconds, within the recorded range)."""
        return self.interpolate([float(t)]).T_world_cam()[0]


@dataclass
class ImuLog:
    """IMU samples in the camera's optical frame.

    t : (N,) float, seconds, strictly increasing.
    gyro : (N, 3) float, angular rate wx wy wz, rad/s.
    accel : (N, 3) float, specific force ax ay az, m/s^2.
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    #: Rows the reader dropped, by kind ("non_finite", "duplicate", "out_of_order").
    dropped: dict = field(default_factory=dict)

    def __post_init__(self):
        self.t = _as_times(self.t)
        self.gyro = _as_columns(self.gyro, len(self.t), 3, "gyro")
        self.accel = _as_columns(self.accel, len(self.t), 3, "accel")

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class JointLog:
    """Head encoder readings.

    t : (N,) float, seconds, strictly increasing.
    q : (N, 3) float, joint angles (elevation, pan, cyclotorsion), rad.
    """

    t: np.ndarray
    q: np.ndarray

    def __post_init__(self):
        self.t = _as_times(self.t)
        self.q = _as_columns(self.q, len(self.t), 3, "q")

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class Target:
    """Known points that fix the world frame and scale at start-up.

    xyz : (N, 3) float, world positions, metres; N >= 4.
    uv : (N, 2) float, their pixels in the first frame of rgb.txt (OpenCV convention).
    """

    xyz: np.ndarray
    uv: np.ndarray

    def __post_init__(self):
        self.xyz = np.asarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise SequenceError(f"target xyz must have shape (N, 3), got {self.xyz.shape}")
        n = len(self.xyz)
        if n < MIN_TARGET_POINTS:
            raise SequenceError(f"a target needs at least {MIN_TARGET_POINTS} points, got {n}")
        self.xyz = _as_columns(self.xyz, n, 3, "target xyz")
        self.uv = _as_columns(self.uv, n, 2, "target uv")

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class Frame:
    """One entry of rgb.txt.

    index : position in rgb.txt (0-based, counting image lines only).
    t : timestamp, seconds.
    path : the image file (absolute, or as rgb.txt gives it if that is absolute).
    image : np.uint8, (H, W) grey or (H, W, 3) RGB; None if the image could not be used.
    problem : why image is None (missing, unreadable, corrupt, wrong size); None otherwise.
    """

    index: int
    t: float
    path: Path
    image: np.ndarray | None
    problem: str | None = None

    @property
    def ok(self) -> bool:
        return self.image is not None
