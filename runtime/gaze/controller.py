"""The gaze controller (paper section 5, Fig. 2b): saccades and fixation from the SLAM camera
pose, Path A (stabilise against the world from the IMU alone), Path B (hold a direction relative
to the wearer's body) and 2D tracking.

Each control period (one camera frame):

1. **Where the head's mount is.** With a SLAM pose, ``T_world_mount = T_world_cam
   inv(T_mount_cam(encoders))``: the camera pose composed with the inverse of the head's FK. The
   IMU's attitude filter gives the rotation when SLAM has none (and always, for Path A).
2. **Where it will be.** The command is reached a period from now (the servos ramp to it over
   the frame) and the mount keeps moving with the wearer, so the mount pose is predicted
   ``lead_s`` ahead: its angular rate is the gyro's (camera frame) less the joints' own
   contribution, its velocity SLAM's camera velocity less the head's and the rotation's lever arm.
3. **Desired angles.** The period's estimate (:class:`~.estimate.GazeEstimate`, frozen) goes
   to the active mode, whose target (a world point, a world attitude, a body direction, an
   image point) goes through the fixation IK with the image-vertical rule.
4. **Rates.** The rate QP (qp.py) follows that motion within the joint ranges, the
   controlled-motion limit (default 30 deg/s, never above the servo's 10 rad/s) and smoothness.
5. **Command.** The rates go through the kinematics servo filter; its output is what is sent.

An unreachable target is refused with the IK's reason and a wearer prompt; while a target
being held becomes unreachable (the wearer turned away), the head holds still and the prompt
is repeated every ``prompt_every_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import HeadGeometry, ServoFilter, forward_kinematics, gaze_at_direction
from kinematics.camera import CameraIntrinsics

from ..robot import MOTION_LIMIT_RAD_S
from .attitude import AttitudeFilter
from .estimate import GazeEstimate, ik_point, up_mount
from .modes import Body, Desired, Fixate, Hold, Mode, Saccade, Slave, Stabilise, Track
from .prompts import Prompt, wearer_prompt
from .qp import RateQP, RateQPSettings


class GazeRefused(ValueError):
    """A gaze target the head cannot reach from the wearer's current pose; carries a prompt."""

    def __init__(self, reason: str, prompt: Prompt | None = None):
        super().__init__(reason + (f"; ask the wearer to {prompt.text}" if prompt and prompt.kind != "none" else ""))
        self.reason = reason
        self.prompt = prompt


@dataclass(frozen=True)
class ControllerSettings:
    """motion_limit_rad_s : the controlled-motion limit on every joint rate (default
    runtime.robot.MOTION_LIMIT_RAD_S, the paper's ~30 deg/s); must not exceed the servos' own.
    lead_s : how far ahead the mount's pose is predicted (None: one control period plus
    ``servo_lag_s``). prompt_every_s : how often a standing
    prompt is repeated. landed_rad : a saccade has landed once the estimated gaze error is below
    this and the joints have (nearly) stopped."""

    motion_limit_rad_s: float = MOTION_LIMIT_RAD_S
    lead_s: float | None = None
    servo_lag_s: float = 0.01
    prompt_every_s: float = 1.0
    landed_rad: float = math.radians(1.0)
    qp: RateQPSettings = field(default_factory=RateQPSettings)


@dataclass
class GazeCommand:
    """One period's output. q : (3,) the command sent (after the servo filter), rad. qd : (3,)
    its rate, rad/s. q_desired : (3,) the IK's angles, or None when holding. error_rad : the
    estimated angle between the optic axis and the target now (fixate, saccade, track), or the
    attitude error (stabilise). prompt : set when the wearer is asked to move."""

    t: float
    mode: str
    q: np.ndarray
    qd: np.ndarray
    q_desired: np.ndarray | None
    error_rad: float = float("nan")
    reachable: bool = True
    prompt: Prompt | None = None
    landed: bool = False


def _gyro_rotation(imu) -> tuple[np.ndarray, float] | None:
    """The camera's turn over a period's IMU rows (k, 7) (each rate held until the next row, the
    last for the rows' median spacing): (R_prev_cur (3, 3), the span, s), or None without two
    good rows."""
    rows = np.asarray(imu, float).reshape(-1, 7)
    rows = rows[np.isfinite(rows).all(axis=1)]
    if len(rows) < 2:
        return None
    d = np.diff(rows[:, 0])
    if not (d > 0).all():
        return None
    d = np.r_[d, np.median(d)]
    R = np.eye(3)
    for w, dk in zip(rows[:, 1:4], d):
        R = R @ Rotation.from_rotvec(w * dk).as_matrix()
    return R, float(d.sum())


class GazeController:
    """Gaze control of the head from SLAM, IMU and encoders (no ground truth).

    Parameters
    ----------
    head, camera : the head being driven and its camera.
    q0 : (3,) the joint angles at start (the encoders), rad.
    dt : the control period, s (the camera's frame period).
    """

    def __init__(self, head: HeadGeometry, camera: CameraIntrinsics, q0, dt: float,
                 settings: ControllerSettings = ControllerSettings()):
        if not settings.motion_limit_rad_s > 0:
            raise ValueError(f"motion_limit_rad_s = {settings.motion_limit_rad_s} must be positive")
        if np.any(settings.motion_limit_rad_s > head.max_speed + 1e-12):
            raise ValueError(f"the controlled-motion limit {settings.motion_limit_rad_s:.3g} rad/s exceeds the servos' "
                             f"{float(np.min(head.max_speed)):.3g} rad/s; use at most that")
        self.head = head
        self.camera = camera
        self.dt = float(dt)
        self.settings = settings
        self.lead = settings.lead_s if settings.lead_s is not None else self.dt + settings.servo_lag_s
        self.filter = ServoFilter(head, q0, speed_limit=settings.motion_limit_rad_s)
        self.speed = self.filter.speed
        self.qp = RateQP(settings.qp)
        self.attitude = AttitudeFilter()
        self.qd_prev = np.zeros(3)
        self.active: Mode = Hold()
        self.T_world_mount: np.ndarray | None = None
        self.v_mount = np.zeros(3)
        self.w_mount = np.zeros(3)    # world frame, rad/s
        self.q_enc = np.asarray(q0, float).copy()
        self.qd_enc = np.zeros(3)           # the encoders' rate over the last period
        self.R_mount_cam_prev = forward_kinematics(head, self.q_enc).R_mount_cam
        self.dR_cam: tuple[np.ndarray, float] | None = None   # the gyro's turn over the last period and its span, s
        self.pose_enc = forward_kinematics(head, self.q_enc)   # the head's FK at the encoder angles
        self.t = 0.0
        self._last_prompt_t = -np.inf
        self.prompts: list[tuple[float, Prompt]] = []
        self.landed = False

    # ------------------------------------------------------------------ modes
    @property
    def mode(self) -> str:
        """The active mode's name (one of :data:`MODES`)."""
        return self.active.name

    def set_mode(self, mode: Mode) -> None:
        """Make a mode object (runtime.gaze.modes) active; the methods below build and check them."""
        self.active = mode
        if isinstance(mode, Saccade):
            self.landed = False

    def fixate(self, p_world) -> None:
        """Hold the optic axis on a world point (m); refused (GazeRefused) if unreachable now."""
        self._aim_at(Fixate(p_world))

    def saccade(self, p_world) -> None:
        """Move the gaze to a world point (in view or not) at the controlled-motion limit, then
        hold it there (fixation). Refused if unreachable from the wearer's current pose."""
        self._aim_at(Saccade(p_world))

    def stabilise(self, R_world_cam=None) -> None:
        """Path A: hold the camera's attitude (default: the present one, from the IMU alone)."""
        R = self.attitude.R if R_world_cam is None else np.asarray(R_world_cam, float)
        if R is None:
            raise ValueError("stabilise needs an attitude: step the controller with IMU samples first")
        self.set_mode(Stabilise(R))

    def body(self, d_mount=None) -> None:
        """Path B: hold a gaze direction relative to the wearer's body (mount frame); default
        the present one. Refused if no joint angles point that way."""
        if d_mount is None:
            d_mount = forward_kinematics(self.head, self.filter.q).optic_axis
        d_mount = np.asarray(d_mount, float)
        res = gaze_at_direction(self.head, d_mount, self.up_mount(), q_current=self.filter.q)
        if not res.reachable:
            raise GazeRefused(f"body direction {np.round(d_mount, 3).tolist()} unreachable: {res.reason}")
        self.set_mode(Body(d_mount, res.q.copy()))

    def track(self, uv) -> None:
        """Keep an image point (pixel) centred, e.g. a 2D tracker's target; call again with
        each new measurement."""
        self.set_mode(Track(uv))

    def slave(self, q) -> None:
        """Follow joint angles given from outside (3,), rad: a tracked person's head mapped onto
        the wearable's joints (vision2d.headtrack.head_to_joint_targets). Call again with each
        new target; angles outside the joint ranges are refused (map them into range first)."""
        mode = Slave(q)
        out = (mode.q < self.head.lower - 1e-12) | (mode.q > self.head.upper + 1e-12)
        if out.any():
            raise GazeRefused(f"slave target {np.degrees(mode.q).round(1).tolist()} deg lies outside the joint ranges")
        self.set_mode(mode)

    def hold(self) -> None:
        self.set_mode(Hold())

    def _aim_at(self, mode: Fixate) -> None:
        p = mode.p_world
        if self.T_world_mount is not None:
            res = ik_point(self.head, p, self.T_world_mount, self.filter.q)
            if not res.reachable:
                prompt = wearer_prompt(self.head, self.T_world_mount, p, self.filter.q)
                self.emit(prompt, force=True)
                raise GazeRefused(f"target {np.round(p, 3).tolist()} m is out of the head's reach: {res.reason}", prompt)
        self.set_mode(mode)

    # ------------------------------------------------------------------ estimation
    def up_mount(self) -> np.ndarray:
        """(3,) world up in the mount frame, from the present estimate."""
        return up_mount(self.T_world_mount, self.attitude.R, self.pose_enc.R_mount_cam)

    def estimate(self, T_world_cam=None) -> GazeEstimate:
        """The present estimate as the modes see it (frozen): built once per period by :meth:`step`.
        T_world_cam : (4, 4) this period's SLAM pose, or None."""
        return GazeEstimate(t=self.t, q_enc=self.q_enc, q=self.filter.q, T_mount_cam=self.pose_enc.T_mount_cam,
                            T_world_cam=T_world_cam, T_world_mount=self.T_world_mount, v_mount=self.v_mount,
                            w_mount=self.w_mount, R_world_cam=self.attitude.R, lead=self.lead,
                            prompt_due=self.prompt_due())

    def _estimate_mount(self, T_world_cam, v_world) -> None:
        pose = self.pose_enc
        if T_world_cam is not None:
            T_mount_cam = pose.T_mount_cam
            T = np.asarray(T_world_cam, float) @ np.linalg.inv(T_mount_cam)
        elif self.attitude.R is not None:
            # No vision: rotation from the IMU, position held where it was last seen.
            T = np.eye(4) if self.T_world_mount is None else self.T_world_mount.copy()
            T[:3, :3] = self.attitude.R @ pose.R_mount_cam.T
        else:
            return
        R_wm = T[:3, :3]
        # The head's own contribution to the camera's motion over the last period.
        R_wc = T[:3, :3] @ pose.R_mount_cam
        if self.dR_cam is not None:
            # The mount's turn over the period: the camera's (the gyro's, R_wc_prev = R_wc dR^T)
            # less the head's (the encoders' before and after).
            dR, span = self.dR_cam
            turn = R_wc @ pose.R_mount_cam.T @ self.R_mount_cam_prev @ dR @ R_wc.T
            self.w_mount = Rotation.from_matrix(turn).as_rotvec() / span
        elif self.attitude.t is not None:
            self.w_mount = R_wc @ self.attitude.omega_cam - R_wm @ (pose.axes_mount.T @ self.qd_enc)
        else:
            self.w_mount = np.zeros(3)        # without any gyro sample the wearer's rotation is unknown: still
        if v_world is not None:
            lever = R_wm @ pose.p_mount_cam                        # mount origin -> optical centre
            v_joints = R_wm @ (np.cross(pose.axes_mount, pose.p_mount_cam - pose.origins_mount).T @ self.qd_enc)
            self.v_mount = np.asarray(v_world, float) - np.cross(self.w_mount, lever) - v_joints
        elif self.T_world_mount is not None and T_world_cam is not None:
            self.v_mount = (T[:3, 3] - self.T_world_mount[:3, 3]) / self.dt
        self.T_world_mount = T

    # ------------------------------------------------------------------ control
    def prompt_due(self) -> bool:
        """Whether a standing prompt would be repeated now: its search (up to 80 IK solves) is
        made only then, not every period, so an unreachable target never slows the loop."""
        return self.t - self._last_prompt_t >= self.settings.prompt_every_s

    def emit(self, prompt: Prompt, force: bool = False) -> Prompt | None:
        """Record a wearer prompt if one is due (or ``force``); returns it, or None if not emitted."""
        if prompt.kind == "ok":          # reachable from where the wearer is now: nothing to ask
            return None
        if force or self.prompt_due():
            self._last_prompt_t = self.t
            self.prompts.append((self.t, prompt))
            return prompt
        return None

    def step(self, t: float, imu, encoders, T_world_cam=None, v_world=None) -> GazeCommand:
        """One control period.

        t : s. imu : (k, 7) IMU rows since the last step. encoders : (3,) rad.
        T_world_cam : (4, 4) SLAM's camera pose, or None (lost, or no SLAM).
        v_world : (3,) SLAM's camera velocity, m/s, or None.
        """
        self.t = float(t)
        enc = np.asarray(encoders, float)
        if enc.shape != (3,) or not np.isfinite(enc).all():
            raise ValueError(f"encoder angles must be 3 finite radians, got {np.asarray(encoders).tolist()}")
        # The joints' and the camera's motion over the same period (the encoders' change, the
        # gyro's mean): the wearer's rotation is their difference. The commanded rate and the
        # latest gyro sample are not simultaneous when the servos reach their targets early in
        # the period (a speed-limited board), and their difference then rang through the loop.
        self.qd_enc = (enc - self.q_enc) / self.dt
        self.R_mount_cam_prev = self.pose_enc.R_mount_cam
        self.dR_cam = _gyro_rotation(imu)
        self.q_enc = enc
        self.pose_enc = forward_kinematics(self.head, enc)    # once per period, used by every mode
        self.attitude.update(imu)
        if T_world_cam is not None and not np.isfinite(np.asarray(T_world_cam, float)).all():
            T_world_cam = None
        self._estimate_mount(T_world_cam, v_world)
        goal: Desired = self.active.desired(self.estimate(T_world_cam), self.head, self.camera)
        q_des, err, reachable = goal.q, goal.error_rad, goal.reachable
        prompt = self.emit(goal.prompt) if goal.prompt is not None else None
        q = self.filter.q
        if q_des is None:
            qd_des = np.zeros(3)
        else:
            qd_des = (q_des - q) / self.dt
        lo, hi = RateQP.bounds(q, self.head.lower, self.head.upper, self.speed, self.dt)
        pose = forward_kinematics(self.head, q)
        J_cam = pose.R_mount_cam.T @ pose.axes_mount.T          # camera-frame angular velocity per joint rate
        qd = self.qp.solve(J_cam, qd_des, self.qd_prev, lo, hi)
        q_cmd = self.filter.step_rate(qd, self.dt)            # the hard limits: range and speed
        qd_sent = (q_cmd - q) / self.dt
        self.qd_prev = qd_sent
        landed = False
        if self.mode == "saccade" and not self.landed and reachable and err < self.settings.landed_rad \
                and np.max(np.abs(qd_sent)) < 0.2 * float(np.min(self.speed)):
            self.landed = landed = True
        return GazeCommand(t=self.t, mode=self.mode, q=q_cmd, qd=qd_sent, q_desired=q_des, error_rad=err,
                           reachable=reachable, prompt=prompt, landed=landed)
