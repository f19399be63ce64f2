"""Forward kinematics of the head and its Jacobians, vectorised over batches of joint angles.

Joint angles ``q`` are ``(..., 3)`` arrays in chain order (elevation, pan, cyclotorsion),
radians. Every returned pose is expressed in the ``mount`` frame (see :mod:`kinematics.geometry`);
``T_mount_x`` maps coordinates in frame x to the mount frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import HeadGeometry


def axis_angle_matrix(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices about a fixed unit ``axis`` (3,) by ``angle`` (...,) radians -> (..., 3, 3).

    Rodrigues' formula, R = I + sin(t) K + (1 - cos(t)) K^2, written out so that a batch of a
    million angles costs a few array operations.
    """
    angle = np.asarray(angle, float)
    x, y, z = (float(v) for v in axis)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    K2 = np.array([[x * x - 1.0, x * y, x * z], [x * y, y * y - 1.0, y * z], [x * z, y * z, z * z - 1.0]])  # K @ K
    s = np.sin(angle)[..., None, None]
    c = np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * K2


@dataclass(frozen=True)
class ChainPose:
    """Result of :func:`forward_kinematics`.

    T_mount_link : (..., 3, 4, 4) pose of each link frame (elevation, pan, cyclotorsion).
    T_mount_cam : (..., 4, 4) pose of the camera's optical frame (x right, y down, z forward).
    axes_mount : (..., 3, 3) joint axes in the mount frame, row i for joint i.
    origins_mount : (..., 3, 3) joint origins (points on each axis) in the mount frame, metres.
    """

    T_mount_link: np.ndarray
    T_mount_cam: np.ndarray
    axes_mount: np.ndarray
    origins_mount: np.ndarray

    @property
    def R_mount_cam(self) -> np.ndarray:
        return self.T_mount_cam[..., :3, :3]

    @property
    def p_mount_cam(self) -> np.ndarray:
        """(..., 3) optical centre in the mount frame, metres."""
        return self.T_mount_cam[..., :3, 3]

    @property
    def optic_axis(self) -> np.ndarray:
        """(..., 3) unit gaze direction (optical z) in the mount frame."""
        return self.T_mount_cam[..., :3, 2]


def forward_kinematics(head: HeadGeometry, q) -> ChainPose:
    """Poses of every link and of the optical frame for joint angles ``q`` (..., 3), radians."""
    q = np.asarray(q, float)
    if q.shape[-1:] != (3,):
        raise ValueError(f"joint angles must have shape (..., 3) (elevation, pan, cyclotorsion), got {q.shape}")
    batch = q.shape[:-1]
    origins, axes = head.origins, head.axes
    R = np.broadcast_to(np.eye(3), batch + (3, 3))
    p = np.zeros(batch + (3,))
    T_links, ax_m, or_m = [], [], []
    for i in range(3):
        # Link i's frame: at the joint origin (in the parent frame), rotated about the joint axis.
        p = p + R @ origins[i]
        a = R @ axes[i]
        R = R @ axis_angle_matrix(axes[i], q[..., i])
        ax_m.append(a)
        or_m.append(p)
        T_links.append(_homogeneous(R, p))
    T_link_cam = head.camera.T_link_cam
    R_cam = R @ T_link_cam[:3, :3]
    p_cam = p + R @ T_link_cam[:3, 3]
    return ChainPose(
        T_mount_link=np.stack(T_links, axis=-3),
        T_mount_cam=_homogeneous(R_cam, p_cam),
        axes_mount=np.stack(ax_m, axis=-2),
        origins_mount=np.stack(or_m, axis=-2),
    )


def _homogeneous(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def angular_jacobian(head: HeadGeometry, q, pose: ChainPose | None = None) -> np.ndarray:
    """(..., 3, 3) J_w with camera angular velocity (mount frame) = J_w @ qdot.

    Column i is joint i's axis in the mount frame: every joint turns the camera about its axis.
    """
    pose = forward_kinematics(head, q) if pose is None else pose
    return np.swapaxes(pose.axes_mount, -1, -2)


def optical_centre_jacobian(head: HeadGeometry, q, pose: ChainPose | None = None) -> np.ndarray:
    """(..., 3, 3) J_v with optical-centre velocity (mount frame, m/s) = J_v @ qdot.

    Column i is axis_i x (p_cam - o_i): the centre swings about each axis on a lever arm from
    any point o_i on that axis.
    """
    pose = forward_kinematics(head, q) if pose is None else pose
    lever = pose.p_mount_cam[..., None, :] - pose.origins_mount
    return np.swapaxes(np.cross(pose.axes_mount, lever), -1, -2)


def point_jacobian(head: HeadGeometry, q, point_link: np.ndarray, link: int, pose: ChainPose | None = None) -> np.ndarray:
    """(..., 3, 3) velocity Jacobian of a point fixed in link ``link`` (0, 1, 2), mount frame.

    Joints after ``link`` do not move the point, so their columns are zero.
    """
    pose = forward_kinematics(head, q) if pose is None else pose
    T = pose.T_mount_link[..., link, :, :]
    p = np.einsum("...ij,j->...i", T[..., :3, :3], np.asarray(point_link, float)) + T[..., :3, 3]
    lever = p[..., None, :] - pose.origins_mount
    J = np.cross(pose.axes_mount, lever)
    J[..., link + 1:, :] = 0.0
    return np.swapaxes(J, -1, -2)


def radii_of_rotation(head: HeadGeometry, q=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(..., 3) distance of the optical centre from each joint axis at angles q, metres.

    The paper's criteria (v)-(vii): the smaller, the less the image sensor translates when the
    head turns, so the closer a rotation is to a pure rotation about the sensor centre.
    """
    pose = forward_kinematics(head, q)
    lever = pose.p_mount_cam[..., None, :] - pose.origins_mount
    return np.linalg.norm(np.cross(pose.axes_mount, lever), axis=-1)
