"""Evaluating many designs at once: the layout as arrays, the criteria by compiled kernels.

:func:`evaluate_batch` is what a sweep calls: designs (n, 12) -> criteria (n, 7) and
constraints (n, 3), the same values as scoring each design's HeadGeometry with
:mod:`design.criteria` (volume to the voxel, the rest to rounding; tests/design/test_fast.py),
at a fraction of the cost: the layout rule is applied to all designs as array operations, what
does not depend on the layout (the workload's link rotations and rates, the posture grid's
angles) is computed once per sweep, and the voxel sweep, the collision grid and the dynamics
run as numba kernels (:mod:`design.kernels`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kinematics import SERVO_CATALOGUE, HeadGeometry
from kinematics.chain import forward_kinematics
from kinematics.geometry import JOINT_NAMES, LINK_NAMES

from . import kernels as K
from .layout import AXES, LENGTH_AXES, MOTOR_LINK
from .volume import LATTICE_OFFSET

#: Part order of every head the layout makes (layout.head_from_variables).
LAYOUT_PARTS = (("elevation_servo", "mount", "servo"), ("pan_servo", "elevation", "servo"),
                ("cyclotorsion_servo", "pan", "servo"), ("camera_body", "cyclotorsion", "camera"),
                ("elevation_bracket", "elevation", "bracket"), ("pan_bracket", "pan", "bracket"),
                ("cyclotorsion_bracket", "cyclotorsion", "bracket"))


@dataclass(frozen=True)
class HeadArrays:
    """n heads with the same axes, ranges, servos and part list, as arrays (SI units).

    link : (P,) link index of each part (LINK_NAMES). solid : (P,) not a bracket.
    center, size : (n, P, 3) part boxes in their link's frame. mass : (n, P).
    origin : (n, 3, 3) joint origins in the parent frames. cam : (n, 3) optical centre in the
    cyclotorsion link's frame. axis : (3, 3). lo, hi : (3,) joint ranges, radians.
    armature, max_torque : (3,) per joint.
    """

    link: np.ndarray
    solid: np.ndarray
    center: np.ndarray
    size: np.ndarray
    mass: np.ndarray
    origin: np.ndarray
    cam: np.ndarray
    axis: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    armature: np.ndarray
    max_torque: np.ndarray

    def __len__(self) -> int:
        return self.center.shape[0]

    def pairs(self, same_link: bool) -> np.ndarray:
        """(K, 2) non-bracket part pairs on different links (collision.collision_pairs) or on
        the same link (collision.same_link_overlap)."""
        solid = np.flatnonzero(self.solid)
        out = [(i, j) for a, i in enumerate(solid) for j in solid[a + 1:]
               if (self.link[i] == self.link[j]) == same_link]
        return np.array(out, np.int64).reshape(-1, 2)


def arrays_from_head(head: HeadGeometry) -> HeadArrays:
    """One HeadGeometry as HeadArrays (n = 1)."""
    P = len(head.parts)
    return HeadArrays(
        link=np.array([LINK_NAMES.index(p.link) for p in head.parts], np.int64),
        solid=np.array([p.kind != "bracket" for p in head.parts], bool),
        center=np.array([p.center_m for p in head.parts], float).reshape(1, P, 3),
        size=np.array([p.size_m for p in head.parts], float).reshape(1, P, 3),
        mass=np.array([p.mass_kg for p in head.parts], float).reshape(1, P),
        origin=np.asarray(head.origins, float)[None].copy(),
        cam=np.asarray(head.camera.T_link_cam[:3, 3], float)[None].copy(),
        axis=np.asarray(head.axes, float).copy(), lo=np.asarray(head.lower, float), hi=np.asarray(head.upper, float),
        armature=np.array([head.servo_of(i).armature_kgm2 for i in range(3)]),
        max_torque=np.asarray(head.max_torque, float))


def arrays_from_variables(X, spec) -> HeadArrays:
    """layout.head_from_variables for designs X (n, 12) at once, as HeadArrays (same arithmetic)."""
    X = np.atleast_2d(np.asarray(X, float))
    n = len(X)
    servo = SERVO_CATALOGUE[spec.servo]
    L, W, H = servo.size_m
    motors = {"elevation": X[:, 0:3], "pan": X[:, 3:6], "cyclotorsion": X[:, 6:9]}
    camera_c = X[:, 9:12]
    shafts, sizes = {}, {}
    for joint, centre in motors.items():
        a, l = np.asarray(AXES[joint]), np.asarray(LENGTH_AXES[joint])
        w = np.cross(a, l)
        shafts[joint] = centre + (L / 2 - W / 2) * l + (H / 2) * a
        sizes[joint] = np.abs(L * l) + np.abs(W * w) + np.abs(H * a)
    depth, width, height = spec.camera_size_m
    fwd = np.asarray(AXES["cyclotorsion"])
    cam_box = camera_c - fwd * depth / 2
    carried = {"elevation": motors["pan"], "pan": motors["cyclotorsion"], "cyclotorsion": cam_box}
    frame = {"mount": np.zeros((n, 3)), **shafts}
    centers, size, mass = [], [], []
    for joint in ("elevation", "pan", "cyclotorsion"):
        centers.append(motors[joint] - frame[MOTOR_LINK[joint]])
        size.append(np.broadcast_to(sizes[joint], (n, 3)))
        mass.append(np.full(n, servo.mass_kg))
    centers.append(cam_box - frame["cyclotorsion"])
    size.append(np.broadcast_to(np.array([depth, width, height]), (n, 3)))
    mass.append(np.full(n, spec.camera_mass_kg))
    for joint in ("elevation", "pan", "cyclotorsion"):
        d = carried[joint] - shafts[joint]
        length = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        mass.append(np.maximum(spec.bracket_density_kg_m * length, 1e-4))
        centers.append((shafts[joint] + carried[joint]) / 2 - frame[joint])
        size.append(np.full((n, 3), spec.bracket_size_m))
    prev = np.zeros((n, 3))
    origin = []
    for joint in ("elevation", "pan", "cyclotorsion"):
        origin.append(shafts[joint] - prev)
        prev = shafts[joint]
    half = math.radians(spec.range_deg) / 2
    return HeadArrays(
        link=np.array([LINK_NAMES.index(link) for _, link, _ in LAYOUT_PARTS], np.int64),
        solid=np.array([kind != "bracket" for _, _, kind in LAYOUT_PARTS], bool),
        center=np.ascontiguousarray(np.stack(centers, axis=1)), size=np.ascontiguousarray(np.stack(size, axis=1)),
        mass=np.stack(mass, axis=1), origin=np.ascontiguousarray(np.stack(origin, axis=1)),
        cam=camera_c - shafts["cyclotorsion"],
        axis=np.array([AXES[j] for j in JOINT_NAMES], float), lo=np.full(3, -half), hi=np.full(3, half),
        armature=np.full(3, servo.armature_kgm2), max_torque=np.full(3, servo.stall_torque_nm))


@dataclass(frozen=True)
class DynamicsPlan:
    """What the workload's dynamics share across designs with the same joint axes (see
    kernels.workload_torques): link rotations and rates over the T samples."""

    R: np.ndarray
    z: np.ndarray
    W: np.ndarray
    DW: np.ndarray
    wl: np.ndarray
    dwl: np.ndarray
    a_base: np.ndarray
    qdd: np.ndarray

    @classmethod
    def build(cls, workload, head: HeadGeometry) -> "DynamicsPlan":
        """As kinematics.dynamics.inverse_dynamics computes them (the rotations and rates do not
        depend on the joint origins)."""
        q = workload.q
        qd, qdd = workload.qd, workload.qdd
        pose = forward_kinematics(head, q)
        z = pose.axes_mount
        R = pose.T_mount_link[..., :3, :3]
        w = np.asarray(workload.omega_mount, float)
        dw = np.asarray(workload.alpha_mount, float)
        Ws, DWs = [w], [dw]
        for i in range(3):
            w_new = w + z[..., i, :] * qd[..., i, None]
            dw = dw + z[..., i, :] * qdd[..., i, None] + np.cross(w, z[..., i, :] * qd[..., i, None])
            w = w_new
            Ws.append(w)
            DWs.append(dw)
        W, DW = np.stack(Ws, axis=1), np.stack(DWs, axis=1)
        wl = np.einsum("tikj,tik->tij", R, W[:, 1:])   # R^T w: each link's rates in its own axes
        dwl = np.einsum("tikj,tik->tij", R, DW[:, 1:])
        a_base = np.asarray(workload.accel_mount, float) - np.asarray(workload.gravity_mount, float)
        c = np.ascontiguousarray
        return cls(R=c(R), z=c(z), W=c(W), DW=c(DW), wl=c(wl), dwl=c(dwl), a_base=c(np.broadcast_to(a_base, q.shape)),
                   qdd=c(qdd))


def link_inertias(arrays: HeadArrays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """kinematics.dynamics.link_inertias for every head: mass (n, 3), com (n, 3, 3) in the link
    frame, inertia about the com (n, 3, 3, 3), link axes."""
    n = len(arrays)
    mass = np.empty((n, 3))
    com = np.empty((n, 3, 3))
    inertia = np.zeros((n, 3, 3, 3))
    eye = np.eye(3)
    for k in range(3):
        on = np.flatnonzero(arrays.link == k + 1)
        m = sum(arrays.mass[:, p] for p in on)
        c = sum(arrays.mass[:, p, None] * arrays.center[:, p] for p in on) / m[:, None]
        for p in on:
            mp = arrays.mass[:, p]
            a, b, cc = arrays.size[:, p, 0], arrays.size[:, p, 1], arrays.size[:, p, 2]
            box = np.zeros((n, 3, 3))
            box[:, 0, 0], box[:, 1, 1], box[:, 2, 2] = mp * (b * b + cc * cc), mp * (a * a + cc * cc), mp * (a * a + b * b)
            r = arrays.center[:, p] - c
            rr = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1] + r[:, 2] * r[:, 2]
            inertia[:, k] += box / 12.0 + mp[:, None, None] * (rr[:, None, None] * eye - r[:, :, None] * r[:, None, :])
        mass[:, k], com[:, k] = m, c
    return mass, com, inertia


class Evaluator:
    """Scores HeadArrays with the sweep's settings; keeps the per-axes dynamics plans."""

    def __init__(self, spec, workload):
        self.spec = spec
        self.workload = workload
        self._plans: dict[bytes, DynamicsPlan] = {}

    def plan(self, arrays: HeadArrays, head: HeadGeometry | None) -> DynamicsPlan:
        key = arrays.axis.tobytes()
        if key not in self._plans:
            if head is None:
                from .layout import head_from_variables
                head = head_from_variables((self.spec.xl + self.spec.xu) / 2, self.spec)
            self._plans[key] = DynamicsPlan.build(self.workload, head)
        return self._plans[key]

    def __call__(self, arrays: HeadArrays, head: HeadGeometry | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(F (n, 7), G (n, 3)) in design.sweep_file.CRITERIA and CONSTRAINTS order."""
        s, w = self.spec, self.workload
        n = len(arrays)
        plan = self.plan(arrays, head)
        mass, com, inertia = link_inertias(arrays)
        cross_pairs, same_pairs = arrays.pairs(False), arrays.pairs(True)
        half = arrays.size / 2.0
        F = np.empty((n, 7))
        G = np.empty((n, 3))
        tau = np.empty((len(w.dt), 3))
        dt = np.ascontiguousarray(w.dt, float)
        energy, peak = np.empty(len(dt)), np.empty(3)
        voxel_m3 = s.voxel_m ** 3
        for d in range(n):
            c, sz = arrays.center[d], arrays.size[d]
            link_c = tuple(np.ascontiguousarray(c[arrays.link == k]) for k in range(4))
            link_s = tuple(np.ascontiguousarray(sz[arrays.link == k]) for k in range(4))
            voxels = K.swept_voxels(link_c, link_s, arrays.axis, arrays.origin[d], arrays.lo, arrays.hi, s.voxel_m,
                                    LATTICE_OFFSET)
            F[d, 0] = voxels * voxel_m3 * 1e6
            hits = K.collision_count(arrays.axis, arrays.origin[d], arrays.lo, arrays.hi, s.collision_steps,
                                     arrays.link, c, half[d], cross_pairs)
            F[d, 1] = float(np.float64(hits) / s.collision_steps ** 3)
            K.workload_torques(plan.R, plan.z, plan.W, plan.DW, plan.wl, plan.dwl, plan.a_base, plan.qdd,
                               arrays.origin[d], mass[d], com[d], inertia[d], arrays.armature, tau)
            K.torque_summary(tau, dt, energy, peak)
            F[d, 2] = float(np.sum(energy))
            F[d, 3] = float(peak.max())
            G[d, 0] = float((peak - arrays.max_torque).max())
            rest = K.rest_penetration_max(arrays.axis, arrays.origin[d], arrays.link, c, half[d], cross_pairs)
            same = K.rest_penetration_max(arrays.axis, arrays.origin[d], arrays.link, c, half[d], same_pairs)
            G[d, 1] = float(rest + s.clearance_m)
            G[d, 2] = float(max(same, -1.0) + s.clearance_m)
        F[:, 4:7] = radii_at_rest(arrays) * 1000
        return F, G


def radii_at_rest(arrays: HeadArrays) -> np.ndarray:
    """(n, 3) kinematics.chain.radii_of_rotation at q = 0, metres: every rotation is the identity
    there, so the joint origins add up and the axes are the joints' own."""
    p = np.zeros(arrays.origin.shape[:1] + (3,))
    origins = []
    for i in range(3):
        p = p + arrays.origin[:, i]
        origins.append(p)
    lever = (p + arrays.cam)[:, None, :] - np.stack(origins, axis=1)
    return np.linalg.norm(np.cross(arrays.axis[None], lever), axis=-1)
