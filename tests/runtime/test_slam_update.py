"""The EKF's measurement steps (filter.py) against a dense textbook reference: the batch update
of a state mixing points and inverse-depth features, the frame's factored update
(:class:`FrameUpdate`, several batches, the covariance formed once at commit; it replaced the
old sequential update), the refusals that must change nothing, and the covariance a new
feature (point or inverse-depth) enters the state with."""

from __future__ import annotations

import numpy as np
import pytest

import slam_testing as st
from kinematics.camera import project, unproject
from runtime.slam.features import FEATURE_DIMS, INVERSE_DEPTH, POINT, inverse_depth
from runtime.slam.filter import (
    FeatureNotMeasurable,
    FrameUpdate,
    add_inverse_depth_feature,
    add_point_feature,
    innovation_covariances,
    innovation_nis,
    update,
)
from runtime.slam.measurement import init_point_from_depth, predict
from runtime.slam.quaternion import normalise_quaternion_jacobian, quat_to_rotation
from runtime.slam.state import CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_TIMED, Q_SLICE, TD_INDEX, SlamNumericalError, State
from test_slam_core import mixed_state

CAMERAS = st.CAMERAS
R_PIX = np.diag([1.5, 0.8])


def dense_H(state: State, ks, cam, x=None) -> tuple[np.ndarray, np.ndarray]:
    """The predicted measurements h (2m,) and the dense Jacobian H (2m, n) at ``x``, its columns
    placed by the feature sizes (not by the state's own offset table), checked against central
    differences of the prediction over the whole state."""
    x = state.x if x is None else x
    pred = predict(state, ks, cam, x=x)
    assert pred.valid.all()
    starts = state.cam_dim + np.concatenate([[0], np.cumsum(FEATURE_DIMS[state.kinds])[:-1]])
    H = np.zeros((2 * len(ks), state.n))
    for i, k in enumerate(ks):
        d = FEATURE_DIMS[state.kinds[k]]
        H[2 * i:2 * i + 2, :7] = pred.H_c[i]
        H[2 * i:2 * i + 2, starts[k]:starts[k] + d] = pred.H_f[i][:, :d]
    H_fd = st.fd_jacobian(lambda a: predict(state, ks, cam, x=a).uv.reshape(-1), x)
    st.assert_close(H, H_fd, 1e-6)
    return pred.uv.reshape(-1), H


def normalise(x, P):
    """q renormalised in the mean and its Jacobian applied to P at the renormalised q (where
    filter.py evaluates it; the textbook's at the unnormalised q differs at second order of the
    update's step along q, which is orthogonal to q)."""
    x = x.copy()
    x[Q_SLICE] /= np.linalg.norm(x[Q_SLICE])
    _, J = normalise_quaternion_jacobian(x[Q_SLICE])
    T = np.eye(len(x))
    T[Q_SLICE, Q_SLICE] = J
    return x, T @ P @ T.T


def joseph_update(P, H, R):
    """The textbook gain and Joseph-form covariance: K, S, (I - KH) P (I - KH)^T + K R K^T."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    IKH = np.eye(len(P)) - K @ H
    return K, S, IKH @ P @ IKH.T + K @ R @ K.T


def true_matches(state: State, ks, cam, rng, noise=1.0) -> np.ndarray:
    """Measurements of the features near where they are predicted (noisy), px."""
    return predict(state, ks, cam).uv + rng.normal(0, noise, (len(ks), 2))


def two_batch_reference(s: State, cam, b1, z1, b2, z2, jacobian=None):
    """The dense textbook frame of two batches: the second linearised at the first's mean with
    the first's covariance. Returns (S1, x1, S2, x2, P2), x2 and P2 renormalised."""
    jacobian = jacobian or dense_H
    x0, P0 = s.x.copy(), s.P.copy()
    R1, R2 = np.kron(np.eye(len(b1)), R_PIX), np.kron(np.eye(len(b2)), R_PIX)
    h1, H1 = jacobian(s, b1, cam)
    S1 = H1 @ P0 @ H1.T + R1
    K1 = P0 @ H1.T @ np.linalg.inv(S1)
    x1 = x0 + K1 @ (z1.reshape(-1) - h1)
    x1[Q_SLICE] /= np.linalg.norm(x1[Q_SLICE])
    P1 = P0 - K1 @ S1 @ K1.T
    h2, H2 = jacobian(s, b2, cam, x=x1)
    S2 = H2 @ P1 @ H2.T + R2
    K2 = P1 @ H2.T @ np.linalg.inv(S2)
    x2, P2 = normalise(x1 + K2 @ (z2.reshape(-1) - h2), P1 - K2 @ S2 @ K2.T)
    return S1, x1, S2, x2, P2


# -- the batch update --------------------------------------------------------------------------

@pytest.mark.parametrize("cam_dim", [CAMERA_DIM, CAMERA_DIM_BIASED])
@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_update_matches_the_dense_reference_with_both_kinds(model, cam_dim):
    cam = CAMERAS[model]
    rng = np.random.default_rng(14)
    s = mixed_state(rng, cam_dim, n_points=4, n_inverse=4, cam=cam)
    ks = np.array([6, 1, 0, 7, 3])                 # any order, both kinds
    assert set(s.kinds[ks].tolist()) == {POINT, INVERSE_DEPTH}
    z = true_matches(s, ks, cam, rng, 2.0)
    h, H = dense_H(s, ks, cam)
    R = np.kron(np.eye(len(ks)), R_PIX)
    K, S_ref, P_ref = joseph_update(s.P, H, R)
    x_ref, P_ref = normalise(s.x + K @ (z.reshape(-1) - h), P_ref)
    S_each = innovation_covariances(s, predict(s, ks, cam), R_PIX)
    res = update(s, ks, z, cam, R_PIX)
    st.assert_close(res.S, S_ref, 1e-10)
    for i in range(len(ks)):
        st.assert_close(S_each[i], S_ref[2 * i:2 * i + 2, 2 * i:2 * i + 2], 1e-10)
    st.assert_close(s.x, x_ref, 1e-12)
    st.assert_close(s.P, P_ref, 1e-9)
    np.testing.assert_allclose(res.nu.reshape(-1), z.reshape(-1) - h, atol=1e-9)
    assert np.isclose(res.nis, res.nu.reshape(-1) @ np.linalg.solve(S_ref, res.nu.reshape(-1)))
    assert abs(np.linalg.norm(s.q) - 1) < 1e-15 and np.array_equal(s.P, s.P.T)


# -- the frame's factored update ---------------------------------------------------------------

@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_frame_update_batches_equal_the_dense_reference(model):
    """Two batches (as the 1-point RANSAC's low-innovation inliers and its rescued matches): the
    second linearised at the first's mean with the first's covariance; P formed once at commit."""
    cam = CAMERAS[model]
    rng = np.random.default_rng(15)
    s = mixed_state(rng, CAMERA_DIM_BIASED, n_points=5, n_inverse=4, cam=cam)
    x0, P0 = s.x, s.P
    x0_copy, P0_copy = s.x.copy(), s.P.copy()
    b1, b2 = np.array([0, 5, 6, 2]), np.array([7, 1, 8])
    z1, z2 = true_matches(s, b1, cam, rng, 2.0), true_matches(s, b2, cam, rng, 2.0)

    S1, x1, S2, x2_ref, P2_ref = two_batch_reference(s, cam, b1, z1, b2, z2)

    fu = FrameUpdate(s, cam, R_PIX)
    r1 = fu.update(b1, z1)
    st.assert_close(r1.S, S1, 1e-10)
    st.assert_close(fu.x, x1, 1e-12)
    # The current ellipses after the first batch: H P1 H^T + R.
    S_now = fu.innovation_covariances(fu.predict(b2))
    for i in range(len(b2)):
        st.assert_close(S_now[i], S2[2 * i:2 * i + 2, 2 * i:2 * i + 2], 1e-9)
    r2 = fu.update(b2, z2)
    st.assert_close(r2.S, S2, 1e-9)
    assert fu.batches == 2
    # The state is untouched until commit.
    assert s.x is x0 and s.P is P0 and np.array_equal(s.x, x0_copy) and np.array_equal(s.P, P0_copy)
    fu.commit()
    st.assert_close(s.x, x2_ref, 1e-12)
    st.assert_close(s.P, P2_ref, 1e-9)
    assert np.array_equal(s.P, s.P.T) and abs(np.linalg.norm(s.q) - 1) < 1e-15

    # Two update() calls renormalise the covariance in between: equal to second order.
    seq = State(x0_copy, P0_copy, s.cam_dim, s.kinds, s.anchors)
    update(seq, b1, z1, cam, R_PIX)
    update(seq, b2, z2, cam, R_PIX)
    st.assert_close(seq.x, s.x, 1e-8)
    st.assert_close(seq.P, s.P, 1e-4)


def test_a_frame_update_with_no_batch_leaves_the_arrays():
    rng = np.random.default_rng(16)
    s = mixed_state(rng)
    x0, P0 = s.x, s.P
    fu = FrameUpdate(s, CAMERAS["pinhole"], 1.0)
    empty = fu.update([], np.zeros((0, 2)))
    assert empty.nu.shape == (0, 2)
    fu.commit()
    assert s.x is x0 and s.P is P0


def test_refused_batches_change_nothing_and_the_frame_goes_on():
    """Repeated features, NaN/Inf matches, a feature behind the camera and an indefinite S are
    refused with the reason; nothing changes, and the frame continues exactly as if they had
    not been tried."""
    cam = CAMERAS["brown"]
    rng = np.random.default_rng(17)
    s = mixed_state(rng, CAMERA_DIM, n_points=4, n_inverse=3, cam=cam)
    # Feature 6 (a point) behind the camera.
    R = quat_to_rotation(s.q)
    s.x[s.feature_slice(6)] = s.r - 2.0 * R[:, 2]
    twin = s.copy()
    good = np.array([0, 3, 5])
    z = true_matches(s, good, cam, rng)
    fu, fu_twin = FrameUpdate(s, cam, 1.0), FrameUpdate(twin, cam, 1.0)
    fu.update(good[:2], z[:2])
    fu_twin.update(good[:2], z[:2])
    x_mid = fu.x.copy()
    with pytest.raises(ValueError, match="not distinct"):
        fu.update([1, 1], np.zeros((2, 2)) + 300)
    with pytest.raises(FeatureNotMeasurable, match=r"measurements of features \[2\] are NaN/Inf"):
        fu.update([1, 2], [[300.0, 200.0], [np.nan, 100.0]])
    with pytest.raises(FeatureNotMeasurable, match=r"features \[6\] have no predicted image point"):
        fu.update([1, 6], [[300.0, 200.0], [320.0, 240.0]])
    bad_R = FrameUpdate(s, cam, -1e9)
    with pytest.raises(SlamNumericalError, match="not positive definite"):
        bad_R.update([1], [[300.0, 200.0]])
    assert bad_R.batches == 0 and fu.batches == 1 and np.array_equal(fu.x, x_mid)
    fu.update(good[2:], z[2:])
    fu_twin.update(good[2:], z[2:])
    fu.commit()
    fu_twin.commit()
    assert np.array_equal(s.x, twin.x)
    st.assert_close(s.P, twin.P, 1e-14)          # BLAS may sum in another order: rounding only
    # update() refuses the same way and leaves the state as it was.
    x0, P0 = s.x.copy(), s.P.copy()
    with pytest.raises(FeatureNotMeasurable, match=r"features \[6\]"):
        update(s, [0, 6], np.zeros((2, 2)), cam, 1.0)
    assert np.array_equal(s.x, x0) and np.array_equal(s.P, P0)
    S = innovation_covariances(s, predict(s, [0, 6], cam), 1.0)
    assert np.isfinite(S[0]).all() and np.isnan(S[1]).all()


def test_commit_refuses_a_negative_variance_and_keeps_the_frame_start():
    """A covariance claiming an impossible correlation (|corr| = 10) between two features: a
    precise measurement of one removes more variance from the other than it has. The commit's
    guard refuses, and the state keeps its mean and covariance."""
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(18)
    s = mixed_state(rng, CAMERA_DIM, n_points=3, n_inverse=0)
    f0, f1 = s.feature_slice(0), s.feature_slice(1)
    P = s.P.copy()
    c = 10.0 * np.sqrt(np.diag(P)[f0] * np.diag(P)[f1])
    P[f0, f1] = np.diag(c)
    P[f1, f0] = np.diag(c)
    s.P = P                                   # put in afterwards: State refuses such a P
    x0, P0 = s.x, s.P
    fu = FrameUpdate(s, cam, 0.01)
    fu.update([0], true_matches(s, [0], cam, rng))
    with pytest.raises(SlamNumericalError, match=r"negative variance P\[1[6-8],1[6-8]\].*feature 1 \(point\)"):
        fu.commit()
    assert s.x is x0 and s.P is P0


# -- new features enter with the right covariance ----------------------------------------------

@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_new_feature_covariances(model):
    """A new feature is a function of the camera, its pixel and (point) a depth or
    (inverse depth) a prior on rho: the grown covariance is A blockdiag(P, R, var) A^T for the
    augmenting map A, which Jacobians against central differences give."""
    cam = CAMERAS[model]
    rng = np.random.default_rng(19)
    s = mixed_state(rng, CAMERA_DIM_BIASED, n_points=2, n_inverse=2, cam=cam)
    uv = np.array([0.4 * cam.width, 0.35 * cam.height])
    R = np.diag([2.0, 3.0])
    cd = s.cam_dim

    def augmented(P, J_x, J_uv, J_extra, var):
        n, d = len(P), len(J_extra)
        A = np.zeros((n + d, n + 3))
        A[:n, :n] = np.eye(n)
        A[n:, :cd] = J_x
        A[n:, n:n + 2] = J_uv
        A[n:, n + 2] = J_extra
        Pa = np.zeros((n + 3, n + 3))
        Pa[:n, :n] = P
        Pa[n:n + 2, n:n + 2] = R
        Pa[n + 2, n + 2] = var
        return A @ Pa @ A.T

    # A point at 2.5 m +- 0.3 m along the ray.
    P0 = s.P.copy()
    lam, var_d = 2.5, 0.3**2
    J_x = st.fd_jacobian(lambda a: init_point_from_depth(a, uv, lam, cam)[0], s.x_v.copy())
    J_uv = st.fd_jacobian(lambda b: init_point_from_depth(s.x_v, b, lam, cam)[0], uv, h=1e-4)
    J_d = st.fd_jacobian(lambda c: init_point_from_depth(s.x_v, uv, c[0], cam)[0], np.array([lam]))[:, 0]
    k = add_point_feature(s, uv, lam, var_d, R, cam)
    assert s.kinds[k] == POINT and np.allclose(s.feature(k), init_point_from_depth(s.x_v, uv, lam, cam)[0])
    st.assert_close(s.P, augmented(P0, J_x, J_uv, J_d, var_d), 1e-6)
    with pytest.raises(ValueError, match="depth"):
        add_point_feature(s, uv, -1.0, var_d, R, cam)

    # An inverse-depth ray, rho0 = 0.8 +- 0.4 (the anchor held at the current orientation).
    P0 = s.P.copy()
    rho0, s_rho = 0.8, 0.4
    y0, A0, _, _ = inverse_depth.init_from_pixel(s.x_v, uv, cam, rho0)

    def ray(xv, p):
        h = A0.T @ quat_to_rotation(xv[3:7]) @ unproject(cam, np.asarray(p, float)[None])[0]
        th, ph, _ = inverse_depth.angles_and_jacobian(h)
        return np.r_[xv[:3], th, ph, rho0]

    J_x = st.fd_jacobian(lambda a: ray(a, uv), s.x_v.copy())
    J_uv = st.fd_jacobian(lambda b: ray(s.x_v, b), uv, h=1e-4)
    k = add_inverse_depth_feature(s, uv, cam, rho0, s_rho, R)
    assert s.kinds[k] == INVERSE_DEPTH and np.allclose(s.feature(k), y0) and np.allclose(s.anchors[k], A0)
    st.assert_close(s.P, augmented(P0, J_x, J_uv, np.eye(6)[5], s_rho**2), 1e-6)
    # The ray through its pixel: at any inverse depth it projects back there.
    for rho in (0.1, 1.0, 3.0):
        y = s.feature(k).copy()
        y[5] = rho
        p = inverse_depth.world_point(y, s.anchors[k])
        np.testing.assert_allclose(project(cam, ((p - s.r) @ quat_to_rotation(s.q))[None])[0], uv, atol=1e-7)
    s.guard("test", check_psd=True)


def test_frame_update_ellipses_of_no_features_after_a_batch():
    rng = np.random.default_rng(20)
    cam = CAMERAS["pinhole"]
    s = mixed_state(rng)
    fu = FrameUpdate(s, cam, 1.0)
    fu.update([0, 1], true_matches(s, [0, 1], cam, rng))
    assert fu.innovation_covariances(fu.predict([])).shape == (0, 2, 2)


# -- the IMU's clock offset in the state ----------------------------------------------------------

def dense_H_timed(state: State, ks, cam, x=None) -> tuple[np.ndarray, np.ndarray]:
    """h (2m,) and the filter's H (2m, n) for a state with the clock-offset entry: the pose and
    feature columns, and t_d's column checked against central differences over t_d (the
    prediction is linear in it). The terms of t_d times the image velocity's own derivatives
    are left out of H (first order in t_d, as the filter leaves them)."""
    x = state.x if x is None else x
    pred = predict(state, ks, cam, x=x)
    assert pred.valid.all() and pred.H_t is not None
    H = np.zeros((2 * len(ks), state.n))
    for i, k in enumerate(ks):
        d = FEATURE_DIMS[state.kinds[k]]
        H[2 * i:2 * i + 2, :7] = pred.H_c[i]
        H[2 * i:2 * i + 2, state.starts[k]:state.starts[k] + d] = pred.H_f[i][:, :d]
        H[2 * i:2 * i + 2, TD_INDEX] = pred.H_t[i]

    def h_of_td(td):
        xt = x.copy()
        xt[TD_INDEX] = td[0]
        return predict(state, ks, cam, x=xt).uv.reshape(-1)
    st.assert_close(H[:, TD_INDEX:TD_INDEX + 1], st.fd_jacobian(h_of_td, x[TD_INDEX:TD_INDEX + 1]), 1e-6)
    return pred.uv.reshape(-1), H


def test_updates_with_the_clock_offset_equal_the_dense_reference():
    """The clock offset's column of H enters the batch update, the frame's factored batches and
    the search ellipses exactly as a dense EKF with that H."""
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(16)
    s = mixed_state(rng, CAMERA_DIM_TIMED, n_points=5, n_inverse=4, cam=cam)
    assert s.has_time_offset and abs(s.t_d) > 0
    x0, P0 = s.x.copy(), s.P.copy()
    b1, b2 = np.array([0, 5, 6, 2]), np.array([7, 1, 8])
    z1, z2 = true_matches(s, b1, cam, rng, 2.0), true_matches(s, b2, cam, rng, 2.0)
    S1, x1, S2, x2_ref, P2_ref = two_batch_reference(s, cam, b1, z1, b2, z2, dense_H_timed)

    S_each = innovation_covariances(s, predict(s, b1, cam), R_PIX)
    for i in range(len(b1)):
        st.assert_close(S_each[i], S1[2 * i:2 * i + 2, 2 * i:2 * i + 2], 1e-10)
    fu = FrameUpdate(s, cam, R_PIX)
    st.assert_close(fu.update(b1, z1).S, S1, 1e-10)
    st.assert_close(fu.x, x1, 1e-12)
    S_now = fu.innovation_covariances(fu.predict(b2))
    for i in range(len(b2)):
        st.assert_close(S_now[i], S2[2 * i:2 * i + 2, 2 * i:2 * i + 2], 1e-9)
    st.assert_close(fu.update(b2, z2).S, S2, 1e-9)
    fu.commit()
    st.assert_close(s.x, x2_ref, 1e-12)
    st.assert_close(s.P, P2_ref, 1e-9)
    # One batch through update() as well.
    one = State(x0, P0, s.cam_dim, s.kinds, s.anchors)
    h1, H1 = dense_H_timed(one, b1, cam)
    K, S_ref, P_ref = joseph_update(P0, H1, np.kron(np.eye(len(b1)), R_PIX))
    x_ref, P_ref = normalise(x0 + K @ (z1.reshape(-1) - h1), P_ref)
    update(one, b1, z1, cam, R_PIX)
    st.assert_close(one.x, x_ref, 1e-12)
    st.assert_close(one.P, P_ref, 1e-9)


def test_the_clock_offset_moves_a_prediction_along_the_cameras_motion():
    """With ``t_d`` in the state a feature is predicted where the constant-velocity camera puts
    it ``t_d`` later; ``H_t`` is that motion's image velocity (central differences of the motion
    model), so a wrong quaternion-rate convention fails here."""
    from runtime.slam.motion import f_and_dfdx

    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(17)
    s = mixed_state(rng, CAMERA_DIM_TIMED, n_points=5, n_inverse=3, cam=cam)
    ks = np.arange(s.n_features)
    t_d = 0.004
    s.x[TD_INDEX] = t_d
    s.t_ref = 0.0                   # the camera block stands at its frame's time
    pred = predict(s, ks, cam)
    assert pred.valid.all()

    def uv_after(dt):
        x = s.x.copy()
        x[TD_INDEX] = 0.0
        if dt != 0.0:
            x_v, _ = f_and_dfdx(x[:s.cam_dim], abs(dt)) if dt > 0 else f_and_dfdx(
                np.r_[x[:7], -x[7:13], x[13:s.cam_dim]], -dt)
            x[:s.cam_dim] = x_v
        return predict(s, ks, cam, x=x).uv
    eps = 1e-5
    np.testing.assert_allclose(pred.H_t, (uv_after(eps) - uv_after(-eps)) / (2 * eps), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(pred.uv, uv_after(t_d), atol=0.05)     # first order in t_d
    uv0 = uv_after(0.0)
    assert np.abs(pred.uv - uv0).max() > 0.5                             # and it moves them
    # A camera block already propagated to the frame's time plus t_d (t_ref) moves them no more.
    s.t_ref = t_d
    np.testing.assert_allclose(predict(s, ks, cam).uv, uv0, atol=1e-9)
    np.testing.assert_allclose(predict(s, ks, cam).H_t, pred.H_t, atol=1e-12)


def test_innovation_nis_is_the_mahalanobis_distance_and_refuses_what_is_not_a_covariance():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(40, 2, 2))
    S = A @ A.transpose(0, 2, 1) + 0.05 * np.eye(2)
    nu = rng.normal(scale=3.0, size=(40, 2))
    expected = np.array([v @ np.linalg.solve(s, v) for v, s in zip(nu, S)])
    np.testing.assert_allclose(innovation_nis(nu, S), expected, rtol=1e-12)
    S[3] = np.nan
    S[4] = [[1.0, 2.0], [2.0, 1.0]]                      # indefinite
    S[5] = [[-1.0, 0.0], [0.0, -1.0]]
    d2 = innovation_nis(nu, S)
    assert np.isinf(d2[3:6]).all() and np.isfinite(np.delete(d2, [3, 4, 5])).all()


def test_update_with_shaped_noise_matches_the_dense_reference():
    """Each match's own noise covariance ``L A_i L^T`` (an edge's match, uncertain along the
    edge): the batch, its ellipses and the scalar multiples all equal the dense textbook update
    with that block-diagonal R."""
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(41)
    s = mixed_state(rng, CAMERA_DIM, n_points=4, n_inverse=4, cam=cam)
    ks = np.array([2, 5, 0, 6])
    z = true_matches(s, ks, cam, rng, 2.0)
    A = np.empty((len(ks), 2, 2))
    for i, (ratio, angle) in enumerate([(1.0, 0.0), (40.0, 0.3), (100.0, -1.2), (3.0, 2.0)]):
        v = np.array([np.cos(angle), np.sin(angle)])
        A[i] = ratio * np.outer(v, v) + np.outer([-v[1], v[0]], [-v[1], v[0]])
    L = np.linalg.cholesky(R_PIX)
    R = np.zeros((2 * len(ks), 2 * len(ks)))
    for i in range(len(ks)):
        R[2 * i:2 * i + 2, 2 * i:2 * i + 2] = L @ A[i] @ L.T
    h, H = dense_H(s, ks, cam)
    K, S_ref, P_ref = joseph_update(s.P, H, R)
    x_ref, P_ref = normalise(s.x + K @ (z.reshape(-1) - h), P_ref)
    S_each = innovation_covariances(s, predict(s, ks, cam), R_PIX, A)
    scalar = innovation_covariances(s, predict(s, ks, cam), R_PIX, np.full(len(ks), 3.0))
    plain = innovation_covariances(s, predict(s, ks, cam), R_PIX)
    for i in range(len(ks)):
        st.assert_close(S_each[i], S_ref[2 * i:2 * i + 2, 2 * i:2 * i + 2], 1e-10)
        st.assert_close(scalar[i] - plain[i], 2.0 * R_PIX, 1e-10)
    res = update(s, ks, z, cam, R_PIX, r_scale=A)
    st.assert_close(res.S, S_ref, 1e-10)
    st.assert_close(s.x, x_ref, 1e-12)
    st.assert_close(s.P, P_ref, 1e-9)


def test_shaped_noise_that_is_not_a_covariance_is_refused():
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(42)
    s = mixed_state(rng, CAMERA_DIM, n_points=2, n_inverse=0, cam=cam)
    ks = np.array([0, 1])
    bad = np.array([np.eye(2), np.diag([1.0, -1.0])])
    with pytest.raises(ValueError, match="positive definite"):
        innovation_covariances(s, predict(s, ks, cam), R_PIX, bad)
    with pytest.raises(ValueError, match="shapes"):
        innovation_covariances(s, predict(s, ks, cam), R_PIX, np.ones((2, 3)))
