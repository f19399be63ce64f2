"""mount.toml: where the head's mount frame sits on a wearer segment.

Written by ``wvr placement map`` (the best polygon of a zone). The segment frame has its origin
at the segment's joint centre and the body's axes in the rest pose (+Z up, facing -Y). The
mount frame is the head's (x forward, y left, z up when worn upright): z is ``up``, x is
``forward`` (made perpendicular to ``up``); ``normal`` (the surface's) is for reference.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinematics.tomlfile import read_toml


class MountError(ValueError):
    """A mount.toml that cannot be used; the message names the field."""


@dataclass(frozen=True)
class Mount:
    segment: str
    position_m: np.ndarray   # (3,) in the segment frame
    up: np.ndarray           # (3,) mount z in the segment frame
    forward: np.ndarray      # (3,) mount x in the segment frame
    zone: str = ""

    def T_rest_mount(self, joint_centre: np.ndarray) -> np.ndarray:
        """(4, 4) mount frame in the wearer's rest-pose body frame."""
        z = self.up / np.linalg.norm(self.up)
        x = self.forward - z * (self.forward @ z)
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = np.asarray(joint_centre) + self.position_m
        return T


_KEYS = {"zone", "segment", "polygon", "position_m", "up", "forward", "normal", "standoff_m", "stature_m"}


def load_mount(path: str | Path) -> Mount:
    path = Path(path)
    d = read_toml(path, MountError, "a mount.toml written by 'wvr placement map'")
    m = d.get("mount")
    if not isinstance(m, dict):
        raise MountError(f"{path}: missing the [mount] table")
    for k in m:
        if k not in _KEYS:
            raise MountError(f"{path}: [mount] has unknown key {k!r}; allowed keys are {sorted(_KEYS)}")
    vecs = {}
    for k in ("position_m", "up", "forward"):
        v = np.asarray(m.get(k, []), float)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise MountError(f"{path}: [mount].{k} must be 3 finite numbers")
        vecs[k] = v
    for k in ("up", "forward"):
        if abs(np.linalg.norm(vecs[k]) - 1) > 1e-3:
            raise MountError(f"{path}: [mount].{k} must be a unit vector")
    if abs(vecs["up"] @ vecs["forward"]) > 0.99:
        raise MountError(f"{path}: [mount].forward must not be parallel to [mount].up")
    if "segment" not in m:
        raise MountError(f"{path}: [mount].segment is missing (e.g. 'chest')")
    return Mount(str(m["segment"]), vecs["position_m"], vecs["up"], vecs["forward"], str(m.get("zone", "")))


def default_shoulder_mount(wearer, side: str = "r", standoff_m: float = 0.02) -> Mount:
    """On top of the shoulder, as in the paper (Fig. 1a): a levelled pad on the highest point of
    the chest within 6 cm (horizontally) of the shoulder joint, the head looking forward."""
    chest = wearer.index("chest")
    shoulder = wearer.joints[wearer.index(f"upper_arm_{side}")]
    v = wearer.vertices[np.unique(wearer.faces[wearer.face_segment == chest])]
    near = np.linalg.norm(v[:, :2] - shoulder[:2], axis=1) < 0.06
    if not near.any():
        raise MountError("no chest surface above the shoulder joint; give a mount.toml from 'wvr placement map'")
    top = v[near][np.argmax(v[near, 2])]
    up = np.array([0.0, 0.0, 1.0])
    return Mount("chest", top + standoff_m * up - wearer.joints[chest], up, np.array([0.0, -1.0, 0.0]), zone="shoulder")
