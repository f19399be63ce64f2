"""Procedural motions of the body: walk, sit down, turn, reach to a bench; and the pose set.

Each returns a :class:`placement.body.Motion`, the same object an imported BVH gives, so
scores, maps and the twin treat them alike. Rotation conventions (body frame: X left, -Y
forward, Z up): +X turns a hanging limb backwards and leans the trunk forwards, so hip and
shoulder flexion are negative X rotations and knee flexion positive; +Z turns to the left.
Angles follow textbook gait and sit-to-stand kinematics (Winter, 2009; Perry, 1992), rounded.
"""

from __future__ import annotations

import math

import numpy as np

from .body import SEGMENT_INDEX, SEGMENTS, Body, Motion, Pose

D = math.radians


def _smooth(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk ramp 0 -> 1 over s in [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def _empty(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros((n, len(SEGMENTS), 3)), np.zeros((n, 3))


def _set(rv: np.ndarray, seg: str, axis: int, angle: np.ndarray) -> None:
    rv[:, SEGMENT_INDEX[seg], axis] += angle


def walk(body: Body, seconds: float = 2.2, rate_hz: float = 30.0, speed_m_s: float = 1.3,
         cycle_s: float = 1.1) -> Motion:
    """Level walking towards -Y: two gait cycles by default, with pelvis bounce, sway and turn."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    rv, root = _empty(len(t))
    phi = 2 * math.pi * t / cycle_s
    for side, ph in (("l", phi), ("r", phi + math.pi)):
        hip_flex = D(10) + D(20) * np.sin(ph)                        # +30 flexion .. -10 extension
        knee_flex = D(5) + D(30) * (1 - np.cos(ph - D(60)))      # 5 .. 65 degrees, peaks in swing
        ankle = D(8) * np.sin(ph + D(90))
        _set(rv, f"thigh_{side}", 0, -hip_flex)
        _set(rv, f"shank_{side}", 0, knee_flex)
        _set(rv, f"foot_{side}", 0, ankle)
        # Arms swing against the same-side leg.
        _set(rv, f"upper_arm_{side}", 0, D(12) * np.sin(ph))
        _set(rv, f"forearm_{side}", 0, -(D(15) + D(8) * np.sin(ph + math.pi) / 2))
    _set(rv, "pelvis", 2, D(5) * np.sin(phi))          # pelvic rotation
    _set(rv, "pelvis", 1, D(3) * np.sin(phi))          # pelvic list
    _set(rv, "chest", 2, -D(6) * np.sin(phi))          # thorax counter-rotation
    _set(rv, "head", 2, D(2) * np.sin(phi))
    root[:, 1] = -speed_m_s * t
    root[:, 2] = 0.02 * np.cos(2 * phi)                # two bounces per cycle
    root[:, 0] = 0.015 * np.sin(phi)                   # lateral sway
    return Motion("walk", t, rv, root)


def sit_down(body: Body, seconds: float = 3.0, rate_hz: float = 30.0) -> Motion:
    """From standing to sitting on a chair behind the wearer (as in the paper's Fig. 4)."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    rv, root = _empty(len(t))
    s = _smooth(t / (0.8 * seconds))
    lean = np.sin(math.pi * np.clip(t / (0.8 * seconds), 0, 1))     # forward lean peaks mid-way
    thigh = np.linalg.norm(body.joints[SEGMENT_INDEX["shank_l"]] - body.joints[SEGMENT_INDEX["thigh_l"]])
    for side in ("l", "r"):
        _set(rv, f"thigh_{side}", 0, -D(90) * s)
        _set(rv, f"shank_{side}", 0, D(90) * s)
        _set(rv, f"upper_arm_{side}", 0, -D(25) * s)
        _set(rv, f"forearm_{side}", 0, -D(35) * s)
    _set(rv, "abdomen", 0, D(20) * lean + D(5) * s)
    _set(rv, "chest", 0, D(15) * lean)
    _set(rv, "head", 0, -D(20) * lean)                  # keeps looking ahead
    # The feet stay put: with knee flexion equal to hip flexion the shanks stay vertical, so the
    # hips ride on a circle of thigh length about the knees, back and down to knee height.
    a = D(90) * s
    root[:, 1] = thigh * np.sin(a)
    root[:, 2] = thigh * (np.cos(a) - 1)
    return Motion("sit-down", t, rv, root)


def turn(body: Body, seconds: float = 2.0, rate_hz: float = 30.0, angle_deg: float = 90.0) -> Motion:
    """Turning on the spot to the left, with small stepping."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    rv, root = _empty(len(t))
    s = _smooth(t / seconds)
    _set(rv, "pelvis", 2, D(angle_deg) * s)
    _set(rv, "head", 2, D(15) * np.sin(math.pi * s))   # the head leads the turn
    step = np.sin(2 * math.pi * t / (seconds / 2))
    for side, sign in (("l", 1.0), ("r", -1.0)):
        lift = np.clip(sign * step, 0, None)
        _set(rv, f"thigh_{side}", 0, -D(20) * lift)
        _set(rv, f"shank_{side}", 0, D(35) * lift)
    root[:, 2] = -0.01 * np.abs(step)
    return Motion("turn", t, rv, root)


def reach(body: Body, seconds: float = 2.0, rate_hz: float = 30.0, side: str = "r") -> Motion:
    """Reaching with one hand to a bench in front at waist height, leaning in and looking down."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    rv, root = _empty(len(t))
    s = _smooth(t / (0.75 * seconds))
    _set(rv, f"upper_arm_{side}", 0, -D(65) * s)
    _set(rv, f"upper_arm_{side}", 2, D(10) * s * (1 if side == "r" else -1))
    _set(rv, f"forearm_{side}", 0, -D(20) * s)
    _set(rv, f"hand_{side}", 0, D(10) * s)
    _set(rv, "abdomen", 0, D(12) * s)
    _set(rv, "chest", 0, D(10) * s)
    _set(rv, "head", 0, D(20) * s)                     # looking down at the bench
    return Motion("reach", t, rv, root)


def stand(body: Body, seconds: float = 12.0, rate_hz: float = 30.0) -> Motion:
    """Standing at a bench: postural sway (a few millimetres, ~0.2 Hz) and breathing."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    rv, root = _empty(len(t))
    root[:, 0] = 0.004 * np.sin(2 * math.pi * 0.17 * t)
    root[:, 1] = 0.006 * np.sin(2 * math.pi * 0.23 * t + 1.0)
    _set(rv, "chest", 0, D(0.8) * np.sin(2 * math.pi * 0.25 * t))    # breathing
    _set(rv, "head", 0, D(1.5) * np.sin(2 * math.pi * 0.11 * t))
    return Motion("stand", t, rv, root)


def stand_then(body: Body, then, first_s: float, seconds: float, rate_hz: float = 30.0) -> Motion:
    """Standing still (:func:`stand`) for ``first_s`` seconds, then ``then(body, rest)`` for the
    remaining ``seconds - first_s`` (at least a second). The stance's sway and breathing fade out
    over its last second, so that the two join without a jump."""
    a = stand(body, first_s, rate_hz)
    b = then(body, max(seconds - first_s, 1.0), rate_hz)
    fade = np.clip(first_s - a.t, 0.0, 1.0)
    return Motion(f"stand-then-{b.name}", np.r_[a.t, a.t[-1] + 1.0 / rate_hz + b.t],
                  np.concatenate([a.rotvec * fade[:, None, None], b.rotvec]),
                  np.concatenate([a.root_m * fade[:, None], b.root_m]))


def turn_round(body: Body, seconds: float = 30.0, rate_hz: float = 30.0, turns: int = 4, angle_deg: float = 90.0,
               first_s: float = 5.0, turn_s: float = 3.0, pause_s: float = 3.25) -> Motion:
    """Standing in one place and turning round to the left in steps: still (:func:`stand`) for
    ``first_s``, then ``turns`` turns of ``angle_deg`` each (:func:`turn`: its stepping and the
    head's lead) over ``turn_s``, each followed by ``pause_s`` standing. The schedule is fixed: a
    shorter ``seconds`` cuts it, a longer one ends standing. The default is a whole turn round
    a room in 30 s."""
    base = stand(body, seconds, rate_hz)           # sway and breathing throughout
    rv, root = base.rotvec.copy(), base.root_m.copy()
    one = turn(body, turn_s, rate_hz, angle_deg)
    pelvis = SEGMENT_INDEX["pelvis"]
    for k in range(turns):
        i0 = int(round((first_s + k * (turn_s + pause_s)) * rate_hz))
        n = min(len(one.t), len(base.t) - i0)
        if n <= 0:
            break
        rv[i0:i0 + n] += one.rotvec[:n]
        root[i0:i0 + n] += one.root_m[:n]
        # After the turn the body keeps its new heading (the turn's last sample is within a
        # hair of the full angle: the ramp is flat there).
        rv[i0 + n:, pelvis, 2] += D(angle_deg)
    return Motion("turn-round", base.t, rv, root)


PROCEDURAL = {"walk": walk, "sit-down": sit_down, "turn": turn, "reach": reach}


def default_motions(body: Body) -> list[Motion]:
    """The motion set for motion resilience: walk, sit down, turn, reach."""
    return [fn(body) for fn in PROCEDURAL.values()]


def default_poses(body: Body) -> dict[str, Pose]:
    """The pose set for field of view and handling view: standing, mid-stride, seated, reaching."""
    w, s, r = walk(body), sit_down(body), reach(body)
    return {"standing": Pose.rest(), "walking": w.pose(len(w) // 4), "seated": s.pose(len(s) - 1),
            "reaching": r.pose(len(r) - 1)}
