"""The seven design criteria of the paper (section 2), each a small pure function of a head.

All are minimised. Names match the output columns exactly (:data:`design.sweep_file.CRITERIA`).

1. ``working_volume_cm3``   volume swept by all parts over the joint ranges, cm^3.
2. ``self_collision``       fraction of a grid over joint space in which parts intersect.
3. ``integrated_torque``    integral over the workload of the summed squared joint torques,
                            N^2 m^2 s. Squared torque, because a DC motor's torque is
                            proportional to its current and its losses to current squared, so
                            this is proportional to the electrical energy the servos dissipate:
                            the paper's "integrated torque or energy consumption".
4. ``max_torque_nm``        peak |joint torque| over the workload, N m.
5-7. ``radius_elevation_mm``, ``radius_pan_mm``, ``radius_cyclotorsion_mm``: distance of the
                            image sensor's centre from each joint axis at rest, mm.
"""

from __future__ import annotations

import numpy as np

from kinematics import HeadGeometry, inverse_dynamics
from kinematics.chain import radii_of_rotation

from .collision import rest_penetration, same_link_overlap, self_collision_fraction
from .volume import swept_volume_m3
from .workload import Workload


def working_volume_cm3(head: HeadGeometry, voxel_m: float = 0.003) -> float:
    """Volume swept by all parts over the joint ranges, cm^3 (voxel sweep, see design.volume)."""
    return swept_volume_m3(head, voxel_m=voxel_m) * 1e6


def self_collision(head: HeadGeometry, steps: int = 9) -> float:
    """Fraction (0..1) of a steps^3 grid over the joint ranges in which any two parts on
    different links intersect; collisions that cut the angular range count."""
    return self_collision_fraction(head, steps=steps)


def workload_torques(head: HeadGeometry, workload: Workload) -> np.ndarray:
    """(N, 3) joint torques over the workload, N m (rigid-body dynamics of the parts + armature)."""
    return inverse_dynamics(head, workload.q, workload.qd, workload.qdd, gravity_mount=workload.gravity_mount,
                            omega_mount=workload.omega_mount, alpha_mount=workload.alpha_mount,
                            accel_mount=workload.accel_mount)


def integrated_torque(head: HeadGeometry, workload: Workload, tau: np.ndarray | None = None) -> float:
    """Integral over the workload of sum_i tau_i^2, N^2 m^2 s (proportional to winding losses)."""
    tau = workload_torques(head, workload) if tau is None else tau
    return float(np.sum((tau**2).sum(axis=1) * workload.dt))


def max_torque_nm(head: HeadGeometry, workload: Workload, tau: np.ndarray | None = None) -> float:
    """Peak |joint torque| over the workload and all joints, N m."""
    tau = workload_torques(head, workload) if tau is None else tau
    return float(np.abs(tau).max())


def radius_elevation_mm(head: HeadGeometry) -> float:
    """Distance of the optical centre from the elevation axis at rest, mm."""
    return float(radii_of_rotation(head)[0] * 1000)


def radius_pan_mm(head: HeadGeometry) -> float:
    """Distance of the optical centre from the pan axis at rest, mm."""
    return float(radii_of_rotation(head)[1] * 1000)


def radius_cyclotorsion_mm(head: HeadGeometry) -> float:
    """Distance of the optical centre from the cyclotorsion axis, mm (0 when on the optic axis)."""
    return float(radii_of_rotation(head)[2] * 1000)


def torque_excess_nm(head: HeadGeometry, workload: Workload, tau: np.ndarray | None = None) -> float:
    """Constraint: largest peak torque minus that joint's servo stall torque, N m (<= 0 feasible)."""
    tau = workload_torques(head, workload) if tau is None else tau
    return float((np.abs(tau).max(axis=0) - head.max_torque).max())


def rest_penetration_m(head: HeadGeometry, clearance_m: float = 0.0) -> float:
    """Constraint: deepest overlap of parts on different links at rest plus the clearance, m (<= 0)."""
    return float(rest_penetration(head) + clearance_m)


def part_overlap_m(head: HeadGeometry, clearance_m: float = 0.0) -> float:
    """Constraint: deepest overlap of parts on the same link plus the clearance, m (<= 0)."""
    return float(max(same_link_overlap(head), -1.0) + clearance_m)
