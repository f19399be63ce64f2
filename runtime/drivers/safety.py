"""The safety chain between a controller and the servos, in layers (after ros2_control's joint
limits and its latched stops). Every command passes, in order:

1. **Range and rate** (``kinematics.ServoFilter``): the joint ranges and the servos' own speed
   (the HS-50's 10 rad/s); non-finite commands are refused (the head holds).
2. **Controlled motion**: a second filter at the controlled-motion limit (paper: ~30 deg/s).
3. **Watchdog**: when the estimate a command rests on (a SLAM pose, the IMU's attitude, a
   tracker's fix: ``JointCommand.basis_t``) or the operator's heartbeat is older than its
   time-out, hold where the head is; after ``hold_s`` more, go home at ``home_rate``.
4. **Pulses**: the calibration maps angles to pulse widths, clipped to each channel's
   ``min_us..max_us``. The board's own speed and acceleration limits (set at start-up from the
   rig's limits, in the Maestro's units) bound how fast the outputs can move even if a wrong
   target got through.
5. **Emergency stop**, latched: once tripped (by a command, the CLI's ``wvr head stop`` through a
   latch file, or a fault), the head holds where it is and no other command moves it until an
   explicit reset (``wvr head reset``).

Each layer keeps counts of what it changed; :meth:`SafetyChain.report` gathers them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kinematics import HeadGeometry, ServoCommandError, ServoFilter

from ..robot import JointCommand


@dataclass(frozen=True)
class SafetySettings:
    """motion_limit_rad_s : the controlled-motion limit. pose_timeout_s : the longest a command's
    basis may be old. heartbeat_timeout_s : the operator's (None: no operator required).
    hold_s : how long to hold before going home. home_rate_rad_s : how fast to go home.
    home : (3,) the home angles, rad."""

    motion_limit_rad_s: float = math.radians(30.0)
    pose_timeout_s: float = 0.5
    heartbeat_timeout_s: float | None = None
    hold_s: float = 1.0
    home_rate_rad_s: float = math.radians(20.0)
    home: tuple = (0.0, 0.0, 0.0)


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
    range_or_servo_speed: int = 0    # commands the range-and-rate filter changed
    motion_limit: int = 0            # commands the controlled-motion filter changed
    watchdog_periods: int = 0        # periods the watchdog held or homed
    estop_periods: int = 0           # periods the e-stop held
    estop_reason: str = ""
    extra: dict = field(default_factory=dict)


class SafetyChain:
    """Layers 1-3 and 5 in software, layer 4's clipping in :meth:`pulses`; see the module."""

    def __init__(self, head: HeadGeometry, q0, settings: SafetySettings = SafetySettings(), estop: EStop | None = None):
        self.head = head
        self.settings = settings
        self.servo = ServoFilter(head, q0)                                   # layer 1
        self.motion = ServoFilter(head, q0, speed_limit=settings.motion_limit_rad_s)   # layer 2
        self.watchdog = Watchdog(settings)                                   # layer 3
        self.estop = estop or EStop()                                        # layer 5
        self.q = self.servo.q.copy()
        self.report_ = SafetyReport()

    def reset_to(self, q) -> None:
        """Start from where the head is (its measured or reported angles)."""
        self.servo.reset(q)
        self.motion.reset(self.servo.q)
        self.q = self.servo.q.copy()

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
