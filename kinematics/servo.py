"""The servo command filter: the one gate between any controller and the head's servos.

Every joint command, from the gaze controller, the twin, a 2D competence or a hardware driver,
goes through :class:`ServoFilter`, which clamps position to the joint range and the step to the
speed limit (the servo's, or a tighter one such as the paper's ~30 deg/s for controlled
motions), and refuses non-finite commands. It also estimates the torque a motion needs
(gravity + inertia of the carried parts) so callers can see when a servo would stall.
"""

from __future__ import annotations

import math

import numpy as np

from .dynamics import GRAVITY, inverse_dynamics, link_inertias
from .geometry import JOINT_NAMES, HeadGeometry


class ServoCommandError(ValueError):
    """A command the filter refuses outright (non-finite, wrong shape, bad time step)."""


def _limits(head: HeadGeometry, speed_limit) -> np.ndarray:
    vmax = head.max_speed
    if speed_limit is None:
        return vmax
    v = np.broadcast_to(np.asarray(speed_limit, float), (3,)).copy()
    if not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise ServoCommandError(f"speed limit {v.tolist()} rad/s must be positive and finite")
    over = v > vmax + 1e-12
    if np.any(over):
        j = int(np.argmax(over))
        raise ServoCommandError(
            f"speed limit {v[j]:.3g} rad/s for {JOINT_NAMES[j]} exceeds the servo's {vmax[j]:.3g} rad/s; "
            f"use at most {vmax[j]:.3g}"
        )
    return v


class ServoFilter:
    """Stateful command filter for the three servos.

    Parameters
    ----------
    head : the head whose joint ranges and servo models bound the commands.
    q0 : (3,) initial commanded angles, radians (clamped into range).
    speed_limit : scalar or (3,) rad/s, at most each servo's own limit; default the servos'.
    """

    def __init__(self, head: HeadGeometry, q0=(0.0, 0.0, 0.0), speed_limit=None):
        self.head = head
        self.lower = head.lower
        self.upper = head.upper
        self.speed = _limits(head, speed_limit)
        self._inertias = link_inertias(head)
        self.q = self._clamp(self._checked(q0, "initial angles"))
        self.clamped_position = 0  # commands whose target lay outside the range
        self.clamped_speed = 0     # commands whose step exceeded the speed limit

    def _checked(self, q, what) -> np.ndarray:
        q = np.asarray(q, float)
        if q.shape != (3,):
            raise ServoCommandError(f"{what} must be 3 angles (elevation, pan, cyclotorsion), got shape {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ServoCommandError(f"{what} {q.tolist()} contain NaN or Inf; command refused, servos hold position")
        return q

    def _clamp(self, q: np.ndarray) -> np.ndarray:
        return np.minimum(np.maximum(q, self.lower), self.upper)

    def reset(self, q0) -> None:
        self.q = self._clamp(self._checked(q0, "initial angles"))

    def step(self, q_target, dt: float) -> np.ndarray:
        """Advance one control period: returns the command actually sent (3,), radians."""
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ServoCommandError(f"time step dt = {dt!r} s must be positive and finite")
        target = self._checked(q_target, "joint command")
        in_range = self._clamp(target)
        if np.any(in_range != target):
            self.clamped_position += 1
        max_step = self.speed * dt
        step = np.clip(in_range - self.q, -max_step, max_step)
        if np.any(step != in_range - self.q):
            self.clamped_speed += 1
        # Clamp again: the previous command is inside the range, so this only guards rounding.
        self.q = self._clamp(self.q + step)
        return self.q.copy()

    def step_rate(self, qd, dt: float) -> np.ndarray:
        """Command joint rates (3,), rad/s, for one period: integrated, then filtered like positions."""
        qd = self._checked(qd, "joint rate command")
        return self.step(self.q + qd * dt, dt)

    def required_torque(self, q, qd, qdd, gravity_mount=(0.0, 0.0, -GRAVITY), **mount_motion) -> np.ndarray:
        """Torque estimate (..., 3), N m: gravity and inertia of the carried parts (RNEA)."""
        return inverse_dynamics(self.head, q, qd, qdd, gravity_mount=gravity_mount, inertias=self._inertias,
                                **mount_motion)

    def torque_margin(self, tau) -> np.ndarray:
        """Stall torque minus |tau| per joint, N m; negative means the servo would stall."""
        return self.head.max_torque - np.abs(np.asarray(tau, float))


def filter_sequence(head: HeadGeometry, q_targets, dt: float, q0=(0.0, 0.0, 0.0), speed_limit=None) -> np.ndarray:
    """Run a whole command sequence (N, 3) through a fresh :class:`ServoFilter`; returns (N, 3)."""
    f = ServoFilter(head, q0, speed_limit)
    return np.array([f.step(q, dt) for q in np.asarray(q_targets, float)]).reshape(-1, 3)
