"""The safety chain between a controller and any robot, in layers (after ros2_control's joint
limits and its latched stops): the same chain for the twin and the hardware rig, composed by
:class:`SafeRobot` (a :class:`runtime.robot.Robot` wrapping a Robot) in ``wvr.assemble``.
Limits are data (:class:`SafetySettings`, the head's ranges and servo speeds); one limiter
(:class:`JointLimiter`) applies them. Every command passes, in order:

1. **Range and rate**: the joint ranges and the servos' own speed (the HS-50's 10 rad/s);
   non-finite commands are refused (the head holds).
2. **Controlled motion**: the same limiter at the controlled-motion limit (paper: ~30 deg/s,
   :data:`runtime.robot.MOTION_LIMIT_RAD_S`).
3. **Watchdog**: when the estimate a command rests on (a SLAM pose, the IMU's attitude, a
   tracker's fix: ``JointCommand.basis_t``) or the operator's heartbeat is older than its
   time-out, hold where the head is; after ``hold_s`` more, go home at ``home_rate``.
4. **Pulses** (the rig's own, runtime.drivers.rig): the calibration maps angles to pulse widths,
   clipped to each channel's ``min_us..max_us``, and the board's speed and acceleration limits
   bound how fast the outputs can move even if a wrong target got through.
5. **Emergency stop**, latched: once tripped (by a command, the CLI's ``wvr head stop`` through a
   latch file, the station's stop, or a fault), the head holds where it is and no other command
   moves it until an explicit reset (``wvr head reset``).

A command already inside every limit passes unchanged, to the bit, so a healthy twin runs as it
would without the chain. Each layer keeps counts of what it changed; :meth:`SafetyChain.report`
gathers them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kinematics import HeadGeometry, ServoCommandError

from .robot import MOTION_LIMIT_RAD_S, JointCommand, Observation, Robot, RobotInfo


@dataclass(frozen=True)
class SafetySettings:
    """motion_limit_rad_s : the controlled-motion limit. pose_timeout_s : the longest a command's
    basis may be old. heartbeat_timeout_s : the operator's (None: no operator required).
    hold_s : how long to hold before going home. home_rate_rad_s : how fast to go home.
    home : (3,) the home angles, rad."""

    motion_limit_rad_s: float = MOTION_LIMIT_RAD_S
    pose_timeout_s: float = 0.5
    heartbeat_timeout_s: float | None = None
    hold_s: float = 1.0
    home_rate_rad_s: float = math.radians(20.0)
    home: tuple = (0.0, 0.0, 0.0)


class EStopLatched(RuntimeError):
    """A robot asked to start while its emergency stop is latched; the message says how to clear it."""


class JointLimiter:
    """Joint range and rate, a period at a time (layers 1 and 2).

    lower, upper : (3,) the joint range, rad. speed : scalar or (3,) the fastest step, rad/s.
    q0 : (3,) where the joints start, rad (clamped into the range). A target inside the range
    and within ``speed * dt`` of the last output is passed unchanged, to the bit; otherwise it is
    clamped to the range, then to the step (``clamped_position``, ``clamped_speed`` count each).
    Non-finite targets raise :class:`kinematics.ServoCommandError`.
    """

    def __init__(self, lower, upper, speed, q0=(0.0, 0.0, 0.0)):
        self.lower = np.asarray(lower, float).reshape(3)
        self.upper = np.asarray(upper, float).reshape(3)
        self.speed = np.broadcast_to(np.asarray(speed, float), (3,)).copy()
        if not (np.isfinite(self.speed).all() and (self.speed > 0).all()):
            raise ServoCommandError(f"speed limit {self.speed.tolist()} rad/s must be positive and finite")
        self.q = self._in_range(self._checked(q0, "initial angles"))
        self.clamped_position = 0
        self.clamped_speed = 0

    @staticmethod
    def _checked(q, what) -> np.ndarray:
        q = np.asarray(q, float)
        if q.shape != (3,):
            raise ServoCommandError(f"{what} must be 3 angles (elevation, pan, cyclotorsion), got shape {q.shape}")
        if not np.isfinite(q).all():
            raise ServoCommandError(f"{what} {q.tolist()} contain NaN or Inf; command refused, servos hold position")
        return q

    def _in_range(self, q: np.ndarray) -> np.ndarray:
        return np.minimum(np.maximum(q, self.lower), self.upper)

    def reset(self, q) -> None:
        self.q = self._in_range(self._checked(q, "initial angles"))

    def step(self, q_target, dt: float) -> np.ndarray:
        """The output (3,) rad for a target (3,) rad over a period ``dt`` s."""
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ServoCommandError(f"time step dt = {dt!r} s must be positive and finite")
        target = self._checked(q_target, "joint command")
        q = self._in_range(target)
        self.clamped_position += int(np.any(q != target))
        # Bounds as q_prev +- max_step, not the step itself: rounding is monotonic, so a command
        # made as q_prev + s with |s| <= max_step (a controller's own filter) lies inside them.
        max_step = self.speed * dt
        q_rate = np.minimum(np.maximum(q, self.q - max_step), self.q + max_step)
        self.clamped_speed += int(np.any(q_rate != q))
        self.q = self._in_range(q_rate)         # the previous output is inside: this only guards rounding
        return self.q.copy()


class EStop:
    """The latched emergency stop. With a ``latch_file`` the latch outlives the process (and
    another process, e.g. ``wvr head stop``, can trip it by creating the file)."""

    def __init__(self, latch_file: str | Path | None = None):
        self.latch_file = Path(latch_file) if latch_file is not None else None
        self._tripped = False
        self.reason = ""

    @property
    def tripped(self) -> bool:
        if not self._tripped and self.latch_file is not None and self.latch_file.exists():
            self._tripped = True
            self.reason = self.latch_file.read_text().strip() or "the latch file exists"
        return self._tripped

    def trip(self, reason: str) -> None:
        if not self._tripped:
            self._tripped, self.reason = True, reason
        if self.latch_file is not None and not self.latch_file.exists():
            self.latch_file.write_text(reason + "\n")

    def reset(self) -> None:
        """The explicit reset: the only thing that clears the latch."""
        self._tripped, self.reason = False, ""
        if self.latch_file is not None:
            self.latch_file.unlink(missing_ok=True)


class Watchdog:
    """Hold when the command's basis (or the heartbeat) goes stale; go home after ``hold_s``."""

    def __init__(self, settings: SafetySettings):
        self.settings = settings
        self.state = "ok"          # "ok", "hold" or "home"
        self.stale_since: float | None = None
        self.heartbeat_t: float | None = None
        self.trips = 0

    def heartbeat(self, t: float) -> None:
        self.heartbeat_t = float(t)

    def stale(self, command: JointCommand, t: float) -> bool:
        if command.basis_t is not None and t - command.basis_t > self.settings.pose_timeout_s:
            return True
        hb = self.settings.heartbeat_timeout_s
        return hb is not None and (self.heartbeat_t is None or t - self.heartbeat_t > hb)

    def apply(self, q: np.ndarray, q_now: np.ndarray, command: JointCommand, t: float, dt: float) -> np.ndarray:
        if not self.stale(command, t):
            self.state, self.stale_since = "ok", None
            return q
        if self.stale_since is None:
            self.stale_since = t
            self.trips += 1
        if t - self.stale_since < self.settings.hold_s:
            self.state = "hold"
            return q_now.copy()
        self.state = "home"
        step = self.settings.home_rate_rad_s * dt
        return q_now + np.clip(np.asarray(self.settings.home, float) - q_now, -step, step)


@dataclass
class SafetyReport:
    refused: int = 0                 # non-finite or malformed commands (held instead)
    range_or_servo_speed: int = 0    # commands the range-and-rate layer changed
    motion_limit: int = 0            # commands the controlled-motion layer changed
    watchdog_periods: int = 0        # periods the watchdog held or homed
    estop_periods: int = 0           # periods the e-stop held
    estop_reason: str = ""
    extra: dict = field(default_factory=dict)


class SafetyChain:
    """Layers 1-3 and 5 in software (see the module); the rig adds layer 4's clipping."""

    def __init__(self, head: HeadGeometry, q0, settings: SafetySettings = SafetySettings(), estop: EStop | None = None):
        vmax = head.max_speed
        if not (math.isfinite(settings.motion_limit_rad_s) and settings.motion_limit_rad_s > 0) \
                or np.any(settings.motion_limit_rad_s > vmax + 1e-12):
            raise ServoCommandError(f"the controlled-motion limit {settings.motion_limit_rad_s!r} rad/s must be positive "
                                    f"and at most the servos' {float(np.min(vmax)):.3g} rad/s")
        self.head = head
        self.settings = settings
        self.servo = JointLimiter(head.lower, head.upper, vmax, q0)                             # layer 1
        self.motion = JointLimiter(head.lower, head.upper, settings.motion_limit_rad_s, q0)     # layer 2
        self.watchdog = Watchdog(settings)                                                     # layer 3
        self.estop = estop or EStop()                                                          # layer 5
        self.q = self.servo.q.copy()
        self.report_ = SafetyReport()

    def reset_to(self, q) -> None:
        """Start from where the head is (its measured or reported angles), the watchdog fresh."""
        self.servo.reset(q)
        self.motion.reset(self.servo.q)
        self.q = self.servo.q.copy()
        self.watchdog.state, self.watchdog.stale_since = "ok", None

    def apply(self, command: JointCommand, t: float, dt: float) -> np.ndarray:
        """The angles (3,) rad to send this period for ``command`` at time ``t`` (s), ``dt`` the period."""
        r = self.report_
        if self.estop.tripped:
            r.estop_periods += 1
            r.estop_reason = self.estop.reason
            return self.q.copy()
        try:
            c1 = self.servo.clamped_position + self.servo.clamped_speed
            q1 = self.servo.step(command.q, dt)
            r.range_or_servo_speed += int(self.servo.clamped_position + self.servo.clamped_speed > c1)
        except ServoCommandError:
            r.refused += 1
            q1 = self.q.copy()
            self.servo.reset(q1)
        c2 = self.motion.clamped_speed
        q2 = self.motion.step(q1, dt)
        r.motion_limit += int(self.motion.clamped_speed > c2)
        q3 = self.watchdog.apply(q2, self.q, command, t, dt)
        if self.watchdog.state != "ok":
            r.watchdog_periods += 1
        # Whatever the watchdog chose stays inside the range and the slower of the two speeds.
        step = min(float(np.min(self.motion.speed)), float(np.min(self.servo.speed))) * dt
        q3 = np.clip(np.clip(q3, self.q - step, self.q + step), self.head.lower, self.head.upper)
        self.servo.reset(q3)
        self.motion.reset(q3)
        self.q = q3
        return q3.copy()

    def report(self) -> SafetyReport:
        return self.report_


class SafeRobot:
    """Any :class:`runtime.robot.Robot` with every command passed through a :class:`SafetyChain`:
    the twin and the hardware rig are driven through the same layers (``wvr.assemble`` composes
    them). The chain starts where the robot's first observation says the joints are.

    robot : the robot driven. settings : the chain's limits and time-outs. estop : the latch
    (default: one in memory; the rig's lives in a file). reset_hint : how to clear a latched
    stop, for the refusal :meth:`reset` raises (:class:`EStopLatched`).
    """

    def __init__(self, robot: Robot, settings: SafetySettings = SafetySettings(), estop: EStop | None = None,
                 reset_hint: str = "reset the latch (estop.reset()) once it is safe"):
        self.robot = robot
        info = robot.info
        self.chain = SafetyChain(info.head, np.zeros(3), settings, estop)
        self.dt = 1.0 / info.frame_rate
        self.reset_hint = reset_hint
        self.t: float | None = None      # the last observation's time: the commands' watchdog clock

    @property
    def info(self) -> RobotInfo:
        return self.robot.info

    @property
    def estop(self) -> EStop:
        return self.chain.estop

    def reset(self) -> Observation:
        """Refused (EStopLatched) while the stop is latched; else the robot's first observation."""
        if self.estop.tripped:
            raise EStopLatched(f"the emergency stop is latched ({self.estop.reason}); {self.reset_hint}")
        obs = self.robot.reset()
        head = self.info.head
        self.chain.reset_to(np.clip(np.asarray(obs.q, float), head.lower, head.upper))
        self.t = obs.t
        return obs

    def step(self, command: JointCommand) -> Observation:
        """The command through the chain, then to the robot; the robot's next observation."""
        if self.t is None:
            raise RuntimeError("call reset() first")
        q = self.chain.apply(command, self.t, self.dt)
        obs = self.robot.step(JointCommand(q, command.qd, command.basis_t))
        self.t = obs.t
        return obs

    def heartbeat(self, t: float) -> None:
        """The operator's heartbeat (s, the observations' clock), for the watchdog's time-out."""
        self.chain.watchdog.heartbeat(t)

    def report(self) -> SafetyReport:
        return self.chain.report()

    def safe_stop(self, reason: str = "", home: bool = True) -> str:
        """The robot's own safe stop where it has one (the rig: hold, then home slowly unless the
        stop is latched), never raising; returns what happened."""
        stop = getattr(self.robot, "safe_stop", None)
        if stop is None:
            return "nothing to stop (the robot has no safe stop of its own)"
        return stop(reason, home=home and not self.estop.tripped)

    def close(self) -> None:
        self.robot.close()
