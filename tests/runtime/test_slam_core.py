"""Tests for runtime.slam's core: state layout, motion and measurement models (Jacobians against
central differences), EKF predict/update against a dense reference, feature initialisation, the
covariance guard, and the filter's consistency (camera-position NEES) in simulation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from kinematics.camera import CameraIntrinsics, in_image, project
from runtime.slam.filter import (
    FeatureNotMeasurable,
    add_point_feature,
    innovation_covariances,
    measurement_order,
    update,
    update_one,
)
from runtime.slam.measurement import (
    h_and_jacobians,
    h_and_jacobians_many,
    init_point_from_depth,
    innovation_covariance,
    ray_from_pixel,
)
from runtime.slam.motion import (
    dfdn,
    f_and_dfdx,
    f_and_dfdx_dfdn,
    noise_covariance,
    normalise_quaternion_jacobian,
    predict,
    process_noise,
)
from runtime.slam.state import (
    Q_SLICE,
    R_SLICE,
    V_SLICE,
    W_SLICE,
    SlamConfig,
    SlamNumericalError,
    State,
    check_covariance,
    feature_slice,
    quat_left_matrix,
    quat_multiply,
    quat_to_rotation,
    quat_to_rotvec,
    rotvec_to_quat,
    rotvec_to_quat_jacobian,
    state_size,
)

DT = 1.0 / 30.0
PINHOLE = CameraIntrinsics(width=640, height=480, fx=514.7, fy=514.7, cx=319.5, cy=239.5)
CAMERAS = {
    "brown": CameraIntrinsics(width=640, height=480, fx=500.0, fy=505.0, cx=322.0, cy=236.0,
                              model="brown", k1=-0.25, k2=0.08, p1=1e-3, p2=-5e-4, k3=-0.01),
    "fisheye": CameraIntrinsics(width=640, height=480, fx=300.0, fy=302.0, cx=318.0, cy=241.0,
                                model="fisheye", k1=0.05, k2=-0.01, k3=0.003, k4=-0.001),
    "radial-sqrt": CameraIntrinsics(width=640, height=480, fx=195.0, fy=195.0, cx=162.0, cy=125.0,
                                    model="radial-sqrt", kd1=9e-7),
}


# -- helpers -----------------------------------------------------------------------------------

def random_quat(rng) -> np.ndarray:
    """A random unit quaternion, w x y z."""
    return Rotation.random(random_state=rng.integers(2**31)).as_quat()[[3, 0, 1, 2]]


def to_scipy(q) -> Rotation:
    return Rotation.from_quat(np.asarray(q)[[1, 2, 3, 0]])


def random_camera(rng, w_scale: float = 1.0) -> np.ndarray:
    return np.concatenate([rng.normal(0, 1, 3), random_quat(rng), rng.normal(0, 0.5, 3),
                           rng.normal(0, w_scale, 3)])


def fd_jacobian(f, x, h: float = 1e-6) -> np.ndarray:
    """Central differences, one coordinate at a time; quaternions are perturbed in R^4 without
    renormalising, as the analytic Jacobians are defined."""
    x = np.asarray(x, dtype=float)
    cols = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h))
    return np.stack(cols, axis=-1)


def assert_jacobian(J, J_fd, rtol: float = 1e-6, atol_scale: float = 1e-6) -> None:
    """|J - J_fd| <= rtol |J_fd| + atol_scale * max|J_fd| element-wise (the 1e-6 scale)."""
    J, J_fd = np.asarray(J), np.asarray(J_fd)
    assert J.shape == J_fd.shape and np.isfinite(J).all()
    tol = rtol * np.abs(J_fd) + atol_scale * max(np.abs(J_fd).max(), 1e-12)
    assert (np.abs(J - J_fd) <= tol).all(), f"max error {np.abs(J - J_fd).max():.3g}"


def tangent_basis(q) -> np.ndarray:
    """(4, 3) dq/dtheta of q * exp(theta) at 0: orthogonal to q, columns of length 1/2."""
    return quat_left_matrix(q)[:, 1:] / 2.0


def camera_covariance(q, sig_r, sig_theta, sig_v, sig_w) -> np.ndarray:
    """A (13, 13) camera covariance with an orientation error theta (local, rad) mapped into the
    quaternion's tangent (so P has q's norm direction as its null direction, as in the filter)."""
    P = np.zeros((13, 13))
    P[R_SLICE, R_SLICE] = sig_r**2 * np.eye(3)
    T = tangent_basis(q)
    P[Q_SLICE, Q_SLICE] = sig_theta**2 * T @ T.T
    P[V_SLICE, V_SLICE] = sig_v**2 * np.eye(3)
    P[W_SLICE, W_SLICE] = sig_w**2 * np.eye(3)
    return P


def reduced_covariance(state: State) -> np.ndarray:
    """P restricted to the complement of the quaternion's norm direction (n - 1 dims)."""
    n = state.n
    q = state.q
    B = np.linalg.svd(np.eye(4) - np.outer(q, q))[0][:, :3]    # orthonormal basis of q-perp
    T = np.zeros((n, n - 1))
    T[:3, :3] = np.eye(3)
    T[3:7, 3:6] = B
    T[7:, 6:] = np.eye(n - 7)
    return T.T @ state.P @ T


def map_state(rng, n_features: int = 5) -> tuple[State, np.ndarray]:
    """A camera looking along world +Z at random points 2-4 m ahead, with a random full
    (correlated) PSD covariance of the right structure. Returns the state and the true points."""
    q = rotvec_to_quat(rng.normal(0, 0.1, 3))
    x_v = np.concatenate([rng.normal(0, 0.1, 3), q, rng.normal(0, 0.3, 3), rng.normal(0, 0.3, 3)])
    Y = np.column_stack([rng.uniform(-1, 1, n_features), rng.uniform(-0.7, 0.7, n_features),
                         rng.uniform(2, 4, n_features)])
    n = state_size(n_features)
    A = rng.normal(0, 0.02, (n, n))
    # Make q's block tangent: the covariance a running filter has.
    Tq = np.eye(n)
    Tq[3:7, 3:7] = np.eye(4) - np.outer(q, q)
    P = Tq @ (A @ A.T + 1e-4 * np.eye(n)) @ Tq.T
    return State(np.concatenate([x_v, Y.reshape(-1)]), P), Y


# -- quaternions and the layout ----------------------------------------------------------------

def test_layout_helpers():
    assert state_size(4) == 25
    assert feature_slice(0) == slice(13, 16) and feature_slice(2) == slice(19, 22)
    rng = np.random.default_rng(0)
    s, _ = map_state(rng, 3)
    assert s.n_features == 3 and np.array_equal(s.feature(1), s.x[16:19])
    assert np.array_equal(s.x_v, s.x[:13]) and np.array_equal(s.q, s.x[3:7])


@pytest.mark.parametrize("angle", [0.0, 1e-9, 5e-4, 2e-3, 0.7, 3.0])
def test_rotvec_to_quat_and_jacobian(angle):
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    theta = angle * axis / np.linalg.norm(axis)
    q, J = rotvec_to_quat_jacobian(theta)
    assert np.allclose(to_scipy(q).as_matrix(), Rotation.from_rotvec(theta).as_matrix(), atol=1e-15)
    assert abs(np.linalg.norm(q) - 1) < 1e-15
    J_fd = fd_jacobian(lambda t: rotvec_to_quat(t), theta, h=1e-6)
    assert_jacobian(J, J_fd)
    if angle == 0.0:
        assert np.array_equal(J, np.vstack([np.zeros(3), 0.5 * np.eye(3)]))
    if angle < np.pi:
        assert np.allclose(quat_to_rotvec(q), theta, atol=1e-12)


def test_quaternion_convention_matches_scipy():
    rng = np.random.default_rng(2)
    q, p = random_quat(rng), random_quat(rng)
    assert np.allclose(quat_to_rotation(q), to_scipy(q).as_matrix(), atol=1e-15)
    # Hamilton product, p applied first: R(q * p) = R(q) R(p)
    assert np.allclose(to_scipy(quat_multiply(q, p)).as_matrix(),
                       (to_scipy(q) * to_scipy(p)).as_matrix(), atol=1e-15)


def test_normalise_quaternion_jacobian():
    rng = np.random.default_rng(3)
    q = 1.3 * random_quat(rng) + rng.normal(0, 0.1, 4)
    qn, J = normalise_quaternion_jacobian(q)
    assert abs(np.linalg.norm(qn) - 1) < 1e-15
    assert_jacobian(J, fd_jacobian(lambda a: a / np.linalg.norm(a), q))
    # At a unit quaternion the Jacobian projects out q itself.
    _, J1 = normalise_quaternion_jacobian(qn)
    assert np.allclose(J1 @ qn, 0, atol=1e-15)


# -- motion model ------------------------------------------------------------------------------

@pytest.mark.parametrize("w_scale", [0.0, 1e-7, 1.0, 20.0])
def test_motion_jacobians_F_and_G(w_scale):
    rng = np.random.default_rng(4)
    for _ in range(3):
        x_v = random_camera(rng, w_scale)
        x_v[Q_SLICE] *= 1.1   # F is defined on R^4; check it off the unit sphere too
        for n in (np.zeros(6), rng.normal(0, 0.2, 6)):
            x_new, F, G = f_and_dfdx_dfdn(x_v, DT, n)
            assert_jacobian(F, fd_jacobian(lambda a: f_and_dfdx_dfdn(a, DT, n)[0], x_v))
            assert_jacobian(G, fd_jacobian(lambda b: f_and_dfdx_dfdn(x_v, DT, b)[0], n))
        x0, F0 = f_and_dfdx(x_v, DT)
        assert np.array_equal(x0, f_and_dfdx_dfdn(x_v, DT)[0]) and np.array_equal(F0, f_and_dfdx_dfdn(x_v, DT)[1])
        assert np.array_equal(dfdn(x_v, DT), f_and_dfdx_dfdn(x_v, DT)[2])


def test_process_noise_is_G_Pn_Gt():
    rng = np.random.default_rng(5)
    cfg = SlamConfig(sigma_a=2.0, sigma_alpha=3.0)
    x_v = random_camera(rng)
    G = dfdn(x_v, DT)
    Pn = noise_covariance(DT, cfg)
    assert np.allclose(np.diag(Pn), [(2 * DT) ** 2] * 3 + [(3 * DT) ** 2] * 3)
    assert np.allclose(process_noise(x_v, DT, cfg), G @ Pn @ G.T)


def test_predict_with_zero_velocities_keeps_mean_and_adds_Q():
    rng = np.random.default_rng(6)
    s, _ = map_state(rng, 4)
    s.x[V_SLICE] = 0.0
    s.x[W_SLICE] = 0.0
    # Zero the velocity rows/columns, so that F P F^T = P and the growth is exactly Q.
    P = s.P.copy()
    P[7:13, :] = 0.0
    P[:, 7:13] = 0.0
    s = State(s.x, P)
    x0, P0 = s.x.copy(), s.P.copy()
    cfg = SlamConfig()
    predict(s, DT, cfg)
    assert np.allclose(s.x, x0, atol=1e-15, rtol=0)
    expected = P0.copy()
    expected[:13, :13] += process_noise(x0[:13], DT, cfg)
    assert np.allclose(s.P, expected, atol=1e-15, rtol=1e-12)


def test_predict_propagates_cross_covariances_and_leaves_features():
    rng = np.random.default_rng(7)
    s, _ = map_state(rng, 3)
    x0, P0 = s.x.copy(), s.P.copy()
    cfg = SlamConfig()
    predict(s, DT, cfg)
    x_new, F = f_and_dfdx(x0[:13], DT)
    Q = process_noise(x0[:13], DT, cfg)
    qn, J = normalise_quaternion_jacobian(x_new[Q_SLICE])
    T = np.eye(13)
    T[3:7, 3:7] = J
    assert np.allclose(s.x[:13], np.r_[x_new[:3], qn, x_new[7:]])
    assert np.allclose(s.P[:13, :13], T @ (F @ P0[:13, :13] @ F.T + Q) @ T.T, atol=1e-15)
    assert np.allclose(s.P[:13, 13:], T @ F @ P0[:13, 13:], atol=1e-15)
    assert np.array_equal(s.P[13:, 13:], P0[13:, 13:])
    assert np.array_equal(s.x[13:], x0[13:])


def test_predict_integrates_constant_velocities_exactly():
    rng = np.random.default_rng(8)
    r0, q0 = rng.normal(size=3), random_quat(rng)
    v, w = np.array([0.3, -0.2, 1.1]), np.array([0.4, 1.5, -0.7])   # w in the camera frame
    s = State.from_camera(np.r_[r0, q0, v, w], np.zeros((13, 13)))
    steps = 90
    for _ in range(steps):
        predict(s, DT)
    t = steps * DT
    assert np.allclose(s.r, r0 + v * t, atol=1e-13)
    # Constant body-frame rate about a fixed axis: R(t) = R0 Rot(w t).
    R_expected = to_scipy(q0).as_matrix() @ Rotation.from_rotvec(w * t).as_matrix()
    assert np.allclose(quat_to_rotation(s.q), R_expected, atol=1e-13)
    assert np.allclose(s.v, v) and np.allclose(s.w, w)


def test_predict_rejects_bad_dt():
    s = State.from_camera(np.r_[np.zeros(3), 1, 0, 0, 0, np.zeros(6)], np.eye(13) * 1e-4)
    for dt in (-0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="dt"):
            predict(s, dt)


# -- measurement model -------------------------------------------------------------------------

def visible_points(cam, x_v, rng, n=6, depth=(1.0, 4.0), margin=30.0) -> np.ndarray:
    """World points that project inside the image (with margin) of the camera x_v."""
    xs = rng.uniform(margin, cam.width - margin, n)
    ys = rng.uniform(margin, cam.height - margin, n)
    out = []
    for u, v in zip(xs, ys):
        lam = rng.uniform(*depth)
        out.append(init_point_from_depth(x_v, [u, v], lam, cam)[0])
    return np.array(out)


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_measurement_jacobians(model):
    cam = CAMERAS[model]
    rng = np.random.default_rng(9)
    for _ in range(4):
        x_v = random_camera(rng)
        Y = visible_points(cam, x_v, rng)
        for y in Y:
            uv, H_x, H_y, valid = h_and_jacobians(x_v, y, cam)
            assert valid and np.isfinite(uv).all()
            assert_jacobian(H_x, fd_jacobian(lambda a: h_and_jacobians(a, y, cam).uv, x_v))
            assert_jacobian(H_y, fd_jacobian(lambda b: h_and_jacobians(x_v, b, cam).uv, y))
            assert np.array_equal(H_x[:, 7:], np.zeros((2, 6)))
            # The projection ignores the quaternion's scale: H_q q = 0.
            assert np.allclose(H_x[:, Q_SLICE] @ x_v[Q_SLICE], 0, atol=1e-9 * np.abs(H_x).max())
        # The vectorised form agrees, and with kinematics.camera.project.
        uv_m, Hx_m, Hy_m, valid_m = h_and_jacobians_many(x_v, Y, cam)
        R_wc = quat_to_rotation(x_v[Q_SLICE])
        assert valid_m.all() and np.allclose(uv_m, project(cam, (Y - x_v[:3]) @ R_wc), atol=1e-9)
        assert np.allclose(Hx_m[0], h_and_jacobians(x_v, Y[0], cam).H_x)


def test_points_behind_the_camera_are_nan_and_flagged():
    x_v = np.r_[np.zeros(3), 1, 0, 0, 0, np.zeros(6)]
    for y in ([0.1, 0.2, -1.0], [0.1, 0.2, 0.0]):
        uv, H_x, H_y, valid = h_and_jacobians(x_v, y, PINHOLE)
        assert not valid and np.isnan(uv).all() and np.isnan(H_x).all() and np.isnan(H_y).all()
    assert h_and_jacobians(x_v, [0.1, 0.2, 1.0], PINHOLE).valid


def test_innovation_covariance_dense():
    rng = np.random.default_rng(10)
    A = rng.normal(size=(5, 5))
    P = A @ A.T
    H = rng.normal(size=(2, 5))
    S = innovation_covariance(P, H, np.eye(2))
    assert np.allclose(S, H @ P @ H.T + np.eye(2)) and np.array_equal(S, S.T)


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_ray_from_pixel_and_init_point_jacobians(model):
    cam = CAMERAS[model]
    rng = np.random.default_rng(11)
    for _ in range(4):
        x_v = random_camera(rng)
        uv = np.array([rng.uniform(20, cam.width - 20), rng.uniform(20, cam.height - 20)])
        lam = rng.uniform(0.5, 5.0)
        origin, d, dd_dx, dd_duv = ray_from_pixel(x_v, uv, cam)
        assert np.allclose(origin, x_v[:3]) and abs(np.linalg.norm(d) - 1) < 1e-12
        assert_jacobian(dd_dx, fd_jacobian(lambda a: ray_from_pixel(a, uv, cam)[1], x_v))
        assert_jacobian(dd_duv, fd_jacobian(lambda b: ray_from_pixel(x_v, b, cam)[1], uv, h=1e-4))

        y, dy_dx, dy_duv, dy_dd = init_point_from_depth(x_v, uv, lam, cam)
        assert np.allclose(y, origin + lam * d)
        # The point projects back to the pixel, at distance lam from the optical centre.
        assert np.allclose(h_and_jacobians(x_v, y, cam).uv, uv, atol=1e-7)
        assert np.isclose(np.linalg.norm(y - x_v[:3]), lam)
        assert_jacobian(dy_dx, fd_jacobian(lambda a: init_point_from_depth(a, uv, lam, cam)[0], x_v))
        assert_jacobian(dy_duv, fd_jacobian(lambda b: init_point_from_depth(x_v, b, lam, cam)[0], uv, h=1e-4))
        assert_jacobian(dy_dd, fd_jacobian(lambda c: init_point_from_depth(x_v, uv, c[0], cam)[0],
                                           np.array([lam]))[:, 0])


# -- state container and guard -----------------------------------------------------------------

def test_add_and_remove_feature():
    rng = np.random.default_rng(12)
    s, _ = map_state(rng, 3)
    x0, P0 = s.x.copy(), s.P.copy()
    B = 0.1 * rng.normal(size=(3, s.n))            # y = B x + noise: a valid joint covariance
    P_yx = B @ s.P
    k = s.add_feature([1.0, 2.0, 3.0], B @ s.P @ B.T + 0.01 * np.eye(3), P_yx)
    assert k == 3 and s.n_features == 4 and np.array_equal(s.feature(3), [1, 2, 3])
    assert np.array_equal(s.P[:-3, -3:], P_yx.T) and np.array_equal(s.P[-3:, :-3], P_yx)
    s.remove_feature(3)
    assert np.array_equal(s.x, x0) and np.array_equal(s.P, P0)
    # Removing a middle feature shifts the later ones down.
    s.remove_feature(1)
    keep = np.r_[0:16, 19:22]
    assert np.array_equal(s.x, x0[keep]) and np.array_equal(s.P, P0[np.ix_(keep, keep)])
    with pytest.raises(IndexError, match="feature 5"):
        s.remove_feature(5)


def test_guard_names_the_problem_and_leaves_state_unchanged():
    rng = np.random.default_rng(13)
    s, _ = map_state(rng, 2)
    x0, P0 = s.x.copy(), s.P.copy()
    with pytest.raises(SlamNumericalError, match="NaN/Inf"):
        s.add_feature([np.nan, 0, 1], np.eye(3), np.zeros((3, s.n)))
    with pytest.raises(SlamNumericalError, match="NaN/Inf.*feature 2"):
        s.add_feature([0, 0, 1], np.full((3, 3), np.inf), np.zeros((3, s.n)))
    with pytest.raises(SlamNumericalError, match="negative variance"):
        s.add_feature([0, 0, 1], -np.eye(3), np.zeros((3, s.n)))
    with pytest.raises(SlamNumericalError, match="not positive semi-definite"):
        s.add_feature([0, 0, 1], np.eye(3), np.full((3, s.n), 10.0))   # |corr| > 1
    assert np.array_equal(s.x, x0) and np.array_equal(s.P, P0)
    P = check_covariance(np.array([[1.0, 0.5], [0.5 + 1e-12, 2.0]]))
    assert np.array_equal(P, P.T)
    with pytest.raises(SlamNumericalError, match="x has NaN/Inf.*camera q"):
        State(np.r_[np.zeros(3), np.nan, 0, 0, 0, np.zeros(6)], np.eye(13))


# -- EKF update --------------------------------------------------------------------------------

def dense_reference_update(state: State, ks, z, cam, R_pix):
    """The textbook EKF update with dense H, as a reference for the compact implementation."""
    n = state.n
    m = len(ks)
    H = np.zeros((2 * m, n))
    h = np.zeros(2 * m)
    for i, k in enumerate(ks):
        uv, H_x, H_y, _ = h_and_jacobians(state.x_v, state.feature(k), cam)
        h[2 * i:2 * i + 2] = uv
        H[2 * i:2 * i + 2, :13] = H_x
        H[2 * i:2 * i + 2, feature_slice(k)] = H_y
    R = np.kron(np.eye(m), R_pix)
    S = innovation_covariance(state.P, H, R)
    K = state.P @ H.T @ np.linalg.inv(S)
    x = state.x + K @ (np.asarray(z).reshape(-1) - h)
    I_KH = np.eye(n) - K @ H
    P = I_KH @ state.P @ I_KH.T + K @ R @ K.T
    qn, J = normalise_quaternion_jacobian(x[Q_SLICE])
    x[Q_SLICE] = qn
    T = np.eye(n)
    T[3:7, 3:7] = J
    return x, T @ P @ T.T, S


@pytest.mark.parametrize("model", ["brown", "fisheye"])
def test_update_matches_dense_reference(model):
    cam = CAMERAS[model]
    rng = np.random.default_rng(14)
    s, Y = map_state(rng, 6)
    ks = [4, 1, 5, 1]   # any order, repeats allowed
    R_pix = np.diag([1.5, 0.8])
    z = np.array([project(cam, ((Y[k] - s.r) @ quat_to_rotation(s.q))[None])[0] for k in ks])
    z += rng.normal(0, 1.0, z.shape)
    x_ref, P_ref, S_ref = dense_reference_update(s, ks, z, cam, R_pix)
    res = update(s, ks, z, cam, R_pix)
    assert np.allclose(res.S, S_ref, rtol=1e-10, atol=1e-10)
    assert np.allclose(s.x, x_ref, rtol=1e-10, atol=1e-12)
    assert np.allclose(s.P, P_ref, rtol=1e-8, atol=1e-14)
    assert abs(np.linalg.norm(s.q) - 1) < 1e-15 and np.array_equal(s.P, s.P.T)
    assert res.nu.shape == (4, 2) and np.isfinite(res.nis)


def test_update_one_and_measurement_order():
    rng = np.random.default_rng(15)
    s, Y = map_state(rng, 5)
    s.P[feature_slice(3), feature_slice(3)] += 1.0 * np.eye(3)   # feature 3 most uncertain
    ks = np.arange(5)
    uv, S, valid = innovation_covariances(s, ks, PINHOLE, 1.0)
    res = update(s.copy(), ks, uv, PINHOLE, 1.0)
    for i in range(5):
        assert np.allclose(S[i], res.S[2 * i:2 * i + 2, 2 * i:2 * i + 2])
    order = measurement_order(s, ks, PINHOLE, 1.0)
    assert order[0] == 3 and sorted(order) == list(ks)
    assert np.all(np.diff([np.linalg.det(S[k]) for k in order]) <= 0)
    # One feature at a time equals the batch update of that one feature.
    s1, s2 = s.copy(), s.copy()
    update_one(s1, 3, uv[3] + [2.0, -1.0], PINHOLE, 1.0)
    update(s2, [3], (uv[3] + [2.0, -1.0])[None], PINHOLE, 1.0)
    assert np.array_equal(s1.x, s2.x) and np.array_equal(s1.P, s2.P)
    # A point behind the camera is refused, and the state is unchanged.
    s.x[feature_slice(0)] = s.r - 2.0 * quat_to_rotation(s.q)[:, 2]
    x0, P0 = s.x.copy(), s.P.copy()
    with pytest.raises(FeatureNotMeasurable, match=r"features \[0\]"):
        update(s, [0, 1], np.zeros((2, 2)), PINHOLE, 1.0)
    assert np.array_equal(s.x, x0) and np.array_equal(s.P, P0)
    assert 0 not in measurement_order(s, ks, PINHOLE, 1.0)


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_add_point_feature_covariance(model):
    cam = CAMERAS[model]
    rng = np.random.default_rng(16)
    s, _ = map_state(rng, 3)
    n = s.n
    P0 = s.P.copy()
    uv, lam, var_d, R_pix = np.array([200.0, 150.0]), 2.5, 0.3**2, np.diag([2.0, 3.0])
    y, J_x, J_uv, J_d = init_point_from_depth(s.x_v, uv, lam, cam)
    k = add_point_feature(s, uv, lam, var_d, R_pix, cam)
    assert k == 3 and np.allclose(s.feature(k), y)
    # The new covariance is A blockdiag(P, R, var_d) A^T for the augmenting map A.
    A = np.zeros((n + 3, n + 3))
    A[:n, :n] = np.eye(n)
    A[n:, :13] = J_x
    A[n:, n:n + 2] = J_uv
    A[n:, n + 2] = J_d
    P_aug = np.zeros((n + 3, n + 3))
    P_aug[:n, :n] = P0
    P_aug[n:n + 2, n:n + 2] = R_pix
    P_aug[n + 2, n + 2] = var_d
    assert np.allclose(s.P, A @ P_aug @ A.T, atol=1e-15)
    with pytest.raises(ValueError, match="depth"):
        add_point_feature(s, uv, -1.0, var_d, R_pix, cam)


# -- consistency -------------------------------------------------------------------------------

SIM_CFG = SlamConfig(sigma_a=0.5, sigma_alpha=0.3, sigma_pixel=1.0)
N_RUNS, N_FRAMES, N_POINTS = 20, 80, 20
SIG_R0, SIG_TH0, SIG_V0, SIG_W0, SIG_Y0 = 0.01, 0.01, 0.05, 0.05, 0.03


def simulate_run(seed: int, sequential: bool, n_frames: int = N_FRAMES) -> dict:
    """One Monte Carlo run: the true camera follows the motion model with impulses drawn from
    the filter's own P_n (sigma_a, sigma_alpha), 20 known points, 1 px pixel noise, predict and
    update every frame. Returns the per-frame position and orientation NEES and checks."""
    rng = np.random.default_rng(seed)
    cam, cfg = PINHOLE, SIM_CFG
    Y = np.column_stack([rng.uniform(-3.0, 3.0, N_POINTS), rng.uniform(-2.0, 2.0, N_POINTS),
                         rng.uniform(3.0, 5.0, N_POINTS)])
    x_true = np.r_[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.1, -0.05, 0.0, 0.0, 0.03, 0.01]

    q_est = quat_multiply(x_true[Q_SLICE], rotvec_to_quat(rng.normal(0, SIG_TH0, 3)))
    x_v = np.r_[x_true[:3] + rng.normal(0, SIG_R0, 3), q_est,
                x_true[V_SLICE] + rng.normal(0, SIG_V0, 3), x_true[W_SLICE] + rng.normal(0, SIG_W0, 3)]
    s = State.from_camera(x_v, camera_covariance(q_est, SIG_R0, SIG_TH0, SIG_V0, SIG_W0))
    for y in Y:
        s.add_feature(y + rng.normal(0, SIG_Y0, 3), SIG_Y0**2 * np.eye(3), np.zeros((3, s.n)))

    Pn_chol = np.sqrt(np.diag(noise_covariance(DT, cfg)))
    nees_r, nees_th, n_seen, min_eig = [], [], [], np.inf
    for frame in range(n_frames):
        x_true = f_and_dfdx_dfdn(x_true, DT, Pn_chol * rng.normal(size=6))[0]
        predict(s, DT, cfg)
        P_cam = (Y - x_true[:3]) @ quat_to_rotation(x_true[Q_SLICE])
        uv_true = project(cam, P_cam)
        seen = np.flatnonzero(in_image(cam, uv_true, margin=10.0))
        z = uv_true[seen] + rng.normal(0, cfg.sigma_pixel, (len(seen), 2))
        if sequential:
            order = measurement_order(s, seen, cam, cfg.R_pix)
            for k in order:
                update_one(s, k, z[np.searchsorted(seen, k)], cam, cfg.R_pix, cfg)
        elif len(seen):
            update(s, seen, z, cam, cfg.R_pix, cfg)
        n_seen.append(len(seen))

        e = x_true[:3] - s.r
        nees_r.append(e @ np.linalg.solve(s.P[R_SLICE, R_SLICE], e))
        # Orientation error in the estimate's local frame, with its 3x3 covariance.
        dth = quat_to_rotvec(quat_multiply([s.q[0], *-s.q[1:]], x_true[Q_SLICE]))
        Tp = 4.0 * tangent_basis(s.q).T      # pseudo-inverse of dq/dtheta
        P_th = Tp @ s.P[Q_SLICE, Q_SLICE] @ Tp.T
        nees_th.append(dth @ np.linalg.solve(P_th, dth))
        assert np.isfinite(s.x).all() and np.isfinite(s.P).all()
        assert np.array_equal(s.P, s.P.T)
        if frame % 10 == 9:
            min_eig = min(min_eig, np.linalg.eigvalsh(reduced_covariance(s))[0])
            lam_full = np.linalg.eigvalsh(s.P)
            assert lam_full[0] > -1e-12 * lam_full[-1]
    return dict(nees_r=np.array(nees_r), nees_th=np.array(nees_th), n_seen=np.array(n_seen),
                min_eig=min_eig)


def chi2_band(dof: int, runs: int) -> tuple[float, float]:
    """95% band of the average of `runs` independent chi-square(dof) NEES values."""
    return chi2.ppf(0.025, dof * runs) / runs, chi2.ppf(0.975, dof * runs) / runs


# The batch update over 20 runs is the consistency test proper; MonoSLAM's sequential updates
# (largest S first) cost ~15 update calls a frame, so they get fewer, shorter runs (a wider band)
# to keep the file fast. (20 x 100 sequential gives the same figures as batch.)
@pytest.mark.parametrize("sequential, n_runs, n_frames",
                         [(False, N_RUNS, N_FRAMES), (True, 5, 40)], ids=["batch", "sequential"])
def test_filter_is_consistent(sequential, n_runs, n_frames):
    runs = [simulate_run(1000 + i, sequential, n_frames) for i in range(n_runs)]
    nees_r = np.array([r["nees_r"] for r in runs])       # (runs, frames)
    nees_th = np.array([r["nees_th"] for r in runs])
    lo, hi = chi2_band(3, n_runs)
    # Every frame's run-average is chi2(3 M) / M if the filter is consistent; averaging over the
    # frames as well only narrows its spread, so the single-frame 95% band is a valid (slightly
    # conservative) band for the overall average.
    avg_r, avg_th = nees_r.mean(), nees_th.mean()
    print(f"\n{'sequential' if sequential else 'batch'}: position NEES {avg_r:.3f}, orientation "
          f"NEES {avg_th:.3f}, 95% band [{lo:.3f}, {hi:.3f}]; frames with run-average in band "
          f"{np.mean((nees_r.mean(0) > lo) & (nees_r.mean(0) < hi)):.0%}; points seen "
          f"{min(r['n_seen'].min() for r in runs)}..{max(r['n_seen'].max() for r in runs)}; "
          f"min eigenvalue of reduced P {min(r['min_eig'] for r in runs):.3g}")
    assert lo < avg_r < hi
    assert lo < avg_th < hi
    # Most frames' run-averages lie in the band too (about 95% expected).
    assert np.mean((nees_r.mean(0) > lo) & (nees_r.mean(0) < hi)) > 0.8
    assert min(r["min_eig"] for r in runs) > 0
    assert min(r["n_seen"].min() for r in runs) >= 5
