"""Inertial prediction (inertial.py): the IMU step's Jacobians against central differences with
the bias columns (camera block of 19), the split of a frame into IMU intervals, integration
against an analytic trajectory, the covariance against the dense product of the intervals, the
bias states converging to an IMU's known constant biases in a simulation with camera updates,
and ImuStream's checks of the rows (NaN, spikes, out of order, gaps)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import slam_testing as st
from kinematics.camera import in_image
from runtime.slam.config import MapSettings, SlamConfig
from runtime.slam.features import POINT
from runtime.slam.filter import update
from runtime.slam.inertial import ImuStream, imu_intervals, imu_step_and_jacobians, predict_imu
from runtime.slam.motion import bias_walk
from runtime.slam.quaternion import normalise_quaternion_jacobian, quat_to_rotation
from runtime.slam.state import (
    BA_SLICE,
    BG_SLICE,
    G_SLICE,
    CAMERA_DIM,
    CAMERA_DIM_BIASED,
    CAMERA_DIM_SCALED,
    CAMERA_DIM_TIMED,
    Q_SLICE,
    R_SLICE,
    SCALE_INDEX,
    TD_INDEX,
    V_SLICE,
    W_SLICE,
    State,
)

#: The world's gravity, z up, as the twin's physics has it (MuJoCo's gravity option in
#: runtime/twin/scene.py), written out here so that the tests do not take it from the module they
#: check: a flipped or mis-scaled constant there must fail them.
G_WORLD = np.array([0.0, 0.0, -9.81])

CFG = SlamConfig()


# -- the step and its Jacobians ----------------------------------------------------------------

@pytest.mark.parametrize("cam_dim", [CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_TIMED, CAMERA_DIM_SCALED])
@pytest.mark.parametrize("d", [0.0, 0.005, 0.03])
def test_imu_step_jacobians(d, cam_dim):
    rng = np.random.default_rng(11)
    for _ in range(3):
        x_v = st.random_camera(rng, 1.0, cam_dim)
        x_v[Q_SLICE] *= 1.1           # defined on R^4, like the motion model's
        g = Rotation.random(random_state=rng.integers(1 << 30)).apply(G_WORLD)   # a natural start's map frame
        if cam_dim == CAMERA_DIM_SCALED:
            x_v[SCALE_INDEX] = rng.uniform(0.5, 3.0)
            x_v[G_SLICE] = g                   # its own gravity state: the argument is then not read
            assert np.array_equal(imu_step_and_jacobians(x_v, np.ones(3), np.ones(3), d, -g)[0],
                                  imu_step_and_jacobians(x_v, np.ones(3), np.ones(3), d, g)[0])
        omega, f = rng.normal(0, 1.0, 3), rng.normal(0, 5.0, 3)
        x_new, F, G = imu_step_and_jacobians(x_v, omega, f, d, g)
        assert F.shape == (cam_dim, cam_dim) and G.shape == (cam_dim, 6)
        st.assert_jacobian(F, st.fd_jacobian(lambda a: imu_step_and_jacobians(a, omega, f, d, g)[0], x_v))
        u = np.r_[f, omega]
        st.assert_jacobian(G, st.fd_jacobian(lambda b: imu_step_and_jacobians(x_v, b[3:], b[:3], d, g)[0], u))
        if cam_dim == CAMERA_DIM_SCALED and d > 0:
            assert np.abs(F[:3, SCALE_INDEX]).max() > 0.1 * d * d      # the scale's column is in use
            assert np.diag(F[7:10, G_SLICE]).min() > 0.4 * d                 # and gravity's
        if cam_dim >= CAMERA_DIM_BIASED:
            assert np.array_equal(x_new[13:], x_v[13:])          # biases (and the clock offset) held
            # A bias is an offset of the sample: the step with biases b equals the step without
            # bias states fed the corrected sample.
            if cam_dim < CAMERA_DIM_SCALED:
                x13, _, _ = imu_step_and_jacobians(x_v[:13], omega - x_v[BG_SLICE], f - x_v[BA_SLICE], d, g)
                np.testing.assert_allclose(x_new[:13], x13, atol=1e-14)
            if d > 0:                                             # the bias columns are in use
                assert np.abs(F[:13, 13:19]).max() > 0.1 * d


def test_a_step_in_a_maps_units_is_the_metric_step_seen_through_the_map():
    """A map whose unit is s metres and whose frame is turned by R_map_world: the step of the
    24-number block there (k = 1 / s, gravity R_map_world g) is the metric step mapped into it."""
    rng = np.random.default_rng(5)
    for _ in range(3):
        x = st.random_camera(rng, 1.0, CAMERA_DIM_BIASED)
        s_m, R_mw = rng.uniform(0.2, 5.0), Rotation.random(random_state=rng.integers(1 << 30))
        omega, f, d = rng.normal(0, 1.0, 3), rng.normal(0, 5.0, 3), 0.02
        x_new, _, _ = imu_step_and_jacobians(x, omega, f, d)          # metric, gravity -z
        q_m = (R_mw * Rotation.from_quat(np.r_[x[4:7], x[3]])).as_quat()
        y = np.r_[R_mw.apply(x[R_SLICE]) / s_m, q_m[3], q_m[:3], R_mw.apply(x[V_SLICE]) / s_m, x[10:19], 0.0, 1 / s_m,
                  R_mw.apply(G_WORLD)]
        y_new, _, _ = imu_step_and_jacobians(y, omega, f, d)          # gravity: the block's own
        np.testing.assert_allclose(y_new[R_SLICE], R_mw.apply(x_new[R_SLICE]) / s_m, atol=1e-12)
        np.testing.assert_allclose(y_new[V_SLICE], R_mw.apply(x_new[V_SLICE]) / s_m, atol=1e-12)
        q_new = R_mw * Rotation.from_quat(np.r_[x_new[4:7], x_new[3]] / np.linalg.norm(x_new[Q_SLICE]))
        r_err = q_new.inv() * Rotation.from_quat(np.r_[y_new[4:7], y_new[3]] / np.linalg.norm(y_new[Q_SLICE]))
        assert r_err.magnitude() < 1e-12
        assert y_new[SCALE_INDEX] == 1 / s_m                        # the scale and gravity are constants
        assert np.array_equal(y_new[G_SLICE], y[G_SLICE])


def test_intervals_cover_the_frame_with_the_sample_holding_over_each():
    imu = np.array([[0.0, *[1, 0, 0], *[0, 0, 1]], [0.005, *[2, 0, 0], *[0, 0, 2]], [0.010, *[3, 0, 0], *[0, 0, 3]],
                    [0.015, *[4, 0, 0], *[0, 0, 4]]])
    d, omegas, fs, held = imu_intervals(imu, 0.003, 0.012)
    np.testing.assert_allclose(d, [0.002, 0.005, 0.002], atol=1e-12)
    assert omegas[:, 0].tolist() == [1, 2, 3] and fs[:, 2].tolist() == [1, 2, 3] and not held.any()
    d, omegas, _, _ = imu_intervals(imu, 0.005, 0.010)              # on the sample times
    np.testing.assert_allclose(d, [0.005], atol=1e-12)
    assert omegas[:, 0].tolist() == [2]
    with pytest.raises(ValueError, match="no IMU sample"):
        imu_intervals(imu[1:], 0.003, 0.012)


def test_intervals_split_where_the_samples_stop_describing_the_motion():
    imu = np.array([[0.0, *[1, 0, 0], *[0, 0, 1]], [0.010, *[2, 0, 0], *[0, 0, 2]]])
    # The last sample (0.010) describes up to 0.020; the frame at 0.033 holds it past that.
    d, omegas, fs, held = imu_intervals(imu, 0.003, 0.033, covered_until=0.020)
    np.testing.assert_allclose(d, [0.007, 0.010, 0.013], atol=1e-12)
    assert omegas[:, 0].tolist() == [1, 2, 2] and held.tolist() == [False, False, True]
    d, _, _, held = imu_intervals(imu, 0.003, 0.018, covered_until=0.020)     # covered to the end
    np.testing.assert_allclose(d, [0.007, 0.008], atol=1e-12)
    assert not held.any()


def test_a_held_stretch_takes_the_noise_of_an_unknown_rate_change():
    """Beyond the samples' cover the last sample is held: the same mean, but the orientation's
    and the rate's variances grow by a rate change of imu_hold_rate_sigma over that stretch (a
    density sigma sqrt(d): the rate's variance grows by sigma^2); covered, nothing changes."""
    x_v = np.r_[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, np.zeros(3), np.zeros(3)]
    imu = np.array([[0.0, 0.3, -0.2, 0.1, 0.0, 9.81, 0.0], [0.010, 0.3, -0.2, 0.1, 0.0, 9.81, 0.0]])
    cfg = replace(CFG, imu_hold_rate_sigma=0.5, imu_hold_accel_sigma=0.0)
    out = {}
    for name, cover in (("covered", 0.040), ("held", 0.020), ("plain", np.inf)):
        s = State.from_camera(x_v.copy(), np.eye(13) * 1e-8)
        predict_imu(s, imu, 0.0, 0.033, cfg, covered_until=cover)
        out[name] = s
    st.assert_close(out["covered"].x, out["held"].x, 1e-3)       # the same hold (split once more: discretisation)
    st.assert_close(out["covered"].P, out["plain"].P, 1e-15)
    dP_w = np.diag(out["held"].P)[W_SLICE] - np.diag(out["covered"].P)[W_SLICE]
    np.testing.assert_allclose(dP_w, 0.5**2, rtol=1e-4)     # the rate: sigma^2 (and the gyro noise over a shorter last interval)
    dP_q = np.trace(out["held"].P[Q_SLICE, Q_SLICE] - out["covered"].P[Q_SLICE, Q_SLICE])
    # The orientation: a rate off by sigma held over d, an angle of variance (sigma d)^2 per axis
    # (quaternion units: a quarter of the angle's).
    assert dP_q == pytest.approx(3 * 0.25 * (0.5 * 0.013) ** 2, rel=0.05)


def analytic_imu(a_world, w_cam, R0, t, b_g=np.zeros(3), b_a=np.zeros(3)):
    """Samples of a camera with constant world acceleration and constant body rate, with
    constant biases added: the integrator holds R(q) f, the world acceleration, exactly."""
    Rt = [R0 * Rotation.from_rotvec(w_cam * ti) for ti in t]
    return np.array([[ti, *(w_cam + b_g), *(Ri.as_matrix().T @ (a_world - G_WORLD) + b_a)] for ti, Ri in zip(t, Rt)]), Rt


@pytest.mark.parametrize("cam_dim", [CAMERA_DIM, CAMERA_DIM_BIASED])
def test_prediction_follows_an_analytic_trajectory(cam_dim):
    a_world = np.array([0.3, -0.2, 0.1])
    w_cam = np.array([0.2, -0.4, 0.3])
    R0 = Rotation.from_euler("xyz", [-100, 10, 40], degrees=True)
    r0, v0 = np.array([0.1, 0.2, 1.4]), np.array([0.3, 0.0, -0.1])
    b_g, b_a = (np.array([0.004, -0.006, 0.003]), np.array([0.05, -0.04, 0.06])) if cam_dim > 13 else (0, 0)
    t = np.arange(0.0, 0.5001, 0.001)
    imu, Rt = analytic_imu(a_world, w_cam, R0, t, b_g, b_a)
    x_v = np.r_[r0, R0.as_quat()[[3, 0, 1, 2]], v0, w_cam]
    if cam_dim > 13:
        x_v = np.r_[x_v, b_g, b_a]                    # the filter knows the biases: they are removed
    s = State.from_camera(x_v, np.eye(cam_dim) * 1e-6)
    predict_imu(s, imu, 0.0, 0.5, CFG)
    T = 0.5
    np.testing.assert_allclose(s.x[R_SLICE], r0 + v0 * T + 0.5 * a_world * T * T, atol=1e-6)
    np.testing.assert_allclose(s.x[V_SLICE], v0 + a_world * T, atol=1e-6)
    np.testing.assert_allclose(quat_to_rotation(s.x[Q_SLICE]), Rt[-1].as_matrix(), atol=1e-9)
    np.testing.assert_allclose(s.x[W_SLICE], w_cam, atol=1e-12)
    assert s.P[0, 0] > 1e-6 and np.array_equal(s.P, s.P.T)
    if cam_dim > 13:
        # Without bias states the same samples drift: the biases are what it integrates.
        s13 = State.from_camera(x_v[:13], np.eye(13) * 1e-6)
        predict_imu(s13, imu, 0.0, 0.5, CFG)
        assert np.linalg.norm(s13.r - s.r) > 0.5 * np.linalg.norm(b_a) * T**2 * 0.5


def test_prediction_covariance_is_the_product_of_the_intervals():
    """P_vv through each interval with its own white noise (density^2 / d), the cross-covariance
    by the product of the intervals' F, the bias walks over the frame, then the quaternion's
    normalisation Jacobian: a dense reference with the step's own (tested) Jacobians."""
    rng = np.random.default_rng(12)
    x_v = st.random_camera(rng, 0.5, CAMERA_DIM_BIASED)
    s = State.from_camera(x_v, st.camera_covariance(x_v[Q_SLICE], 0.01, 0.01, 0.1, 0.1, CAMERA_DIM_BIASED))
    for _ in range(3):
        s.add_feature(POINT, rng.normal(0, 2, 3), 0.01 * np.eye(3), 0.05 * rng.normal(size=(3, s.n)) @ s.P)
    t = np.r_[0.0, np.sort(rng.uniform(0.001, 0.04, 7)), 0.05]
    imu = np.column_stack([t, rng.normal(0, 1, (len(t), 3)), rng.normal(0, 5, (len(t), 3))])
    t0, t1 = 0.004, 0.037
    ds, omegas, fs, _ = imu_intervals(imu, t0, t1)
    x, P_vv, F_total = s.x[:19].copy(), s.P[:19, :19].copy(), np.eye(19)
    for d, w, f in zip(ds, omegas, fs):
        x, F, G = imu_step_and_jacobians(x, w, f, d)
        Pn = np.diag(np.r_[np.full(3, CFG.imu.imu_accel_noise**2 / d), np.full(3, CFG.imu.imu_gyro_noise**2 / d)])
        P_vv = F @ P_vv @ F.T + G @ Pn @ G.T
        F_total = F @ F_total
    bias_walk(P_vv, t1 - t0, CFG)
    P = s.P.copy()
    P[:19, :19] = P_vv
    P[:19, 19:] = F_total @ s.P[:19, 19:]
    P[19:, :19] = P[:19, 19:].T
    qn, J = normalise_quaternion_jacobian(x[Q_SLICE])
    T = np.eye(s.n)
    T[Q_SLICE, Q_SLICE] = J
    x_ref = np.r_[x, s.x[19:]]
    x_ref[Q_SLICE] = qn
    predict_imu(s, imu, t0, t1, CFG)
    st.assert_close(s.x, x_ref, 1e-13)
    st.assert_close(s.P, T @ P @ T.T, 1e-11)


# -- the bias states converge ------------------------------------------------------------------

def simulate_biased_imu(seed: int, b_g, b_a, seconds: float = 8.0, rate_hz: int = 210, fps: int = 30,
                        t_d: float | None = None, s_map: float | None = None, k_error: float = 0.0,
                        g_error_rad: float = 0.0, truth: dict | None = None) -> State:
    """A camera swaying and turning (about 0.5 rad, 0.2 m) in front of known points, its
    IMU with constant biases ``b_g``, ``b_a`` and white noise of the filter's own densities,
    integrated with the filter's own zero-order hold (so the IMU model is exact); the filter
    (bias states from zero with their configured prior) predicts through the samples and is
    updated by the visible points' pixels (1 px) every frame. With ``t_d`` (s) the IMU's
    stamps run that far ahead of the camera's clock and the filter has the clock-offset state
    (from zero, its configured prior). With ``s_map`` (metres per map unit) the filter runs in
    a natural start's map: its frame turned from the world's, its unit s_map metres, the scale
    state k starting ``k_error`` (relative) off 1 / s_map with a 5% prior, the gravity state
    starting turned ``g_error_rad`` off the map's gravity (about a random axis across it) with the
    hand-over's prior (0.05 rad across, 0.05 m/s^2 along); ``truth`` then gets the map's true
    gravity (``"g_map"``). Returns the final state."""
    rng = np.random.default_rng(seed)
    cam = st.PINHOLE
    dt = 1.0 / rate_hz
    per_frame = rate_hz // fps
    n = int(seconds * rate_hz)
    t = np.arange(n + 1) * dt
    # The true attitude R0 Exp(theta(t)), theta smooth and within 0.4 rad, gives the body rates
    # of each interval exactly (R_j+1 = R_j Exp(omega_j dt)); the world acceleration is a damped
    # spring towards the start driven by sines, so the camera sways but stays put.
    ph = rng.uniform(0, 2 * np.pi, 6)
    theta = 0.4 * np.column_stack([np.sin(0.9 * t + ph[0]), np.sin(0.7 * t + ph[1]), np.sin(1.3 * t + ph[2])])
    R0 = st.look_at([0, 0, 0], [0, 1, 0])
    Rt = Rotation.from_matrix(R0) * Rotation.from_rotvec(theta)
    w_true = (Rt[:-1].inv() * Rt[1:]).as_rotvec() / dt
    x = np.r_[0.0, 0.0, 0.0, st.quat_of(R0), 0.0, 0.0, 0.0, w_true[0]]
    sg, sa = CFG.imu.imu_gyro_noise / np.sqrt(dt), CFG.imu.imu_accel_noise / np.sqrt(dt)
    rows, states = [], [x]
    for j in range(n):
        a = -2.0 * x[:3] - 1.0 * x[7:10] + 0.4 * np.sin([1.1 * t[j] + ph[3], 0.8 * t[j] + ph[4], 1.5 * t[j] + ph[5]])
        f = quat_to_rotation(x[Q_SLICE]).T @ (a - G_WORLD)
        rows.append([t[j], *(w_true[j] + b_g + rng.normal(0, sg, 3)), *(f + b_a + rng.normal(0, sa, 3))])
        x, _, _ = imu_step_and_jacobians(x, w_true[j], f, dt)
        x[Q_SLICE] /= np.linalg.norm(x[Q_SLICE])
        states.append(x)
    rows = np.array(rows)
    if t_d is not None:
        rows[:, 0] += t_d                  # a sample taken at camera time t is stamped t + t_d
    # Known points 2 to 4 m away, up to about 60 degrees around the first view's axis (+y).
    d = np.column_stack([rng.uniform(-1.7, 1.7, 150), np.ones(150), rng.uniform(-1.7, 1.7, 150)])
    Y = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2.0, 4.0, (150, 1))
    cfg = CFG
    cam_dim = CAMERA_DIM_BIASED if t_d is None else CAMERA_DIM_TIMED
    if s_map is not None:
        cam_dim = CAMERA_DIM_SCALED
    k0 = 0 if t_d is None else 1           # a frame late, so that samples precede it whatever t_d
    x_v = np.r_[states[k0 * per_frame][:13], np.zeros(cam_dim - 13)]
    x_v[:3] += rng.normal(0, 0.003, 3)
    R_mw, s_m, sig_r = Rotation.identity(), 1.0, 0.003
    if s_map is not None:                  # the map's frame and unit
        R_mw, s_m = Rotation.from_rotvec(rng.normal(0, 1.0, 3)), s_map
        q_m = (R_mw * Rotation.from_quat(np.r_[x_v[4:7], x_v[3]])).as_quat()
        x_v[R_SLICE], x_v[V_SLICE] = R_mw.apply(x_v[R_SLICE]) / s_m, R_mw.apply(x_v[V_SLICE]) / s_m
        x_v[Q_SLICE] = np.r_[q_m[3], q_m[:3]]
        x_v[SCALE_INDEX] = (1 + k_error) / s_m
        g_map = R_mw.apply(G_WORLD)
        axis = np.cross(g_map, rng.normal(size=3))
        x_v[G_SLICE] = Rotation.from_rotvec(g_error_rad * axis / np.linalg.norm(axis)).apply(g_map)
        if truth is not None:
            truth["g_map"] = g_map
        sig_r /= s_m
    P_v = st.camera_covariance(x_v[Q_SLICE], sig_r, 1e-3, 0.01 / s_m, 0.05, cam_dim, cfg.imu.gyro_bias_sigma0,
                               cfg.imu.accel_bias_sigma0, cfg.imu.time_offset_sigma0)
    if s_map is not None:
        P_v[TD_INDEX, TD_INDEX] = 0.0      # the clock is exact here
        P_v[SCALE_INDEX, SCALE_INDEX] = (0.05 / s_m) ** 2
        u = x_v[G_SLICE] / np.linalg.norm(x_v[G_SLICE])
        P_v[G_SLICE, G_SLICE] = (9.81 * 0.05) ** 2 * (np.eye(3) - np.outer(u, u)) + 0.05**2 * np.outer(u, u)
    s = State.from_camera(x_v, P_v)
    sig_y = 0.001
    for y in Y:
        s.add_feature(POINT, R_mw.apply(y + rng.normal(0, sig_y, 3)) / s_m, (sig_y / s_m) ** 2 * np.eye(3),
                      np.zeros((3, s.n)))
    for k in range(k0 + 1, n // per_frame + 1):
        j0, j1 = (k - 1) * per_frame, k * per_frame
        predict_imu(s, rows if t_d is not None else rows[j0:j1 + 1], t[j0], t[j1], cfg)
        xt = states[j1]
        uv = st.pixels(cam, quat_to_rotation(xt[Q_SLICE]), xt[:3], Y)
        seen = np.flatnonzero(in_image(cam, uv, margin=20.0))
        assert len(seen) >= 8
        update(s, seen, uv[seen] + rng.normal(0, 1.0, (len(seen), 2)), cam, 1.0)
    return s


@pytest.mark.parametrize("seed, b_g, b_a", [
    (1, [0.004, -0.006, 0.003], [0.05, -0.04, 0.06]),
    (2, [-0.003, 0.002, 0.007], [-0.03, 0.07, -0.05]),
])
def test_bias_states_converge_to_the_imus_biases(seed, b_g, b_a):
    b_g, b_a = np.array(b_g), np.array(b_a)
    s = simulate_biased_imu(seed, b_g, b_a)
    e_g, e_a = s.b_g - b_g, s.b_a - b_a
    sd_g, sd_a = np.sqrt(np.diag(s.P)[BG_SLICE]), np.sqrt(np.diag(s.P)[BA_SLICE])
    print(f"\ngyro bias {np.round(1000 * s.b_g, 2)} mrad/s (true {1000 * b_g}, sd {np.round(1000 * sd_g, 2)}); "
          f"accel bias {np.round(100 * s.b_a, 2)} cm/s^2 (true {100 * b_a}, sd {np.round(100 * sd_a, 2)})")
    # Within 3 sigma of the filter's own covariance ...
    assert (np.abs(e_g) < 3 * sd_g).all() and (np.abs(e_a) < 3 * sd_a).all()
    # ... that covariance far below the prior's (the biases were learnt) ...
    assert (sd_g < 0.3 * CFG.imu.gyro_bias_sigma0).all() and (sd_a < 0.3 * CFG.imu.accel_bias_sigma0).all()
    # ... and clearly nearer the truth than the prior's zero.
    assert np.linalg.norm(e_g) < 0.25 * np.linalg.norm(b_g)
    assert np.linalg.norm(e_a) < 0.25 * np.linalg.norm(b_a)


@pytest.mark.parametrize("seed, t_d", [(1, 0.006), (2, -0.004)])
def test_the_clock_offset_state_converges_to_the_imus_offset(seed, t_d):
    """The IMU's stamps a few ms off the camera's (a host stamping on arrival): the clock-offset
    state, from zero with a 5 ms prior, ends within 3 sigma and 1 ms of the truth."""
    s = simulate_biased_imu(seed, [0.004, -0.006, 0.003], [0.05, -0.04, 0.06], t_d=t_d)
    sd = np.sqrt(s.P[TD_INDEX, TD_INDEX])
    print(f"\nclock offset {1000 * s.t_d:.2f} ms (true {1000 * t_d:.1f}, sd {1000 * sd:.2f})")
    assert abs(s.t_d - t_d) < min(3 * sd, 0.001)
    assert sd < 0.3 * CFG.imu.time_offset_sigma0


@pytest.mark.parametrize("seed, s_map, k_error, g_error_deg", [(1, 0.37, 0.05, 0.0), (2, 2.6, -0.06, 0.0),
                                                                (1, 0.37, 0.05, 2.5), (2, 2.6, -0.06, -3.0)])
def test_the_scale_and_gravity_states_converge_to_the_maps(seed, s_map, k_error, g_error_deg):
    """A natural start's map (its own frame, a unit of s_map metres) handed to the IMU with the
    scale 5-6% off and gravity's direction 0-3 degrees off: the scale state ends within 3 sigma
    and 2% of 1 / s_map (gravity learnt beside it; 1% when gravity was given exactly), its sigma
    well below the prior's 5%; gravity within 0.5 degrees of the map's and its own 3 sigma; the
    biases are learnt as in a metric map."""
    b_g, b_a = np.array([0.004, -0.006, 0.003]), np.array([0.05, -0.04, 0.06])
    truth = {}
    s = simulate_biased_imu(seed, b_g, b_a, s_map=s_map, k_error=k_error, g_error_rad=np.radians(g_error_deg),
                            truth=truth)
    k, sd = s.x[SCALE_INDEX], np.sqrt(s.P[SCALE_INDEX, SCALE_INDEX])
    g, g_map = s.x[G_SLICE], truth["g_map"]
    print(f"\nk {k:.5f} per m (true {1 / s_map:.5f}, sd {sd:.5f}); accel bias {np.round(100 * s.b_a, 2)} cm/s^2; "
          f"gravity {g.round(3)} |g| {np.linalg.norm(g):.3f}")
    assert abs(k * s_map - 1) < 0.02 and abs(k - 1 / s_map) < 3 * sd
    assert sd * s_map < 0.3 * 0.05
    assert np.linalg.norm(s.b_a - b_a) < 0.25 * np.linalg.norm(b_a)
    # Gravity: the angle to the map's, and the error within 3 sigma of the state's own covariance.
    angle = np.arccos(np.clip(g @ g_map / np.linalg.norm(g) / 9.81, -1, 1))
    e = g - g_map
    print(f"gravity {np.degrees(angle):.2f} deg off (from {abs(g_error_deg)}), Mahalanobis "
          f"{np.sqrt(e @ np.linalg.solve(s.P[G_SLICE, G_SLICE], e)):.2f}")
    assert angle < np.radians(0.5) and abs(np.linalg.norm(g) - 9.81) < 0.05
    assert e @ np.linalg.solve(s.P[G_SLICE, G_SLICE], e) < 3**2 * 3


# -- ImuStream ---------------------------------------------------------------------------------

def rows(t, w=(0.01, 0.02, -0.01), a=(0.0, -9.81, 0.1)):
    t = np.atleast_1d(np.asarray(t, float))
    return np.column_stack([t, np.tile(w, (len(t), 1)), np.tile(a, (len(t), 1))])


def test_imu_stream_drops_and_counts_bad_rows():
    s = ImuStream(MapSettings())
    assert s.add(rows(np.arange(0.0, 0.1, 0.005))) == []
    good = rows(np.arange(0.1, 0.2, 0.005))
    bad = good.copy()
    bad[2, 1] = np.nan                      # a NaN row
    bad[5, 4] = np.inf
    bad[7, 3] = 1e30                        # spikes: a 1e30 rate and a 1e30 acceleration
    bad[9, 6] = -1e30
    bad[11, 0] = 0.05                       # out of time order (before rows already given)
    bad[13, 0] = bad[12, 0]                 # a repeated time stamp
    msgs = s.add(bad)
    c = s.counts
    assert (c.rows, c.non_finite, c.spikes, c.out_of_order) == (40, 2, 2, 2)
    assert any("2 IMU samples with NaN/Inf dropped" in m for m in msgs)
    assert any("2 IMU samples beyond the sensor's range (spikes) dropped" in m for m in msgs)
    assert any("2 IMU samples out of time order dropped" in m for m in msgs)
    assert len(s.rows) == 40 - 6 and np.isfinite(s.rows).all() and np.all(np.diff(s.rows[:, 0]) > 0)
    assert np.abs(s.rows[:, 1:4]).max() < 1 and np.abs(s.rows[:, 4:7]).max() < 10
    # A later row older than the last good one is out of order too, counted again.
    s.add(rows([0.15]))
    assert s.counts.out_of_order == 3


def test_imu_stream_covering_and_gaps():
    settings = MapSettings(imu_max_gap_s=0.05)
    s = ImuStream(settings)
    t = np.r_[np.arange(0.0, 0.5, 0.005), np.arange(0.62, 1.0, 0.005)]      # a 0.125 s gap
    s.add(rows(t))
    seg = s.covering(0.1, 0.2)
    assert seg is not None and seg[0, 0] <= 0.1 and seg[-1, 0] <= 0.2 and seg[-1, 0] > 0.2 - 0.005 - 1e-9
    d, _, _, _ = imu_intervals(seg, 0.1, 0.2)
    np.testing.assert_allclose(d.sum(), 0.1, atol=1e-12)
    assert s.counts.gaps == 0
    assert s.covering(0.48, 0.53) is not None       # within the gap allowance at its start
    assert s.covering(0.5, 0.6) is None              # across the gap
    assert s.covering(0.55, 0.65) is None
    assert s.counts.gaps == 2
    assert s.covering(0.7, 0.8) is not None and s.counts.gaps == 2
    assert s.covering(1.2, 1.3) is None              # beyond the last row
    assert s.counts.gaps == 3
    s.drop_before(0.7)
    assert s.rows[0, 0] <= 0.7 < s.rows[1, 0]
    assert s.covering(0.7, 0.75) is not None
    assert ImuStream(settings).covering(0.0, 0.1) is None      # nothing yet: not a gap


def test_still_biases_accelerometer_jacobian_against_finite_differences():
    from runtime.slam.inertial import still_biases

    rng = np.random.default_rng(3)
    q = st.random_quat(rng)
    t = np.arange(0.0, 1.0, 0.005)
    f = quat_to_rotation(q).T @ -G_WORLD + np.array([0.05, -0.02, 0.03])
    imu = np.column_stack([t, np.tile([0.004, 0.0, -0.002], (len(t), 1)), np.tile(f, (len(t), 1))])
    s = MapSettings()
    res = still_biases(imu, t[-1], q, s, CFG)
    assert res is not None and res.seconds == pytest.approx(t[-1] - t[0])
    np.testing.assert_allclose(res.b_a, [0.05, -0.02, 0.03], atol=1e-12)
    J_fd = st.fd_jacobian(lambda qq: still_biases(imu, t[-1], qq, s, CFG).b_a, q)
    st.assert_jacobian(res.J_q, J_fd)


def test_an_imu_at_rest_predicts_no_motion():
    """A still camera's accelerometer reads the specific force +9.81 m/s^2 towards world up
    (physics, not the module's constant): integrated, it must neither rise nor fall."""
    rng = np.random.default_rng(7)
    q = st.random_quat(rng)
    f_still = quat_to_rotation(q).T @ np.array([0.0, 0.0, 9.81])
    x = np.r_[0.0, 0.0, 0.0, q, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    for _ in range(100):                      # 1 s at 100 Hz
        x, _, _ = imu_step_and_jacobians(x, np.zeros(3), f_still, 0.01)
    np.testing.assert_allclose(x[:3], 0.0, atol=1e-9)
    np.testing.assert_allclose(x[7:10], 0.0, atol=1e-9)
