"""Wearer prompts: when a gaze target is beyond the head's joint ranges from where the wearer
stands, say which way and roughly how far the wearer should turn or step so that the head can
see it (the paper's section 5, "request the wearer to move").

The search is over the motions a person makes on request: turning on the spot about the
vertical through the mount (left is positive, anticlockwise seen from above), then stepping
towards or away from the point. Each candidate moves the mount frame, not the point, and asks
the fixation IK whether the point is then reachable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kinematics import HeadGeometry, gaze_at_point


#: Turn steps in a band of the coarse search.
_COARSE = 4


@dataclass(frozen=True)
class Prompt:
    """kind : "turn", "step", "none" (no single turn or step helps) or "ok" (already reachable).
    turn_rad : the turn, radians, left positive. step_m : the step along the horizontal
    direction to the point, metres (negative: step back). text : what to tell the wearer."""

    kind: str
    turn_rad: float = 0.0
    step_m: float = 0.0
    text: str = ""


def _reachable(head: HeadGeometry, T_world_mount: np.ndarray, p_world: np.ndarray, q_current) -> bool:
    R, p = T_world_mount[:3, :3], T_world_mount[:3, 3]
    res = gaze_at_point(head, R.T @ (p_world - p), R.T @ np.array([0.0, 0.0, 1.0]), q_current=q_current)
    return res.reachable


def turned_mount(T_world_mount: np.ndarray, psi: float) -> np.ndarray:
    """(4, 4) the mount after the wearer turns on the spot by ``psi`` rad (left positive) about
    the vertical through the mount."""
    c, s = math.cos(psi), math.sin(psi)
    T = np.asarray(T_world_mount, float).copy()
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
    return T


def turn_prompt(psi: float) -> Prompt:
    """The request to turn on the spot by ``psi`` rad (left positive), said to 5 deg."""
    way = "left" if psi > 0 else "right"
    return Prompt("turn", turn_rad=psi, text=f"turn {way} about {round(math.degrees(abs(psi)) / 5) * 5:.0f} deg")


def wearer_prompt(head: HeadGeometry, T_world_mount: np.ndarray, p_world, q_current=None,
                  turn_step_rad: float = math.radians(5.0), steps_m=(0.25, 0.5, 0.75, 1.0)) -> Prompt:
    """The smallest turn (then the smallest step) that makes ``p_world`` (3,) fixatable.

    T_world_mount : (4, 4) where the head's mount is now. Returns a :class:`Prompt`; kind "ok"
    when the point is already reachable (nothing to ask)."""
    p_world = np.asarray(p_world, float)
    T = np.asarray(T_world_mount, float)
    if _reachable(head, T, p_world, q_current):
        return Prompt("ok", text="the point is reachable; nothing to ask")

    # Coarse to fine, each step of ``turn_step_rad`` as the plain search would meet them: the
    # first band of COARSE steps whose far end is reachable (either way) is searched step by
    # step. About a third of the IK solves of a step-by-step search for a far turn (the
    # reachable turns form an interval much wider than a band: the pan range).
    n = int(round(math.pi / turn_step_rad))
    for b0 in range(0, n, _COARSE):
        b1 = min(b0 + _COARSE, n)
        if not any(_reachable(head, turned_mount(T, sign * b1 * turn_step_rad), p_world, q_current)
                   for sign in (1.0, -1.0)):
            continue
        for i in range(b0 + 1, b1 + 1):
            for sign in (1.0, -1.0):
                psi = sign * i * turn_step_rad
                if _reachable(head, turned_mount(T, psi), p_world, q_current):
                    return turn_prompt(psi)
    d = p_world[:2] - T[:2, 3]
    if np.linalg.norm(d) > 1e-9:
        d = d / np.linalg.norm(d)
        for step in steps_m:
            for sign in (-1.0, 1.0):
                Tn = T.copy()
                Tn[:2, 3] += sign * step * d
                if _reachable(head, Tn, p_world, q_current):
                    way = "back" if sign < 0 else "towards it"
                    return Prompt("step", step_m=sign * step, text=f"step {way} about {step:.2f} m")
    return Prompt("none", text="no single turn or step brings the point within the head's reach")
