"""A head's kinematic summary: the chain, masses, radii, torques and gaze coverage, as data.

Used by ``wvr kinematics show`` and the demo's kinematics stage; every figure is computed from
the geometry by the same functions design and runtime use.
"""

from __future__ import annotations

import math

import numpy as np

from .chain import forward_kinematics, radii_of_rotation
from .dynamics import gravity_torque, link_inertias
from .gaze_ik import gaze_at_direction
from .geometry import JOINT_NAMES, HeadGeometry


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) nearly uniform unit vectors on the sphere (golden-angle spiral)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def gaze_coverage(head: HeadGeometry, n_directions: int = 2000, up=(0.0, 0.0, 1.0)) -> dict:
    """Fraction of the sphere of gaze directions the head can fixate upright, and why not elsewhere."""
    dirs = fibonacci_sphere(n_directions)
    blocked = {name: 0 for name in JOINT_NAMES}
    other = 0
    reachable = 0
    for d in dirs:
        r = gaze_at_direction(head, d, up)
        if r.reachable:
            reachable += 1
        elif r.blocking_joint:
            blocked[r.blocking_joint] += 1
        else:
            other += 1
    return {"directions": n_directions, "reachable_fraction": reachable / n_directions,
            "blocked_by": {k: v / n_directions for k, v in blocked.items()}, "unreachable_other": other / n_directions}


def worst_static_torque(head: HeadGeometry, steps: int = 9) -> np.ndarray:
    """(3,) largest holding torque over a grid of postures (mount upright), N m."""
    grids = np.meshgrid(*[np.linspace(lo, hi, steps) for lo, hi in zip(head.lower, head.upper)], indexing="ij")
    q = np.stack([g.ravel() for g in grids], -1)
    return np.abs(gravity_torque(head, q)).max(axis=0)


def summarize(head: HeadGeometry, n_directions: int = 2000) -> dict:
    """Everything a person checks about a head before building it, as a JSON-ready dict (SI units)."""
    pose0 = forward_kinematics(head, np.zeros(3))
    inertias = link_inertias(head)
    joints = []
    for i, j in enumerate(head.joints):
        s = head.servo_of(i)
        joints.append({
            "name": j.name, "origin_m": list(j.origin_m), "axis": list(j.axis),
            "range_deg": [math.degrees(j.range_rad[0]), math.degrees(j.range_rad[1])],
            "servo": s.name, "max_speed_rad_s": s.max_speed_rad_s, "stall_torque_nm": s.stall_torque_nm,
            "link_mass_kg": inertias[i].mass_kg,
        })
    tau_worst = worst_static_torque(head)
    return {
        "name": head.name,
        "joints": joints,
        "total_mass_kg": sum(p.mass_kg for p in head.parts),
        "camera_rest_position_m": pose0.p_mount_cam.tolist(),
        "camera_rest_optic_axis": pose0.optic_axis.tolist(),
        "radii_of_rotation_mm": dict(zip(JOINT_NAMES, (1000 * radii_of_rotation(head)).tolist())),
        "static_torque_rest_nm": dict(zip(JOINT_NAMES, gravity_torque(head, np.zeros(3)).tolist())),
        "static_torque_worst_nm": dict(zip(JOINT_NAMES, tau_worst.tolist())),
        "static_torque_worst_fraction_of_stall": dict(zip(JOINT_NAMES, (tau_worst / head.max_torque).tolist())),
        "gaze_coverage": gaze_coverage(head, n_directions),
    }


def summary_markdown(s: dict) -> str:
    """The summary as a Markdown page."""
    lines = [f"# Head `{s['name']}`", "", "Chain from collar to camera (paper, Fig. 2a):", "",
             "| joint | origin in parent (mm) | axis | range (deg) | servo | link mass (g) |",
             "|---|---|---|---|---|---|"]
    for j in s["joints"]:
        o = ", ".join(f"{1000 * v:.1f}" for v in j["origin_m"])
        a = ", ".join(f"{v:g}" for v in j["axis"])
        lines.append(f"| {j['name']} | {o} | {a} | {j['range_deg'][0]:.0f} to {j['range_deg'][1]:.0f} | "
                     f"{j['servo']} ({j['max_speed_rad_s']:g} rad/s, {j['stall_torque_nm']:g} Nm) | "
                     f"{1000 * j['link_mass_kg']:.1f} |")
    cov = s["gaze_coverage"]
    lines += [
        "", f"- Total mass of the parts: {1000 * s['total_mass_kg']:.1f} g",
        "- Camera at rest (mount frame, mm): " + ", ".join(f"{1000 * v:.1f}" for v in s["camera_rest_position_m"]),
        "- Radii of rotation of the sensor centre (mm): "
        + ", ".join(f"{k} {v:.1f}" for k, v in s["radii_of_rotation_mm"].items()),
        "- Holding torque at rest (N m): " + ", ".join(f"{k} {v:.4f}" for k, v in s["static_torque_rest_nm"].items()),
        "- Worst holding torque over the joint ranges (fraction of stall): "
        + ", ".join(f"{k} {v:.3f}" for k, v in s["static_torque_worst_fraction_of_stall"].items()),
        f"- Gaze directions fixated upright (of {cov['directions']} over the sphere, mount upright): "
        f"{100 * cov['reachable_fraction']:.1f}%; blocked by "
        + ", ".join(f"{k} {100 * v:.1f}%" for k, v in cov["blocked_by"].items()),
        "",
    ]
    return "\n".join(lines)
