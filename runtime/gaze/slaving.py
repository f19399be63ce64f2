"""Slaving the wearable's head to a tracked head (paper section 3, item 2, Fig. 5a): the tracked
head's yaw, pitch and roll (runtime.vision2d.headtrack) mapped onto the wearable's own joints,
which the gaze controller's slave mode then follows within its rate limits and servo filter.
The yaw, pitch, roll convention is runtime.vision2d.headmodel's.
"""

from __future__ import annotations

import numpy as np


def head_to_joint_targets(ypr, gain=1.0, limits=None, rest=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Desired joint angles (radians) of the wearable's head that copy a tracked head's motion.

    ypr : (3,) yaw, pitch, roll of the tracked head, radians (runtime.vision2d.headmodel).
    gain : scalar or (3,) per (yaw, pitch, roll); 1 copies the motion one to one.
    limits : (2, 3) [[lower], [upper]] joint limits in radians in kinematics' joint order
        (elevation, pan, cyclotorsion), or a HeadGeometry (its ``lower``/``upper``); None = no limits.
    rest : (3,) joint angles (elevation, pan, cyclotorsion) that the offsets are added to.

    Returns (3,) [elevation, pan, cyclotorsion] = rest + gain * [pitch, yaw, roll], clipped to the
    limits: yaw -> pan (both positive to the left: the person turning to their left turns the
    wearable to the wearer's left), pitch -> elevation (both positive up), roll -> cyclotorsion
    (both positive right side down, about the forward axis). Pure function; the gaze controller's
    rate limits and servo filter are applied downstream (runtime.gaze).
    """
    a = np.asarray(ypr, float)
    if a.shape != (3,):
        raise ValueError(f"ypr must be (3,) yaw, pitch, roll in radians, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("ypr has NaN (a lost frame?); do not servo on a lost head pose")
    g = np.broadcast_to(np.asarray(gain, float), (3,)) if np.ndim(gain) <= 1 else None
    if g is None or not np.all(np.isfinite(g)):
        raise ValueError(f"gain must be a finite scalar or (3,) per yaw, pitch, roll, got {gain!r}")
    q0 = np.asarray(rest, float)
    if q0.shape != (3,) or not np.all(np.isfinite(q0)):
        raise ValueError(f"rest must be (3,) finite joint angles (elevation, pan, cyclotorsion), got {rest!r}")
    q = q0 + g[[1, 0, 2]] * a[[1, 0, 2]]
    if limits is None:
        return q
    if hasattr(limits, "lower") and hasattr(limits, "upper"):
        lo, hi = np.asarray(limits.lower, float), np.asarray(limits.upper, float)
    else:
        L = np.asarray(limits, float)
        if L.shape != (2, 3):
            raise ValueError(f"limits must be (2, 3) [[lower], [upper]] radians in the order elevation, pan, "
                             f"cyclotorsion (or a HeadGeometry), got shape {L.shape}")
        lo, hi = L
    if not np.all(lo <= hi):
        raise ValueError(f"limits: every lower bound must be <= its upper bound, got {lo} and {hi}")
    return np.clip(q, lo, hi)
