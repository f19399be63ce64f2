"""The seam between a control program and a head: the :class:`Robot` protocol and the types that
cross it. The MuJoCo twin implements it (``runtime.twin.twin.Twin``) and so does the hardware rig
(``runtime.drivers.rig.HardwareRig``); the closed loop (``runtime.apps.closed_loop``) is typed on
it and never knows which it drives. Both are driven through the same safety chain
(``runtime.safety.SafeRobot``, a Robot wrapping a Robot), composed in ``wvr.assemble``.

A robot is driven one camera frame at a time::

    obs = robot.reset()                 # the first observation, the head where it is
    while ...:
        obs = robot.step(JointCommand(q, qd))
    robot.close()

Truth (the camera's true pose, the true joint angles) is a separate capability,
:class:`TruthSource`, that only a simulator offers; it is for scoring and recording, never for
the control path.

Frames and units: SI and radians; IMU samples in the camera's optical frame (x right, y down,
z forward), the accelerometer giving specific force (``+9.81`` along world up at rest).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from kinematics import HeadGeometry
from kinematics.camera import CameraIntrinsics

#: The controlled-motion limit on every joint rate (paper, section 5: ~30 deg/s), the one default
#: of the gaze controller, the safety chain, rig.toml and the command line (deg/s, and rad/s).
MOTION_LIMIT_DEG_S = 30.0
MOTION_LIMIT_RAD_S = math.radians(MOTION_LIMIT_DEG_S)

#: What the joint angles of an observation are: read back from encoders, or the commands the
#: servos were last sent (hobby servos report nothing; the Maestro reports its own ramped output).
JOINTS_MEASURED = "measured"
JOINTS_COMMANDED = "commanded"


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples, one type end to end (driver, twin, controller, SLAM, recorder).

    t : (k,) s. gyro : (k, 3) rad/s. accel : (k, 3) m/s^2 specific force. Camera frame.
    """

    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gyro: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    accel: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self):
        t = np.asarray(self.t, float).reshape(-1)
        g = np.asarray(self.gyro, float).reshape(-1, 3)
        a = np.asarray(self.accel, float).reshape(-1, 3)
        if not (len(t) == len(g) == len(a)):
            raise ValueError(f"IMU samples need as many times as rows: t {len(t)}, gyro {len(g)}, accel {len(a)}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "gyro", g)
        object.__setattr__(self, "accel", a)

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def from_rows(cls, rows) -> "ImuSamples":
        """From (k, 7) rows ``[t, wx, wy, wz, ax, ay, az]`` (the layout of imu.txt)."""
        r = np.asarray(rows, float).reshape(-1, 7)
        return cls(r[:, 0], r[:, 1:4], r[:, 4:7])

    def rows(self) -> np.ndarray:
        """(k, 7) rows ``[t, wx, wy, wz, ax, ay, az]``: what SLAM and the attitude filter take."""
        return np.column_stack([self.t, self.gyro, self.accel]).reshape(-1, 7)

    # As an array (np.asarray, np.vstack) and when iterated, the samples are their imu.txt rows.
    def __array__(self, dtype=None, copy=None):
        r = self.rows()
        return r if dtype is None else r.astype(dtype)

    def __iter__(self):
        return iter(self.rows())

    @staticmethod
    def concat(parts: list["ImuSamples"]) -> "ImuSamples":
        parts = [p for p in parts if len(p)]
        if not parts:
            return ImuSamples()
        return ImuSamples(np.concatenate([p.t for p in parts]), np.concatenate([p.gyro for p in parts]),
                          np.concatenate([p.accel for p in parts]))

    def rotated(self, R_cam_imu: np.ndarray) -> "ImuSamples":
        """The same samples expressed in another frame: ``R_cam_imu @ v`` for each vector."""
        R = np.asarray(R_cam_imu, float)
        return ImuSamples(self.t, self.gyro @ R.T, self.accel @ R.T)


@dataclass(frozen=True)
class Observation:
    """What a controller may see after a step.

    t : s (the image's time stamp). image : (H, W, 3) uint8 RGB. imu : the samples since the
    previous observation. q : (3,) joint angles, rad (elevation, pan, cyclotorsion).
    q_source : :data:`JOINTS_MEASURED` (encoders) or :data:`JOINTS_COMMANDED` (what the servos were
    last driven to). fresh_image : False when the camera delivered no new frame (the image is
    the previous one): the controller holds, SLAM skips it.
    """

    t: float
    image: np.ndarray
    imu: ImuSamples
    q: np.ndarray
    q_source: str = JOINTS_MEASURED
    fresh_image: bool = True

    @property
    def encoders(self) -> np.ndarray:
        """The joint angles as the controller takes them (measured, or the commands if none)."""
        return self.q


@dataclass(frozen=True)
class JointCommand:
    """One period's command. q : (3,) joint targets, rad. qd : (3,) the rates the controller
    planned to reach them at, rad/s (information for drivers and logs; the safety chain bounds
    the motion itself). basis_t : the time (s, the observations' clock) of the newest estimate
    the command rests on (a SLAM pose, the IMU's attitude, a tracker's fix), for the safety
    watchdog; None when the command needs none."""

    q: np.ndarray
    qd: np.ndarray = field(default_factory=lambda: np.zeros(3))
    basis_t: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "q", np.asarray(self.q, float).reshape(3).copy())
        object.__setattr__(self, "qd", np.asarray(self.qd, float).reshape(3).copy())


@dataclass(frozen=True)
class ImuNoise:
    """An IMU's white-noise densities as the SLAM's prediction should take them: gyro,
    rad/s/sqrt(Hz), and accelerometer (specific force), m/s^2/sqrt(Hz)."""

    gyro: float
    accel: float


@dataclass(frozen=True)
class RobotInfo:
    """What a robot reports about itself.

    head : the head's geometry (joint ranges and servo speeds are its hard limits).
    camera : the camera's intrinsics. frame_rate : Hz, the control period's inverse.
    speed_limit : (3,) rad/s, the fastest any joint may be driven (at most the servos').
    name : for logs and reports. imu_noise : its IMU's noise (:class:`ImuNoise`), or None for
    the SLAM's defaults (a calibrated MEMS IMU's raw rates and specific force).
    imu_clock_offset_s : the IMU's stamps' measured lag behind the camera's, s, where SLAM
    starts learning it. clock_waits : the robot's clock stands still while the loop works (a
    simulation): work beside the loop is then collected at a fixed loop time, waited for if need
    be, so a run does not depend on the threads' timing (runtime.background).
    """

    head: HeadGeometry
    camera: CameraIntrinsics
    frame_rate: float
    speed_limit: np.ndarray
    name: str = "robot"
    imu_noise: ImuNoise | None = None
    imu_clock_offset_s: float = 0.0
    clock_waits: bool = False

    @property
    def lower(self) -> np.ndarray:
        return self.head.lower

    @property
    def upper(self) -> np.ndarray:
        return self.head.upper


@runtime_checkable
class Robot(Protocol):
    """A head with a camera and an IMU, driven a frame at a time."""

    @property
    def info(self) -> RobotInfo: ...

    def reset(self) -> Observation:
        """Start (or restart) a session; returns the first observation."""
        ...

    def step(self, command: JointCommand) -> Observation:
        """Send one command; return the next observation (one frame period later)."""
        ...

    def close(self) -> None: ...


class SessionEnded(Exception):
    """Raised by a robot's step when its session ends of itself (a replayed or simulated camera
    ran out of frames): the loop finishes normally."""


@dataclass(frozen=True)
class Truth:
    """Scoring only. t : s. T_world_cam : (4, 4) optical frame to world. q : (3,) true joint
    angles. T_world_mount : (4, 4) the head's mount. command : (3,) what the servos were sent."""

    t: float
    T_world_cam: np.ndarray
    q: np.ndarray
    T_world_mount: np.ndarray
    command: np.ndarray


@runtime_checkable
class TruthSource(Protocol):
    """What only a simulator offers: the truth of the present moment, and named world points
    of its scene (e.g. ``"target_corners"``, (4, 3)) for scoring a task."""

    def truth(self) -> Truth: ...

    def landmarks(self) -> dict[str, np.ndarray]: ...
