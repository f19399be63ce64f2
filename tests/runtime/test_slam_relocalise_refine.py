"""The re-localised pose's refinement over every match (relocalise.refine_pose): its Jacobians
against central differences, and the pose it finds against a synthetic scene's truth: from a
minimal set's pose centimetres off, with points whose depths are uncertain and wrong peaks among
the matches, to the true pose within its own covariance."""

from __future__ import annotations

import numpy as np
import pytest
import slam_testing as st
from scipy.spatial.transform import Rotation

from kinematics.camera import project
from runtime.slam.relocalise import refine_pose
from runtime.slam.startup import pose_jacobians


@pytest.mark.parametrize("name", sorted(st.CAMERAS))
def test_pose_jacobians_match_central_differences(name):
    cam = st.CAMERAS[name]
    rng = np.random.default_rng(1)
    R_wc = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
    r = rng.normal(0, 0.2, 3)
    Y = r + (np.c_[rng.uniform(-0.4, 0.4, (12, 2)), rng.uniform(0.8, 2.5, 12)]) @ R_wc.T
    uv, J, J_y = pose_jacobians(cam, Y, R_wc, r)
    assert np.allclose(uv, project(cam, (Y - r) @ R_wc))
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        up = project(cam, (Y - r - d[3:]) @ (R_wc @ Rotation.from_rotvec(d[:3]).as_matrix()))
        dn = project(cam, (Y - r + d[3:]) @ (R_wc @ Rotation.from_rotvec(-d[:3]).as_matrix()))
        assert np.allclose(J[:, :, i], (up - dn) / (2 * eps), rtol=1e-4, atol=1e-3), (name, i)
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        num = (project(cam, (Y + d - r) @ R_wc) - project(cam, (Y - d - r) @ R_wc)) / (2 * eps)
        assert np.allclose(J_y[:, :, i], num, rtol=1e-4, atol=1e-3), (name, i)


def scene(rng, cam, n=36):
    """A camera looking at n points 1-3 m away, each mapped with an error drawn from its own
    covariance (most along the ray from where the map saw it: a depth a few per cent off), seen
    at its true pixel plus 0.5 px noise, with a wrong peak (a repeated texture) for a third of
    them. Returns the truth, the map's points and covariances, and the matches."""
    R_wc = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
    r = rng.normal(0, 0.1, 3)
    P_cam = np.c_[rng.uniform(-0.7, 0.7, (n, 2)), np.ones(n)] * rng.uniform(1.0, 3.0, (n, 1))
    Y_true = r + P_cam @ R_wc.T
    anchor = r + rng.normal(0, 0.1, 3)            # where the map saw them from
    cov = np.empty((n, 3, 3))
    for k in range(n):
        ray = (Y_true[k] - anchor) / np.linalg.norm(Y_true[k] - anchor)
        depth_sd = rng.uniform(0.002, 0.06) * np.linalg.norm(Y_true[k] - anchor)
        cov[k] = depth_sd**2 * np.outer(ray, ray) + 0.002**2 * np.eye(3)
    Y = Y_true + np.einsum("kij,kj->ki", np.linalg.cholesky(cov), rng.normal(size=(n, 3)))
    uv_true = project(cam, P_cam)
    uv = uv_true + rng.normal(0, 0.5, uv_true.shape)
    wrong = rng.choice(n, n // 3, replace=False)
    decoys = uv_true[wrong] + rng.uniform(15, 60, (len(wrong), 2)) * rng.choice([-1, 1], (len(wrong), 2))
    return (R_wc, r), Y, cov, np.r_[uv, decoys], np.r_[np.arange(n), wrong]


def unit(v):
    return v / np.linalg.norm(v)


def turned_to_fit(cam, Y, uv, R_wc, r):
    """The rotation, the camera held at r, that best fits pixels uv of points Y (Gauss-Newton)."""
    for _ in range(20):
        pred, J, _ = pose_jacobians(cam, Y, R_wc, r)
        J = J[:, :, :3].reshape(-1, 3)
        d = np.linalg.lstsq(J, (uv - pred).reshape(-1), rcond=None)[0]
        R_wc = R_wc @ Rotation.from_rotvec(d).as_matrix()
    return R_wc, r


def test_a_pose_centimetres_off_is_refined_to_the_truth_within_its_covariance():
    cam = st.PINHOLE
    rng = np.random.default_rng(7)
    nees, errors, start_errors = [], [], []
    for _ in range(40):
        (R_wc, r), Y, cov, uv, owner = scene(rng, cam)
        # A minimal set's pose: 8 cm off sideways and turned to fit 5 of the points (the
        # rotation-translation ambiguity a few points at similar depths leave).
        start = rng.choice(len(Y), 5, replace=False)
        R0, r0 = turned_to_fit(cam, Y[start], uv[start], R_wc, r + 0.08 * R_wc @ unit(np.r_[rng.normal(size=2), 0.0]))
        start_errors.append(np.degrees(np.linalg.norm(Rotation.from_matrix(R0.T @ R_wc).as_rotvec())))
        ref = refine_pose(cam, Y, cov, uv, owner, R0, r0, 0.5, start)
        assert ref is not None
        d = np.r_[Rotation.from_matrix(ref.R_world_cam.T @ R_wc).as_rotvec(), r - ref.r]
        nees.append(d @ np.linalg.solve(ref.cov, d))
        errors.append(np.linalg.norm(r - ref.r))
        # Every point kept its true match, not the wrong peak.
        n = len(Y)
        true_uv = uv[:n][ref.used]
        assert np.allclose(ref.uv, true_uv), "a wrong peak was chosen"
        assert len(ref.used) >= 0.9 * n
    assert np.median(start_errors) > 1.5             # degrees: the start is far from the truth
    # From 8 cm to millimetres, and as uncertain as its covariance says (6 dof: NEES mean 6).
    assert np.median(errors) < 0.005 and max(errors) < 0.02, errors
    assert 3.5 < np.mean(nees) < 9.0, np.mean(nees)


def test_too_few_points_give_no_pose():
    cam = st.PINHOLE
    (R_wc, r), Y, cov, uv, owner = scene(np.random.default_rng(3), cam, n=3)
    assert refine_pose(cam, Y, cov, uv, owner, R_wc, r, 0.5, np.arange(3)) is None
