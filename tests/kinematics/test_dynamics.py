"""Inverse dynamics of the head's parts against MuJoCo's mj_inverse and analytic cases."""

import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics import forward_kinematics, gravity_torque, inverse_dynamics, link_inertias, reference_head
from kinematics.dynamics import GRAVITY
from kinematics.mjcf import build_mjcf, head_body


def _states(head, n, rng):
    span = head.upper - head.lower
    q = rng.uniform(head.lower + 0.05 * span, head.upper - 0.05 * span, (n, 3))  # off the limits
    return q, rng.normal(0, 5, (n, 3)), rng.normal(0, 200, (n, 3))


def test_matches_mj_inverse_on_a_tilted_fixed_mount():
    head = reference_head()
    R_world_mount = Rotation.from_euler("xyz", [0.3, -0.5, 0.2])
    x, y, z, w = R_world_mount.as_quat()
    model = mujoco.MjModel.from_xml_string(build_mjcf(head, mount_quat_wxyz=(w, x, y, z)))
    data = mujoco.MjData(model)
    g_mount = R_world_mount.inv().apply([0, 0, -GRAVITY])
    q, qd, qdd = _states(head, 200, np.random.default_rng(0))
    tau = inverse_dynamics(head, q, qd, qdd, gravity_mount=g_mount)
    for k in range(len(q)):
        data.qpos[:], data.qvel[:], data.qacc[:] = q[k], qd[k], qdd[k]
        mujoco.mj_inverse(model, data)
        np.testing.assert_allclose(tau[k], data.qfrc_inverse, atol=1e-9)


def test_matches_mj_inverse_on_a_moving_mount():
    """The wearer's motion: the mount rides a free body with velocity and acceleration."""
    head = reference_head()
    root = ET.Element("mujoco")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", gravity=f"0 0 {-GRAVITY}")
    base = ET.SubElement(ET.SubElement(root, "worldbody"), "body", name="wearer")
    ET.SubElement(base, "freejoint")
    ET.SubElement(base, "inertial", pos="0 0 0", mass="1", diaginertia="0.01 0.01 0.01")
    base.append(head_body(head, pos=(0.05, -0.02, 0.1), quat_wxyz=(0.9, 0.1, -0.2, 0.3)))
    model = mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(1)
    q, qd, qdd = _states(head, 100, rng)
    for k in range(len(q)):
        quat = rng.normal(size=4); quat /= np.linalg.norm(quat)
        data.qpos[:7] = np.r_[rng.normal(size=3), quat]
        data.qpos[7:] = q[k]
        data.qvel[:6] = rng.normal(0, 2, 6)
        data.qvel[6:] = qd[k]
        data.qacc[:6] = rng.normal(0, 20, 6)
        data.qacc[6:] = qdd[k]
        mujoco.mj_inverse(model, data)
        # Free joint: linear velocity/acceleration of the body origin in the world frame,
        # angular ones in the body frame. Express everything in the mount frame.
        R_world_base = Rotation.from_quat(data.qpos[[4, 5, 6, 3]])
        R_base_mount = Rotation.from_quat(model.body_quat[2][[1, 2, 3, 0]])
        p_base_mount = model.body_pos[2]
        w_b, dw_b = data.qvel[3:6], data.qacc[3:6]
        a_base = R_world_base.inv().apply(data.qacc[:3])
        a_mount_b = a_base + np.cross(dw_b, p_base_mount) + np.cross(w_b, np.cross(w_b, p_base_mount))
        R_world_mount = R_world_base * R_base_mount
        tau = inverse_dynamics(
            head, q[k], qd[k], qdd[k],
            gravity_mount=R_world_mount.inv().apply([0, 0, -GRAVITY]),
            omega_mount=R_base_mount.inv().apply(w_b), alpha_mount=R_base_mount.inv().apply(dw_b),
            accel_mount=R_base_mount.inv().apply(a_mount_b))
        np.testing.assert_allclose(tau, data.qfrc_inverse[6:], atol=1e-9)


def test_static_torque_is_m_g_r():
    """Each outboard part is a point mass m at horizontal lever r from the elevation axis: tau = sum m g r."""
    head = reference_head()
    pose = forward_kinematics(head, np.zeros(3))
    expected = 0.0
    for i, link in enumerate(("elevation", "pan", "cyclotorsion")):
        T = pose.T_mount_link[i]
        for p in head.parts_on(link):
            c = T[:3, :3] @ p.center_m + T[:3, 3]
            # Elevation axis is -y through (0, 0, 0.02): lever arm is the forward (x) offset.
            expected += p.mass_kg * GRAVITY * c[0]
    assert gravity_torque(head, np.zeros(3))[0] == pytest.approx(expected, abs=1e-15)
    # Pan and cyclotorsion axes are vertical/horizontal-through-the-masses at rest.
    assert gravity_torque(head, np.zeros(3))[1] == pytest.approx(0.0, abs=1e-15)


def test_link_inertias_match_mujoco_from_geoms():
    """MuJoCo's own inertia from the part boxes equals our lumped inertias."""
    head = reference_head()
    model = mujoco.MjModel.from_xml_string(build_mjcf(head, explicit_inertia=False))
    for i, li in enumerate(link_inertias(head)):
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, head.joints[i].name)
        assert model.body_mass[b] == pytest.approx(li.mass_kg, rel=1e-12)
        np.testing.assert_allclose(model.body_ipos[b], li.com_m, atol=1e-12)
        R = Rotation.from_quat(model.body_iquat[b][[1, 2, 3, 0]]).as_matrix()
        np.testing.assert_allclose(R @ np.diag(model.body_inertia[b]) @ R.T, li.inertia_com, atol=1e-12)


def test_batched_equals_single():
    head = reference_head()
    q, qd, qdd = _states(head, 10, np.random.default_rng(2))
    batched = inverse_dynamics(head, q, qd, qdd)
    for k in range(10):
        np.testing.assert_allclose(batched[k], inverse_dynamics(head, q[k], qd[k], qdd[k]), atol=1e-15)
