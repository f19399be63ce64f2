"""What a gaze mode may know in one control period: :class:`GazeEstimate`, built once per period
by the controller (runtime.gaze.controller) from the encoders, the IMU and SLAM, and handed to
the active mode (runtime.gaze.modes). A mode reads nothing else of the controller.

Frames: the mount is the head's base on the wearer; the camera is the optical frame (x right,
y down, z forward); the world is SLAM's (z up). SI units and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import HeadGeometry, gaze_at_point

#: World up (z), the image-vertical rule's reference.
UP = np.array([0.0, 0.0, 1.0])


def _frozen(a) -> np.ndarray | None:
    """A read-only copy (None stays None): an estimate is a snapshot, not a handle on the controller."""
    if a is None:
        return None
    a = np.array(a, float)
    a.setflags(write=False)
    return a


def up_mount(T_world_mount: np.ndarray | None, R_world_cam: np.ndarray | None, R_mount_cam: np.ndarray) -> np.ndarray:
    """(3,) world up in the mount frame: from the mount's pose where there is one, else from the
    IMU's attitude through the encoders' camera rotation, else the mount's own z."""
    if T_world_mount is not None:
        return T_world_mount[:3, :3].T @ UP
    if R_world_cam is not None:
        return R_mount_cam @ R_world_cam.T @ UP
    return UP


def ik_point(head: HeadGeometry, p_world: np.ndarray, T_world_mount: np.ndarray, q_current: np.ndarray):
    """The fixation IK (kinematics.gaze_at_point) for a world point (3,) m seen from a mount pose
    (4, 4), with the image-vertical rule's up from that pose; near ``q_current`` (3,) rad."""
    R, o = T_world_mount[:3, :3], T_world_mount[:3, 3]
    return gaze_at_point(head, R.T @ (p_world - o), R.T @ UP, q_current=q_current)


@dataclass(frozen=True)
class GazeEstimate:
    """One control period's estimate, read-only.

    t : s, the period's time.
    q_enc : (3,) rad, the joint angles the robot reported (encoders, or the commands it was sent).
    q : (3,) rad, the angles last commanded (the controller's servo filter): where the IK starts
        and what a joint-space mode's error is measured from.
    T_mount_cam : (4, 4) the camera's pose in the mount frame at ``q_enc`` (the head's FK).
    T_world_cam : (4, 4) SLAM's camera pose this period, or None (lost, or no SLAM).
    T_world_mount : (4, 4) the mount's pose (SLAM's camera pose through the FK, or the IMU's
        rotation with the position last seen), or None before either is known.
    v_mount : (3,) m/s, the mount's velocity (world frame).
    w_mount : (3,) rad/s, the mount's angular rate (world frame): the wearer's turning.
    R_world_cam : (3, 3) the camera's attitude from the IMU alone, or None before any sample.
    lead : s, how far ahead the mount's pose is predicted (the command is reached then).
    prompt_due : whether a standing wearer prompt would be repeated this period (the
        controller's rate limit): a mode builds one only then.
    """

    t: float
    q_enc: np.ndarray
    q: np.ndarray
    T_mount_cam: np.ndarray
    T_world_cam: np.ndarray | None
    T_world_mount: np.ndarray | None
    v_mount: np.ndarray
    w_mount: np.ndarray
    R_world_cam: np.ndarray | None
    lead: float
    prompt_due: bool = False

    def __post_init__(self):
        for name in ("q_enc", "q", "T_mount_cam", "T_world_cam", "T_world_mount", "v_mount", "w_mount", "R_world_cam"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))

    @property
    def R_mount_cam(self) -> np.ndarray:
        """(3, 3) the camera's rotation in the mount frame at the encoders' angles."""
        return self.T_mount_cam[:3, :3]

    def up_mount(self) -> np.ndarray:
        """(3,) world up in the mount frame (see :func:`up_mount`)."""
        return up_mount(self.T_world_mount, self.R_world_cam, self.R_mount_cam)

    def predicted_mount(self, lead: float | None = None) -> np.ndarray:
        """(4, 4) the mount's pose ``lead`` s ahead (default :attr:`lead`) at constant velocity;
        needs :attr:`T_world_mount`."""
        lead = self.lead if lead is None else lead
        T = self.T_world_mount.copy()
        T[:3, :3] = Rotation.from_rotvec(self.w_mount * lead).as_matrix() @ T[:3, :3]
        T[:3, 3] = T[:3, 3] + self.v_mount * lead
        return T
