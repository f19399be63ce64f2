"""ATE after each alignment against trajectories made from a known similarity of the truth."""

import numpy as np
from scipy.spatial.transform import Rotation

from runtime.eval import align_sim3, trajectory_errors
from runtime.sequence import Trajectory


def _walk(n=200, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    p = np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0)
    q = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0)).as_quat()
    return Trajectory(t, p, q)


def test_sim3_alignment_recovers_a_known_similarity():
    gt = _walk()
    R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    s_true, t_true = 2.5, np.array([1.0, -2.0, 0.5])
    # The estimate is the truth in another frame and unit: gt = s R est + t.
    p_est = (gt.p_world_cam - t_true) @ R / s_true
    est = Trajectory(gt.t, p_est, gt.q_xyzw)
    Ra, ta, sa = align_sim3(est.p_world_cam, gt.p_world_cam)
    np.testing.assert_allclose(Ra, R, atol=1e-9)
    np.testing.assert_allclose(ta, t_true, atol=1e-9)
    assert abs(sa - s_true) < 1e-9
    e = trajectory_errors(est, gt)
    assert e.ate_sim3_rmse_m < 1e-9 and abs(e.sim3_scale - s_true) < 1e-9
    # Without scale the best rigid fit leaves the walk's shape at the wrong size.
    assert e.ate_aligned_rmse_m > 0.01 and e.ate_rmse_m > e.ate_aligned_rmse_m
    assert e.ate("sim3") == (e.ate_sim3_rmse_m, e.ate_sim3_max_m)


def test_sim3_ate_of_a_noisy_estimate_is_its_noise():
    gt = _walk(seed=1)
    rng = np.random.default_rng(2)
    noise = rng.normal(0, 0.004, gt.p_world_cam.shape)
    est = Trajectory(gt.t, 0.5 * (gt.p_world_cam + noise), gt.q_xyzw)
    e = trajectory_errors(est, gt)
    rms_noise = np.sqrt(np.mean(np.sum(noise**2, axis=1)))
    assert abs(e.sim3_scale - 2.0) < 0.02
    assert 0.8 * rms_noise < e.ate_sim3_rmse_m < 1.05 * rms_noise
