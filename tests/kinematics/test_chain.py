"""Forward kinematics and Jacobians against MuJoCo's own kinematics and finite differences."""

import mujoco
import numpy as np
import pytest

from kinematics import angular_jacobian, forward_kinematics, optical_centre_jacobian, point_jacobian, reference_head
from kinematics.mjcf import R_OPT_MJCAM, build_mjcf
from kinematics.chain import axis_angle_matrix
from scipy.spatial.transform import Rotation


def random_q(head, n, rng):
    return rng.uniform(head.lower, head.upper, size=(n, 3))


def skewed_head():
    """A head with oblique axes and offsets everywhere, so no term of FK can hide."""
    h = reference_head()
    from dataclasses import replace
    rng = np.random.default_rng(7)
    joints = []
    for j in h.joints:
        a = np.asarray(j.axis) + rng.normal(0, 0.3, 3)
        joints.append(replace(j, axis=tuple(a / np.linalg.norm(a)),
                              origin_m=tuple(np.asarray(j.origin_m) + rng.normal(0, 0.01, 3))))
    fwd = np.asarray(joints[2].axis)
    right = np.cross(fwd, [0.0, 0.0, 1.0]); right /= np.linalg.norm(right)
    cam = replace(h.camera, forward=tuple(fwd), right=tuple(right), origin_m=(0.02, 0.004, -0.003))
    return replace(h, joints=tuple(joints), camera=cam).validate()


@pytest.mark.parametrize("make_head", [reference_head, skewed_head])
def test_fk_matches_mujoco_1000_random(make_head):
    head = make_head()
    model = mujoco.MjModel.from_xml_string(build_mjcf(head))
    data = mujoco.MjData(model)
    qs = random_q(head, 1000, np.random.default_rng(0))
    pose = forward_kinematics(head, qs)  # batched
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "camera")
    body_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in ("elevation", "pan", "cyclotorsion")]
    err_p = err_R = 0.0
    for k, q in enumerate(qs):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)  # camera poses are not part of mj_kinematics
        for i, b in enumerate(body_ids):
            err_p = max(err_p, np.abs(data.xpos[b] - pose.T_mount_link[k, i, :3, 3]).max())
            err_R = max(err_R, np.abs(data.xmat[b].reshape(3, 3) - pose.T_mount_link[k, i, :3, :3]).max())
        R_cam = data.cam_xmat[cam_id].reshape(3, 3) @ R_OPT_MJCAM
        err_p = max(err_p, np.abs(data.cam_xpos[cam_id] - pose.p_mount_cam[k]).max())
        err_R = max(err_R, np.abs(R_cam - pose.R_mount_cam[k]).max())
    assert err_p < 1e-9
    assert err_R < 1e-9


def test_fk_batched_equals_single():
    head = reference_head()
    qs = random_q(head, 20, np.random.default_rng(1)).reshape(4, 5, 3)
    batched = forward_kinematics(head, qs).T_mount_cam
    for idx in np.ndindex(4, 5):
        np.testing.assert_allclose(batched[idx], forward_kinematics(head, qs[idx]).T_mount_cam, atol=1e-15)


def test_optical_frame_of_reference_head_at_rest():
    pose = forward_kinematics(reference_head(), np.zeros(3))
    # Mount frame x forward, y left, z up; optical x right, y down, z forward.
    np.testing.assert_allclose(pose.R_mount_cam, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-15)


def test_rodrigues_matches_scipy():
    rng = np.random.default_rng(2)
    a = rng.normal(size=3); a /= np.linalg.norm(a)
    t = rng.uniform(-3, 3, 50)
    np.testing.assert_allclose(axis_angle_matrix(a, t), Rotation.from_rotvec(t[:, None] * a).as_matrix(), atol=1e-14)


def _log_so3(R):
    return Rotation.from_matrix(R).as_rotvec()


@pytest.mark.parametrize("make_head", [reference_head, skewed_head])
def test_jacobians_against_finite_differences(make_head):
    head = make_head()
    rng = np.random.default_rng(3)
    h = 1e-6
    for q in random_q(head, 25, rng):
        pose = forward_kinematics(head, q)
        Jw, Jv = angular_jacobian(head, q), optical_centre_jacobian(head, q)
        for i in range(3):
            dq = np.zeros(3); dq[i] = h
            p_plus, p_minus = forward_kinematics(head, q + dq), forward_kinematics(head, q - dq)
            v_fd = (p_plus.p_mount_cam - p_minus.p_mount_cam) / (2 * h)
            # Angular velocity in the mount frame: log(R(q+h) R(q-h)^T) / 2h.
            w_fd = _log_so3(p_plus.R_mount_cam @ p_minus.R_mount_cam.T) / (2 * h)
            np.testing.assert_allclose(Jv[:, i], v_fd, atol=1e-9)
            np.testing.assert_allclose(Jw[:, i], w_fd, atol=1e-9)
        # A point on the pan link: the cyclotorsion column must vanish.
        pt = np.array([0.01, -0.02, 0.005])
        Jp = point_jacobian(head, q, pt, link=1, pose=pose)
        for i in range(3):
            dq = np.zeros(3); dq[i] = h
            Tp = forward_kinematics(head, q + dq).T_mount_link[1]
            Tm = forward_kinematics(head, q - dq).T_mount_link[1]
            fd = (Tp[:3, :3] @ pt + Tp[:3, 3] - Tm[:3, :3] @ pt - Tm[:3, 3]) / (2 * h)
            np.testing.assert_allclose(Jp[:, i], fd, atol=1e-9)
        assert np.all(Jp[:, 2] == 0)


def test_fk_rejects_wrong_shape():
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        forward_kinematics(reference_head(), np.zeros(2))
