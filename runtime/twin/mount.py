"""Where the head's mount frame sits on a wearer segment: :class:`Mount`, from mount.toml.

mount.toml (written by ``wvr placement map``) has one schema, :mod:`kinematics.mountfile`; this
module turns it into the twin's Mount. The segment frame has its origin at the segment's joint
centre and the body's axes in the rest pose (+Z up, facing -Y). The mount frame is the head's
(x forward, y left, z up when worn upright): z is ``up``, x is ``forward`` (made perpendicular
to ``up``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinematics.mountfile import MountFileError as MountError
from kinematics.mountfile import load_mount_file

__all__ = ["Mount", "MountError", "default_shoulder_mount", "load_mount"]


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


def load_mount(path: str | Path) -> Mount:
    """The Mount a mount.toml describes (raises MountError naming the file and field)."""
    m = load_mount_file(path)
    return Mount(m.segment, m.position_m, m.up, m.forward, m.zone)


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
