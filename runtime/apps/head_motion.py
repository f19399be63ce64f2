"""The head-motion start of the closed loop: wait for the wearer to be still, take the head along
the diagonals of a box in pan and elevation (:data:`CORNERS`) at the controlled-motion limit, and start SLAM
metric from what the camera saw through that known motion (``runtime.slam.head_motion_start``).

Only what a real wearable has is read: the images, the encoders (the head model gives the
camera's pose on the mount at their angles), and the IMU (the wearer's stillness, and gravity to
level the world frame). The phase drives the head through the controller's ``slave`` mode, so
the motion passes the same command filter and limits as every other. The start's solve (seconds
of CPU) runs on a worker thread while the loop keeps its period, the head holding: a stalled
loop would trip the servos' bus watchdog.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kinematics import forward_kinematics
from kinematics.camera import CameraIntrinsics
from kinematics.geometry import HeadGeometry

from ..background import DelayedResult
from ..slam.head_motion_start import HeadMotionResult, HeadMotionSettings, HeadMotionStart, baseline_m
from ..slam.natural_start import StartWait
from ..slam.corners import grey, grey8


@dataclass(frozen=True)
class HeadMotionPlan:
    """The start's motion and its stillness test.

    amplitude_rad : how far the head turns each way in pan and in elevation from where it is
        (both at once: the camera's centre goes along the diagonals of a box, so it moves across
        the view both ways, and back and forth faster than a still wearer sways).
    still_rate_rad_s : the wearer is still when every 0.1 s mean of the gyro's rate over the
        last ``still_s`` is below this (the head holding).
    still_s : how long the wearer must be still before the motion starts.
    settle_s : the head holds this long after the motion before the start is solved (its last
        frames see the scene again from where the task begins).
    arrive_rad : a waypoint is reached when the commanded angles are this close to it.
    """

    amplitude_rad: float = math.radians(10.0)
    still_rate_rad_s: float = 0.1
    still_s: float = 0.5
    settle_s: float = 0.4
    arrive_rad: float = math.radians(0.2)
    points: HeadMotionSettings = field(default_factory=HeadMotionSettings)


#: Loop time, s, after which a robot whose clock waits for the loop (the twin) takes the start's
#: solve; hardware takes it at the first period after it is done.
SOLVE_DELAY_S = 0.5

#: Frames, at most, kept while the start is solved (grey, 0.3 MB each at 640 x 480).
MAX_BACKLOG = 150

#: The motion's corners in (elevation, pan), in units of the amplitude: each diagonal of the box
#: twice there and back, then home. Both joints reverse at (nearly) every corner, so the motion
#: is faster than the wearer's sway in pan as in elevation.
CORNERS = ((1, 1), (-1, -1)) * 2 + ((1, -1), (-1, 1)) * 2 + ((0, 0),)


def waypoints(head: HeadGeometry, q0, amplitude_rad: float) -> np.ndarray:
    """(9, 3) joint angles, rad: the corners of :data:`CORNERS` about ``q0`` (3,), each inside
    the joint ranges."""
    q0 = np.asarray(q0, float)
    w = np.array([q0 + amplitude_rad * np.array([e, p, 0.0]) for e, p in CORNERS])
    return np.clip(w, head.lower, head.upper)


def plan_baseline_m(head: HeadGeometry, q0, amplitude_rad: float) -> float:
    """How far, m, the camera's centre moves from its start along the planned motion."""
    w = np.vstack([np.asarray(q0, float)[None], waypoints(head, q0, amplitude_rad)])
    q = np.concatenate([a + np.linspace(0, 1, 20)[:, None] * (b - a) for a, b in zip(w[:-1], w[1:])])
    return baseline_m(forward_kinematics(head, q).T_mount_cam)


def level_attitude(f_cam: np.ndarray) -> np.ndarray:
    """(3, 3) R_world_cam of a camera whose accelerometer reads ``f_cam`` (3,) at rest: world z
    up, world x the optic axis's heading (its camera x where it looks straight up or down)."""
    z = np.asarray(f_cam, float) / np.linalg.norm(f_cam)
    a = np.array([0.0, 0.0, 1.0])
    x = a - (a @ z) * z
    if np.linalg.norm(x) < 0.1:
        a = np.array([1.0, 0.0, 0.0])
        x = a - (a @ z) * z
    x /= np.linalg.norm(x)
    return np.vstack([x, np.cross(z, x), z])


class HeadMotionPhase:
    """Steps the start: ``step`` each period until it returns a :class:`HeadMotionResult`.

    head, camera : the robot's. q0 : (3,) the encoders at the first period. plan : the motion.
    clock_waits : the robot's clock stands still while the loop works (the twin: the solve is
    taken :data:`SOLVE_DELAY_S` of loop time after it was asked for, so a run does not depend on
    the threads' timing). Raises ValueError at once when the head's camera centre does not move
    in the planned motion (no baseline). ``said`` : what the phase has told the person, in order
    (time, text). ``solving_at`` : the time, s, of the frame the start is being solved at (None
    when no solve is in flight). ``frame`` : once the start is made, that image and its time, a
    few periods before the one ``step`` returns the start in; ``backlog`` : the frames (grey
    uint8, time) seen since, which SLAM must go through to reach the present.
    """

    def __init__(self, head: HeadGeometry, camera: CameraIntrinsics, q0, plan: HeadMotionPlan = HeadMotionPlan(),
                 clock_waits: bool = False):
        base = plan_baseline_m(head, q0, plan.amplitude_rad)
        if base < plan.points.min_baseline_m:
            raise ValueError(f"--start head-motion: this head's camera centre moves only {1e3 * base:.1f} mm in a "
                             f"{math.degrees(plan.amplitude_rad):.0f} deg pan and elevation motion (it lies on the "
                             f"axes): no baseline to fix the scale; use a target (target.toml) or a saved map")
        self.head, self.camera, self.plan = head, camera, plan
        self.path: np.ndarray | None = None    # the motion's waypoints, from where it begins
        self.state = "waiting"
        self.said: list[tuple[float, str]] = []
        self._imu: list[np.ndarray] = []
        self._t_first: float | None = None
        self._k = 0
        self._t_end = 0.0
        self._estimator: HeadMotionStart | None = None
        self._R_world_cam0 = np.eye(3)
        self._solve = DelayedResult("head-motion-start", SOLVE_DELAY_S, clock_waits)
        self.frame: tuple[np.ndarray, float] | None = None
        self.solving_at: float | None = None
        self.backlog: list[tuple[np.ndarray, float]] = []

    def _say(self, t: float, text: str) -> None:
        if not self.said or self.said[-1][1] != text:
            self.said.append((t, text))

    def _still(self) -> tuple[bool, float]:
        """Whether the gyro samples kept while waiting (the last ``still_s``) are still, and their
        largest 0.1 s mean rate."""
        rows = self.imu_rows
        if len(rows) < 5 or rows[-1, 0] - rows[0, 0] < 0.8 * self.plan.still_s:
            return False, float("nan")
        k = np.floor((rows[:, 0] - rows[0, 0]) / 0.1).astype(int)
        means = np.array([rows[k == i, 1:4].mean(axis=0) for i in np.unique(k)])
        peak = float(np.linalg.norm(means, axis=1).max())
        return peak < self.plan.still_rate_rad_s, peak

    @property
    def imu_rows(self) -> np.ndarray:
        """(k, 7) the IMU rows the phase keeps: while waiting, the last ``still_s``; from the
        motion's start on, all since then."""
        return np.vstack(self._imu) if self._imu else np.zeros((0, 7))

    def step(self, obs, ctl) -> HeadMotionResult | None:
        """One period: the observation, the gaze controller to drive (its ``slave`` mode). The
        result, when it comes, is the start at the image in :attr:`frame`."""
        rows = obs.imu.rows()
        if len(rows):
            self._imu.append(rows)
        t = float(obs.t)
        if self.state == "waiting":
            if self._imu:
                # Only the stillness window counts while waiting: a wearer who never keeps still
                # must not grow the phase's memory or its work each period.
                kept = self.imu_rows
                self._imu = [kept[kept[:, 0] > t - self.plan.still_s]]
            if self._t_first is None:
                self._t_first = t
            has_imu = bool(self._imu)
            if not has_imu and t - self._t_first < self.plan.still_s:
                ctl.hold()                 # an IMU's first samples come with the first step
                return None
            still, peak = self._still() if has_imu else (True, float("nan"))
            if has_imu and not still:
                if np.isfinite(peak):
                    self._say(t, f"head-motion start: waiting for the wearer to keep still (turning at "
                                 f"{math.degrees(peak):.1f} deg/s; below {math.degrees(self.plan.still_rate_rad_s):.1f} "
                                 "needed)")
                ctl.hold()
                return None
            if obs.image is None or not obs.fresh_image:
                return None
            if has_imu:
                self._R_world_cam0 = level_attitude(self.imu_rows[:, 4:7].mean(axis=0))
            else:
                self._say(t, "head-motion start: no IMU: the wearer's stillness is not checked and the world is "
                             "the first camera's frame (not levelled)")
            self._estimator = HeadMotionStart(self.camera, self.plan.points)
            self._k = 0
            self.path = waypoints(self.head, obs.q, self.plan.amplitude_rad)
            self._add(obs)
            ctl.slave(self.path[0])
            self.state = "moving"
            self._say(t, "head-motion start: the head turns to fix the map's scale; keep still")
            return None
        if obs.fresh_image and obs.image is not None and self.state in ("moving", "settling"):
            self._add(obs)
        if self.state == "moving":
            if np.abs(ctl.filter.q - self.path[self._k]).max() < self.plan.arrive_rad:
                self._k += 1
                if self._k == len(self.path):
                    self.state, self._t_end = "settling", t
                    ctl.hold()
                else:
                    ctl.slave(self.path[self._k])
            return None
        if self.state == "settling" and t - self._t_end >= self.plan.settle_s and obs.fresh_image \
                and obs.image is not None:
            # The frames end here: the worker owns the estimator until it answers.
            self._solve.submit(t, self._estimator.solve, self._R_world_cam0, self.imu_rows if self._imu else None,
                               context=(np.array(obs.image), t))
            self.state, self.solving_at, self.backlog = "solving", t, []
            self._say(t, "head-motion start: solving for the map (keep still)")
            return None
        if self.state == "solving":
            ctl.hold()
            if obs.fresh_image and obs.image is not None:
                # SLAM goes through these once the start is made; past the cap, every other
                # one is dropped, so a slow solve costs frame rate, not memory.
                if len(self.backlog) >= MAX_BACKLOG:
                    self.backlog = self.backlog[1::2]
                self.backlog.append((grey8(obs.image), t))
            got = self._solve.collect(t)
            if got is None:
                return None
            r, frame = got
            self.solving_at = None
            if isinstance(r, StartWait):
                self._say(t, f"head-motion start: no start ({r.reason}); trying again")
                self.state, self._imu = "waiting", []
                return None
            self.state, self.frame = "done", frame
            self._say(t, f"head-motion start: SLAM started metric from {len(r.start.xyz)} points (camera moved "
                         f"{1e3 * r.baseline_m:.0f} mm, wearer drift {1e3 * r.drift_m:.1f} mm, "
                         f"{r.rms_px:.2f} px RMS)")
            return r
        return None

    def _add(self, obs) -> None:
        T_mount_cam = forward_kinematics(self.head, np.asarray(obs.q, float)).T_mount_cam
        self._estimator.add(grey(obs.image), float(obs.t), T_mount_cam)


__all__ = ["CORNERS", "MAX_BACKLOG", "SOLVE_DELAY_S", "HeadMotionPhase", "HeadMotionPlan", "level_attitude",
           "plan_baseline_m", "waypoints"]
