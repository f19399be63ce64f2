"""From the sweep's variables (positions of camera and motors) to a HeadGeometry.

The chain order and axis directions are fixed, as in the paper: elevation about the mount's
lateral axis, then pan about the (elevated) vertical, then cyclotorsion along the optic axis,
which points forward at rest. What varies is where things are: the centres of the three servo
bodies and the camera's optical centre, in the mount frame at rest (x forward, y left, z up).

Each servo's shaft position follows from its body centre by the servo's layout (shaft along
the body's height, centred across its width, half a width from one end of its length,
protruding from the face on the +axis side). The joint origins are those shaft points; the
links they imply are brackets from each shaft to what it carries, whose mass grows with their
length (``[bracket]`` in sweep.toml).
"""

from __future__ import annotations

import math

import numpy as np

from kinematics import CameraMount, HeadGeometry, Joint, Part, SERVO_CATALOGUE

from .sweep_file import SweepSpec, VARIABLES

#: Joint axes in the mount frame at rest (all link frames are parallel to the mount at rest).
AXES = {"elevation": (0.0, -1.0, 0.0), "pan": (0.0, 0.0, 1.0), "cyclotorsion": (1.0, 0.0, 0.0)}
#: Direction of each servo body's length (perpendicular to its shaft), mount frame at rest.
LENGTH_AXES = {"elevation": (0.0, 0.0, 1.0), "pan": (1.0, 0.0, 0.0), "cyclotorsion": (0.0, 0.0, 1.0)}
#: The camera's optical x (right) in the mount frame at rest; forward is the cyclotorsion axis.
CAMERA_RIGHT = (0.0, -1.0, 0.0)
def _t(v) -> tuple[float, ...]:
    return tuple(float(c) for c in v)


MOTOR_LINK = {"elevation": "mount", "pan": "elevation", "cyclotorsion": "pan"}


def servo_box(joint: str, centre: np.ndarray, servo) -> tuple[np.ndarray, np.ndarray]:
    """(shaft point (3,), box size along mount x, y, z (3,)) of a servo body centred at ``centre``."""
    L, W, H = servo.size_m
    a = np.asarray(AXES[joint])
    l = np.asarray(LENGTH_AXES[joint])
    w = np.cross(a, l)
    shaft = centre + (L / 2 - W / 2) * l + (H / 2) * a
    size = np.abs(L * l) + np.abs(W * w) + np.abs(H * a)
    return shaft, size


def head_from_variables(x, spec: SweepSpec, name: str = "candidate") -> HeadGeometry:
    """The HeadGeometry of one design. ``x`` is (12,): the four positions in ``VARIABLES`` order, metres."""
    x = np.asarray(x, float)
    if x.shape != (len(VARIABLES),):
        raise ValueError(f"a design has {len(VARIABLES)} variables ({', '.join(VARIABLES)}), got shape {x.shape}")
    servo = SERVO_CATALOGUE[spec.servo]
    motors = {"elevation": x[0:3], "pan": x[3:6], "cyclotorsion": x[6:9]}
    camera_c = x[9:12]
    half = math.radians(spec.range_deg) / 2
    shafts, parts = {}, []
    for joint, centre in motors.items():
        shaft, size = servo_box(joint, centre, servo)
        shafts[joint] = shaft
        parts.append((f"{joint}_servo", MOTOR_LINK[joint], centre, size, servo.mass_kg, "servo"))
    depth, width, height = spec.camera_size_m
    fwd = np.asarray(AXES["cyclotorsion"])
    cam_box_centre = camera_c - fwd * depth / 2   # the optical centre is on the box's front face
    parts.append(("camera_body", "cyclotorsion", cam_box_centre, np.array([depth, width, height]),
                  spec.camera_mass_kg, "camera"))
    # Links: from each shaft to the body it drives (the next servo, or the camera).
    carried = {"elevation": motors["pan"], "pan": motors["cyclotorsion"], "cyclotorsion": cam_box_centre}
    for joint, target in carried.items():
        length = float(np.linalg.norm(target - shafts[joint]))
        mass = max(spec.bracket_density_kg_m * length, 1e-4)  # a horn at least, never massless
        parts.append((f"{joint}_bracket", joint, (shafts[joint] + target) / 2, np.full(3, spec.bracket_size_m),
                      mass, "bracket"))
    # Express every part in its own link's frame: link frames sit at their shafts at rest.
    frame_origin = {"mount": np.zeros(3), **shafts}
    parts = tuple(Part(name=n, link=link, center_m=_t(c - frame_origin[link]), size_m=_t(s), mass_kg=float(m), kind=k)
                  for n, link, c, s, m, k in parts)
    prev = np.zeros(3)
    joints = []
    for joint in ("elevation", "pan", "cyclotorsion"):
        joints.append(Joint(name=joint, origin_m=_t(shafts[joint] - prev), axis=AXES[joint],
                            range_rad=(-half, half), servo=spec.servo))
        prev = shafts[joint]
    camera = CameraMount(origin_m=_t(camera_c - shafts["cyclotorsion"]), forward=AXES["cyclotorsion"],
                         right=CAMERA_RIGHT)
    return HeadGeometry(name=name, joints=tuple(joints), camera=camera, parts=parts).validate()


def variables_from_head(head: HeadGeometry, spec: SweepSpec) -> np.ndarray:
    """Inverse of :func:`head_from_variables` for heads it made: the (12,) positions, metres."""
    from kinematics import forward_kinematics

    pose = forward_kinematics(head, np.zeros(3))
    T = {"mount": np.eye(4), "elevation": pose.T_mount_link[0], "pan": pose.T_mount_link[1],
         "cyclotorsion": pose.T_mount_link[2]}
    out = []
    for joint in ("elevation", "pan", "cyclotorsion"):
        p = next(p for p in head.parts if p.name == f"{joint}_servo")
        out.append(T[p.link][:3, :3] @ p.center_m + T[p.link][:3, 3])
    out.append(pose.p_mount_cam)
    return np.concatenate(out)
