"""HeadGeometry -> MJCF: the head as MuJoCo data, generated, never written by hand.

Bodies ``mount`` > ``elevation`` > ``pan`` > ``cyclotorsion`` mirror the chain exactly (same
origins, axes and ranges), so MuJoCo's kinematics of the model equal :mod:`kinematics.chain`.
Each link's inertia is the lumped inertia of its parts (:func:`kinematics.dynamics.link_inertias`),
written explicitly; the part boxes are geoms for looks and collision queries. Servos are
position actuators with the servo's force limit and the joint's range; encoders are joint
position sensors; an IMU site on the camera carries a gyro and an accelerometer; the camera
has the intrinsics of a camera.toml (MuJoCo renders the pinhole part only; lens distortion is
applied, if at all, by whoever renders).

MuJoCo cameras look along their -z axis with y up; the optical frame (x right, y down,
z forward) is that frame turned half a turn about x, which the builder applies.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from .camera import CameraIntrinsics, default_camera
from .dynamics import GRAVITY, link_inertias
from .geometry import HeadGeometry
from .transforms import quat_wxyz_from_matrix

#: Optical frame -> MuJoCo camera frame (x same, y and z flipped).
R_OPT_MJCAM = np.diag([1.0, -1.0, -1.0])
#: Position servo stiffness, N m/rad: the HS-50's 0.06 Nm is reached at ~1 degree of error, as a
#: hobby servo's proportional controller saturates within a degree or two.
SERVO_KP = 3.4
#: Nominal pixel pitch used to express the intrinsics as a physical sensor (only ratios matter).
PIXEL_PITCH_M = 1.0e-5


def fmt(v, digits: int | None = None) -> str:
    """Numbers as MJCF attributes take them: space separated, each the shortest repr that reads
    back exactly, or ``digits`` significant digits (large meshes, where exactness buys nothing).

    v : a number or an array of any shape (flattened in C order).
    """
    if digits is None:
        return " ".join(repr(float(x)) for x in np.ravel(v))
    return " ".join(f"{float(x):.{digits}g}" for x in np.ravel(v))


def _quat_wxyz(R: np.ndarray) -> str:
    return fmt(quat_wxyz_from_matrix(R))


def effective_joint_inertia(head: HeadGeometry) -> np.ndarray:
    """(3,) inertia about each joint axis at the zero posture (outboard links + armature), kg m^2.

    Used only to choose the servos' damping so the position loops are critically damped.
    """
    from .chain import forward_kinematics

    pose = forward_kinematics(head, np.zeros(3))
    inertias = link_inertias(head)
    out = np.zeros(3)
    for j in range(3):
        a, o = pose.axes_mount[j], pose.origins_mount[j]
        total = head.servo_of(j).armature_kgm2
        for k, li in enumerate(inertias):
            if k < j:
                continue
            R = pose.T_mount_link[k, :3, :3]
            com = pose.T_mount_link[k, :3, :3] @ li.com_m + pose.T_mount_link[k, :3, 3]
            r = (com - o) - a * ((com - o) @ a)
            total += a @ (R @ li.inertia_com @ R.T) @ a + li.mass_kg * (r @ r)
        out[j] = total
    return out


def head_body(head: HeadGeometry, camera: CameraIntrinsics | None = None, prefix: str = "",
              pos=(0.0, 0.0, 0.0), quat_wxyz=(1.0, 0.0, 0.0, 0.0), explicit_inertia: bool = True) -> ET.Element:
    """The ``mount`` body element (with the whole chain inside), for embedding in a larger scene.

    ``prefix`` is prepended to every name so several heads (or a wearer) can share a model.
    ``explicit_inertia=False`` lets MuJoCo compute inertias from the part geoms instead (tests
    use it as an independent check of :func:`link_inertias`).
    """
    camera = default_camera() if camera is None else camera
    n = lambda s: prefix + s  # noqa: E731
    mount = ET.Element("body", name=n("mount"), pos=fmt(pos), quat=fmt(quat_wxyz))
    for p in head.parts_on("mount"):
        _part_geom(mount, p, n)
    parent = mount
    inertias = link_inertias(head)
    for i, joint in enumerate(head.joints):
        body = ET.SubElement(parent, "body", name=n(joint.name), pos=fmt(joint.origin_m))
        li = inertias[i]
        if explicit_inertia:
            I = li.inertia_com
            ET.SubElement(body, "inertial", pos=fmt(li.com_m), mass=repr(li.mass_kg),
                          fullinertia=fmt([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]))
        servo = head.servo_of(i)
        ET.SubElement(body, "joint", name=n(joint.name), type="hinge", pos="0 0 0", axis=fmt(joint.axis),
                      range=fmt(joint.range_rad), limited="true", armature=repr(servo.armature_kgm2),
                      damping="0")
        for p in head.parts_on(joint.name):
            _part_geom(body, p, n, with_mass=not explicit_inertia)
        parent = body
    cam = head.camera
    R_link_mjcam = cam.R_link_cam @ R_OPT_MJCAM
    W, H = camera.width, camera.height
    # MuJoCo takes the principal point as (image centre - principal point) in pixels, both axes
    # (checked by rendering, tests/kinematics/test_mjcf.py); OpenCV's pixel-centre convention
    # puts the image centre at ((W-1)/2, (H-1)/2).
    ET.SubElement(parent, "camera", name=n("camera"), pos=fmt(cam.origin_m), quat=_quat_wxyz(R_link_mjcam),
                  resolution=f"{W} {H}", sensorsize=fmt([W * PIXEL_PITCH_M, H * PIXEL_PITCH_M]),
                  focalpixel=fmt([camera.fx, camera.fy]),
                  principalpixel=fmt([(W - 1) / 2.0 - camera.cx, (H - 1) / 2.0 - camera.cy]))
    ET.SubElement(parent, "site", name=n("imu"), pos=fmt(cam.origin_m), quat=_quat_wxyz(cam.R_link_cam),
                  size="0.002")
    return mount


def _part_geom(body: ET.Element, part, n, with_mass: bool = False) -> None:
    rgba = {"servo": "0.15 0.15 0.15 1", "camera": "0.2 0.3 0.8 1", "bracket": "0.7 0.7 0.7 1"}[part.kind]
    attrs = dict(name=n(part.name), type="box", size=fmt(np.asarray(part.size_m) / 2.0),
                 pos=fmt(part.center_m), rgba=rgba, contype="0", conaffinity="0", group="1")
    if with_mass:
        attrs["mass"] = repr(part.mass_kg)
    else:
        attrs["mass"] = "0"
    ET.SubElement(body, "geom", **attrs)


def head_actuators_and_sensors(head: HeadGeometry, root: ET.Element, prefix: str = "") -> None:
    """Append the servos (position actuators), encoders and IMU sensors for a head to ``root``."""
    n = lambda s: prefix + s  # noqa: E731
    act = root.find("actuator")
    if act is None:
        act = ET.SubElement(root, "actuator")
    sens = root.find("sensor")
    if sens is None:
        sens = ET.SubElement(root, "sensor")
    I_eff = effective_joint_inertia(head)
    for i, joint in enumerate(head.joints):
        servo = head.servo_of(i)
        kv = 2.0 * math.sqrt(SERVO_KP * I_eff[i])  # critical damping of the position loop
        ET.SubElement(act, "position", name=n(joint.name), joint=n(joint.name), kp=repr(SERVO_KP), kv=repr(kv),
                      ctrlrange=fmt(joint.range_rad), ctrllimited="true",
                      forcerange=fmt([-servo.stall_torque_nm, servo.stall_torque_nm]), forcelimited="true")
        ET.SubElement(sens, "jointpos", name=n(f"encoder_{joint.name}"), joint=n(joint.name))
    ET.SubElement(sens, "gyro", name=n("imu_gyro"), site=n("imu"))
    ET.SubElement(sens, "accelerometer", name=n("imu_accel"), site=n("imu"))


def build_mjcf(head: HeadGeometry, camera: CameraIntrinsics | None = None, *, timestep: float = 0.001,
               explicit_inertia: bool = True, mount_pos=(0.0, 0.0, 0.0), mount_quat_wxyz=(1.0, 0.0, 0.0, 0.0)) -> str:
    """A complete MJCF model (string) of the head on a fixed mount, ready for ``MjModel.from_xml_string``."""
    root = ET.Element("mujoco", model=f"wvr_head_{head.name}")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", timestep=repr(timestep), gravity=fmt([0, 0, -GRAVITY]), integrator="implicitfast")
    vis = ET.SubElement(root, "visual")
    ET.SubElement(vis, "global", offwidth="1280", offheight="960")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", pos="0 0 1", dir="0 0 -1", directional="true")
    world.append(head_body(head, camera, pos=mount_pos, quat_wxyz=mount_quat_wxyz, explicit_inertia=explicit_inertia))
    head_actuators_and_sensors(head, root)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"

