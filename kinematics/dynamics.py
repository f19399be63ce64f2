"""Rigid-body dynamics of the head's parts: link inertias and inverse dynamics (joint torques).

The torques are what the servos must deliver to move the parts they carry (gravity plus
inertia, including the mount's own motion on a moving wearer). Recursive Newton-Euler over the
three links, vectorised over batches of states, all vectors in the mount frame. Cross-checked
against MuJoCo's ``mj_inverse`` on the MJCF built from the same geometry (tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .chain import forward_kinematics
from .geometry import JOINT_NAMES, HeadGeometry

GRAVITY = 9.81  # m/s^2, as the twin and MuJoCo models use


@dataclass(frozen=True)
class LinkInertia:
    """Mass properties of one link (all parts it carries, lumped).

    mass_kg : total mass.
    com_m : (3,) centre of mass in the link frame, metres.
    inertia_com : (3, 3) inertia tensor about the centre of mass, link-frame axes, kg m^2.
    """

    mass_kg: float
    com_m: np.ndarray
    inertia_com: np.ndarray


def link_inertias(head: HeadGeometry) -> tuple[LinkInertia, LinkInertia, LinkInertia]:
    """Lumped mass properties of the elevation, pan and cyclotorsion links (parallel-axis theorem)."""
    out = []
    for link in JOINT_NAMES:
        parts = head.parts_on(link)
        m = sum(p.mass_kg for p in parts)
        com = sum(p.mass_kg * np.asarray(p.center_m) for p in parts) / m
        I = np.zeros((3, 3))
        for p in parts:
            r = np.asarray(p.center_m) - com
            I += p.inertia_about_center() + p.mass_kg * ((r @ r) * np.eye(3) - np.outer(r, r))
        out.append(LinkInertia(mass_kg=float(m), com_m=com, inertia_com=I))
    return tuple(out)


def inverse_dynamics(head: HeadGeometry, q, qd, qdd, *, gravity_mount=(0.0, 0.0, -GRAVITY),
                     omega_mount=(0.0, 0.0, 0.0), alpha_mount=(0.0, 0.0, 0.0),
                     accel_mount=(0.0, 0.0, 0.0), inertias=None) -> np.ndarray:
    """Joint torques (..., 3), N m, to realise ``qdd`` at state (q, qd) on a possibly moving mount.

    Parameters
    ----------
    q, qd, qdd : (..., 3) joint angles (rad), rates (rad/s), accelerations (rad/s^2).
    gravity_mount : (..., 3) gravity in the mount frame, m/s^2.
    omega_mount, alpha_mount : (..., 3) the mount's angular velocity and acceleration, expressed
        in the mount frame, rad/s and rad/s^2 (a wearer turning or bobbing).
    accel_mount : (..., 3) linear acceleration of the mount origin in the mount frame, m/s^2.
    inertias : precomputed :func:`link_inertias` (optional, for sweeps).

    Includes each servo's armature (reflected rotor inertia) times its joint acceleration.
    Gravity enters as an upward acceleration of the base (the usual RNEA trick).
    """
    q = np.asarray(q, float)
    qd = np.broadcast_to(np.asarray(qd, float), q.shape)
    qdd = np.broadcast_to(np.asarray(qdd, float), q.shape)
    inertias = link_inertias(head) if inertias is None else inertias
    pose = forward_kinematics(head, q)
    batch = q.shape[:-1]
    z = pose.axes_mount                # (..., 3 joints, 3)
    o = pose.origins_mount             # (..., 3, 3)
    R = pose.T_mount_link[..., :3, :3]  # (..., 3, 3, 3)

    w = np.broadcast_to(np.asarray(omega_mount, float), batch + (3,))
    dw = np.broadcast_to(np.asarray(alpha_mount, float), batch + (3,))
    a_o = np.broadcast_to(np.asarray(accel_mount, float) - np.asarray(gravity_mount, float), batch + (3,))
    o_prev = np.zeros(batch + (3,))
    F, N, C = [], [], []
    for i in range(3):
        r = o[..., i, :] - o_prev
        # Acceleration of joint i's origin, carried rigidly by the previous link.
        a_o = a_o + np.cross(dw, r) + np.cross(w, np.cross(w, r))
        w_new = w + z[..., i, :] * qd[..., i, None]
        dw = dw + z[..., i, :] * qdd[..., i, None] + np.cross(w, z[..., i, :] * qd[..., i, None])
        w = w_new
        li = inertias[i]
        c = np.einsum("...ij,j->...i", R[..., i, :, :], li.com_m)      # COM offset from o_i, mount axes
        a_c = a_o + np.cross(dw, c) + np.cross(w, np.cross(w, c))
        I = R[..., i, :, :] @ li.inertia_com @ np.swapaxes(R[..., i, :, :], -1, -2)
        Iw = np.einsum("...ij,...j->...i", I, w)
        F.append(li.mass_kg * a_c)
        N.append(np.einsum("...ij,...j->...i", I, dw) + np.cross(w, Iw))
        C.append(c)
        o_prev = o[..., i, :]
    tau = np.empty(batch + (3,))
    f = np.zeros(batch + (3,))
    n = np.zeros(batch + (3,))
    for i in (2, 1, 0):
        # Moment about joint i's origin of everything outboard of it.
        r_next = (o[..., i + 1, :] - o[..., i, :]) if i < 2 else np.zeros(batch + (3,))
        n = N[i] + n + np.cross(C[i], F[i]) + np.cross(r_next, f)
        f = F[i] + f
        tau[..., i] = np.einsum("...i,...i->...", z[..., i, :], n)
    armature = np.array([head.servo_of(i).armature_kgm2 for i in range(3)])
    return tau + armature * qdd


def gravity_torque(head: HeadGeometry, q, gravity_mount=(0.0, 0.0, -GRAVITY)) -> np.ndarray:
    """Static holding torques (..., 3), N m, at joint angles q."""
    q = np.asarray(q, float)
    return inverse_dynamics(head, q, np.zeros_like(q), np.zeros_like(q), gravity_mount=gravity_mount)
