"""Inertial prediction (inertial.py): Jacobians against finite differences, the split of a frame
into IMU intervals, and integration against an analytic trajectory."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import test_slam_core as core
from runtime.slam.inertial import GRAVITY, imu_intervals, imu_step_and_jacobians, predict_imu
from runtime.slam.state import Q_SLICE, R_SLICE, V_SLICE, W_SLICE, State, quat_to_rotation


@pytest.mark.parametrize("d", [0.0, 0.005, 0.03])
def test_imu_step_jacobians(d):
    rng = np.random.default_rng(11)
    for _ in range(3):
        x_v = core.random_camera(rng, 1.0)
        x_v[Q_SLICE] *= 1.1           # defined on R^4, like the motion model's
        omega, f = rng.normal(0, 1.0, 3), rng.normal(0, 5.0, 3)
        x_new, F, G = imu_step_and_jacobians(x_v, omega, f, d)
        core.assert_jacobian(F, core.fd_jacobian(lambda a: imu_step_and_jacobians(a, omega, f, d)[0], x_v))
        u = np.r_[f, omega]
        core.assert_jacobian(G, core.fd_jacobian(lambda b: imu_step_and_jacobians(x_v, b[3:], b[:3], d)[0], u))


def test_intervals_cover_the_frame_with_the_sample_holding_over_each():
    imu = np.array([[0.0, *[1, 0, 0], *[0, 0, 1]], [0.005, *[2, 0, 0], *[0, 0, 2]], [0.010, *[3, 0, 0], *[0, 0, 3]],
                    [0.015, *[4, 0, 0], *[0, 0, 4]]])
    steps = imu_intervals(imu, 0.003, 0.012)
    assert [round(d, 9) for d, _, _ in steps] == [0.002, 0.005, 0.002]
    assert [w[0] for _, w, _ in steps] == [1, 2, 3]
    with pytest.raises(ValueError, match="no IMU sample"):
        imu_intervals(imu[1:], 0.003, 0.012)


def test_prediction_follows_an_analytic_trajectory():
    # Constant world acceleration and constant body rate: exact IMU samples, fine steps.
    a_world = np.array([0.3, -0.2, 0.1])
    w_cam = np.array([0.2, -0.4, 0.3])
    R0 = Rotation.from_euler("xyz", [-100, 10, 40], degrees=True)
    r0, v0 = np.array([0.1, 0.2, 1.4]), np.array([0.3, 0.0, -0.1])
    t = np.arange(0.0, 0.5001, 0.001)
    Rt = [R0 * Rotation.from_rotvec(w_cam * ti) for ti in t]
    # Samples at each instant: the integrator holds R(q) f, the world acceleration, exactly.
    imu = np.array([[ti, *w_cam, *(Ri.as_matrix().T @ (a_world - GRAVITY))] for ti, Ri in zip(t, Rt)])
    x_v = np.r_[r0, R0.as_quat()[[3, 0, 1, 2]], v0, w_cam]
    s = State.from_camera(x_v, np.eye(13) * 1e-6)
    predict_imu(s, imu, 0.0, 0.5)
    T = 0.5
    np.testing.assert_allclose(s.x[R_SLICE], r0 + v0 * T + 0.5 * a_world * T * T, atol=1e-6)
    np.testing.assert_allclose(s.x[V_SLICE], v0 + a_world * T, atol=1e-6)
    np.testing.assert_allclose(quat_to_rotation(s.x[Q_SLICE]), Rt[-1].as_matrix(), atol=1e-9)
    np.testing.assert_allclose(s.x[W_SLICE], w_cam)
    # Uncertainty grows with the integration, and the covariance stays symmetric.
    assert s.P[0, 0] > 1e-6 and np.allclose(s.P, s.P.T)
