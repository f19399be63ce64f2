"""The MJCF built from a HeadGeometry: limits, sensors, and the camera's intrinsics by rendering."""

import dataclasses
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from scipy import ndimage

from kinematics import forward_kinematics, reference_head
from kinematics.camera import default_camera, project
from kinematics.mjcf import build_mjcf


def test_actuators_and_sensors_honour_the_servo():
    head = reference_head()
    model = mujoco.MjModel.from_xml_string(build_mjcf(head))
    assert model.nu == 3 and model.njnt == 3
    for i, j in enumerate(head.joints):
        np.testing.assert_allclose(model.jnt_range[i], j.range_rad)
        np.testing.assert_allclose(model.actuator_ctrlrange[i], j.range_rad)
        np.testing.assert_allclose(model.actuator_forcerange[i], [-0.06, 0.06])
        assert model.dof_armature[i] == head.servo_of(i).armature_kgm2
    names = {model.sensor(k).name for k in range(model.nsensor)}
    assert {"encoder_elevation", "encoder_pan", "encoder_cyclotorsion", "imu_gyro", "imu_accel"} <= names


def test_servo_tracks_a_step_and_imu_reads_gravity_at_rest():
    head = reference_head()
    model = mujoco.MjModel.from_xml_string(build_mjcf(head))
    data = mujoco.MjData(model)
    data.ctrl[:] = [0.2, -0.1, 0.05]
    mujoco.mj_step(model, data, nstep=1000)
    np.testing.assert_allclose(data.qpos, data.ctrl, atol=2e-3)   # settles within 1 s
    np.testing.assert_allclose(data.qvel, 0, atol=1e-3)
    acc = data.sensor("imu_accel").data
    # At rest the accelerometer reads the reaction to gravity: 9.81 m/s^2 pointing up.
    R = forward_kinematics(head, data.qpos).R_mount_cam
    np.testing.assert_allclose(R @ acc, [0, 0, 9.81], atol=0.05)


@pytest.mark.parametrize("cx,cy,fx,fy", [(319.5, 239.5, 514.7, 514.7), (300.0, 260.0, 500.0, 510.0)])
def test_rendered_camera_matches_the_intrinsics(cx, cy, fx, fy):
    """Small glowing spheres at known points land where the pinhole model says (to 0.25 px)."""
    head = reference_head()
    cam = dataclasses.replace(default_camera(), cx=cx, cy=cy, fx=fx, fy=fy)
    root = ET.fromstring(build_mjcf(head, cam))
    ET.SubElement(ET.SubElement(root, "asset"), "material", name="glow", emission="1", rgba="1 1 1 1")
    world = root.find("worldbody")
    q = np.array([0.2, -0.3, 0.1])
    pose = forward_kinematics(head, q)
    R, c = pose.R_mount_cam, pose.p_mount_cam
    P_cam = np.array([[0.12, 0.08, 0.7], [-0.15, -0.05, 0.6], [0.0, 0.0, 0.5], [0.2, -0.12, 0.9]])
    for P in P_cam:
        ET.SubElement(world, "geom", type="sphere", size="0.002", pos=" ".join(map(str, R @ P + c)),
                      material="glow", contype="0", conaffinity="0")
    model = mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, cam.height, cam.width) as r:
        r.update_scene(data, camera="camera")
        img = r.render().astype(float).sum(-1)
    lab, n = ndimage.label(img > 100)
    assert n == len(P_cam)
    found = np.array([(c[1], c[0]) for c in ndimage.center_of_mass(img, lab, range(1, n + 1))])
    expected = project(cam, P_cam)
    for e in expected:
        assert np.min(np.linalg.norm(found - e, axis=1)) < 0.25
