"""The feature models (point, inverse depth): measurement Jacobians against central differences
for every lens model, initialisation Jacobians, conversion to a point, the linearity index, and
the state's offset table under additions, removals and conversions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, project, unproject
from runtime.slam.features import FEATURE_DIMS, INVERSE_DEPTH, POINT, inverse_depth
from runtime.slam.filter import add_inverse_depth_feature, add_point_feature, convert_to_point, update
from runtime.slam.measurement import predict
from runtime.slam.quaternion import quat_to_rotation
from runtime.slam.state import CAMERA_DIM, CAMERA_DIM_BIASED, State

CAMERAS = {
    "pinhole": CameraIntrinsics(width=640, height=480, fx=514.7, fy=514.7, cx=319.5, cy=239.5),
    "brown": CameraIntrinsics(width=640, height=480, fx=500.0, fy=505.0, cx=322.0, cy=236.0,
                              model="brown", k1=-0.25, k2=0.08, p1=1e-3, p2=-5e-4, k3=-0.01),
    "fisheye": CameraIntrinsics(width=640, height=480, fx=300.0, fy=302.0, cx=318.0, cy=241.0,
                                model="fisheye", k1=0.05, k2=-0.01, k3=0.003, k4=-0.001),
    "radial-sqrt": CameraIntrinsics(width=320, height=240, fx=195.0, fy=195.0, cx=162.0, cy=125.0,
                                    model="radial-sqrt", kd1=9e-7),
}


def camera_block(rng, cam_dim=CAMERA_DIM):
    q = Rotation.random(random_state=int(rng.integers(2**31))).as_quat()[[3, 0, 1, 2]]
    x = np.concatenate([rng.normal(0, 1, 3), q, rng.normal(0, 0.3, 3), rng.normal(0, 0.3, 3)])
    if cam_dim == CAMERA_DIM_BIASED:
        x = np.concatenate([x, rng.normal(0, 0.01, 3), rng.normal(0, 0.05, 3)])
    return x


def state_with_features(rng, cam, n_points=3, n_inverse=3, cam_dim=CAMERA_DIM):
    """A camera and features in front of it: points and inverse-depth rays started at pixels."""
    x_v = camera_block(rng, cam_dim)
    st = State.from_camera(x_v, np.diag(rng.uniform(1e-4, 1e-2, cam_dim)))
    for _ in range(n_inverse):
        uv = rng.uniform([0.2 * cam.width, 0.2 * cam.height], [0.8 * cam.width, 0.8 * cam.height])
        k = add_inverse_depth_feature(st, uv, cam, 1.0, 0.5, 1.0)
        st.x[st.feature_slice(k)][5] = rng.uniform(0.3, 1.5)      # some depth
        st.x[st.feature_slice(k)][:3] += rng.normal(0, 0.05, 3)   # seen from elsewhere
    for _ in range(n_points):
        uv = rng.uniform([0.2 * cam.width, 0.2 * cam.height], [0.8 * cam.width, 0.8 * cam.height])
        add_point_feature(st, uv, rng.uniform(0.7, 3.0), 0.01, 1.0, cam)
    return st


def numeric_jacobian(f, x, eps=1e-6):
    x = np.asarray(x, float)
    cols = []
    for i in range(len(x)):
        d = np.zeros_like(x)
        d[i] = eps
        cols.append((f(x + d) - f(x - d)) / (2 * eps))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("cam_dim", [CAMERA_DIM, CAMERA_DIM_BIASED])
def test_measurement_jacobians_match_central_differences(name, cam_dim):
    cam = CAMERAS[name]
    rng = np.random.default_rng(7)
    st = state_with_features(rng, cam, cam_dim=cam_dim)
    ks = np.arange(st.n_features)
    pred = predict(st, ks, cam)
    assert pred.valid.all()
    for i, k in enumerate(ks):
        sl = st.feature_slice(k)

        def h(x):
            return predict(st, [k], cam, x=x).uv[0]

        J = numeric_jacobian(h, st.x)
        np.testing.assert_allclose(pred.H_c[i], J[:, :7], rtol=1e-5, atol=1e-4)
        d = FEATURE_DIMS[st.kinds[k]]
        np.testing.assert_allclose(pred.H_f[i][:, :d], J[:, sl], rtol=1e-5, atol=1e-4)
        # The measurement does not see v, w, the biases or any other feature.
        others = np.ones(st.n, bool)
        others[:7] = False
        others[sl] = False
        assert np.abs(J[:, others]).max() < 1e-6


def test_inverse_depth_predicts_the_point_it_stands_for():
    """A ray started at a pixel, with the true inverse depth, projects where the true point does
    from any other camera (an independent projection through kinematics.camera)."""
    cam = CAMERAS["brown"]
    rng = np.random.default_rng(3)
    st = State.from_camera(camera_block(rng), np.eye(CAMERA_DIM) * 1e-4)
    R0 = Rotation.from_quat(st.q[[1, 2, 3, 0]]).as_matrix()
    X = st.r + R0 @ np.array([0.2, -0.1, 2.0])               # a point 2 m ahead
    uv0 = project(cam, ((X - st.r) @ R0)[None])[0]
    k = add_inverse_depth_feature(st, uv0, cam, 1.0, 0.5, 1.0)
    st.x[st.feature_slice(k)][5] = 1.0 / np.linalg.norm(X - st.r)
    np.testing.assert_allclose(inverse_depth.world_point(st.feature(k), st.anchors[k]), X, atol=1e-9)
    # Move the camera and compare.
    st.x[:3] += [0.3, 0.1, -0.2]
    st.x[3:7] = Rotation.from_matrix(R0 @ Rotation.from_euler("xyz", [0.05, -0.1, 0.02]).as_matrix()).as_quat()[[3, 0, 1, 2]]
    R1 = Rotation.from_quat(st.q[[1, 2, 3, 0]]).as_matrix()
    uv1 = project(cam, ((X - st.r) @ R1)[None])[0]
    np.testing.assert_allclose(predict(st, [k], cam).uv[0], uv1, atol=1e-6)


@pytest.mark.parametrize("name", ["pinhole", "fisheye"])
def test_inverse_depth_initialisation_jacobians(name):
    cam = CAMERAS[name]
    rng = np.random.default_rng(11)
    x_v = camera_block(rng)
    uv = np.array([0.3 * cam.width, 0.6 * cam.height])
    y, A, J_x, J_uv = inverse_depth.init_from_pixel(x_v, uv, cam, 1.0)

    h = unproject(cam, uv[None])[0]

    def angles_world(xv):
        # The anchor is held fixed at the current estimate, as in the filter; R(q) is the
        # homogeneous formula the filter differentiates.
        th, ph, _ = inverse_depth.angles_and_jacobian(A.T @ quat_to_rotation(xv[3:7]) @ h)
        return np.r_[xv[:3], th, ph, 1.0]

    J = numeric_jacobian(angles_world, x_v)
    np.testing.assert_allclose(J_x[:, :7], J[:, :7], rtol=1e-5, atol=1e-6)
    J2 = numeric_jacobian(lambda p: inverse_depth.init_from_pixel(x_v, p, cam, 1.0)[0], uv)
    np.testing.assert_allclose(J_uv, J2, rtol=1e-5, atol=1e-7)


def test_to_point_jacobian_and_conversion_keeps_the_prediction():
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(5)
    st = state_with_features(rng, cam, n_points=2, n_inverse=3)
    k = int(np.flatnonzero(st.kinds == INVERSE_DEPTH)[1])
    y, A = st.feature(k).copy(), st.anchors[k]
    p, J = inverse_depth.to_point(y, A)
    np.testing.assert_allclose(J, numeric_jacobian(lambda v: inverse_depth.to_point(v, A)[0], y), rtol=1e-6, atol=1e-8)
    before = predict(st, np.arange(st.n_features), cam).uv
    n_before = st.n
    convert_to_point(st, k)
    assert st.kinds[k] == POINT and st.n == n_before - 3
    np.testing.assert_allclose(predict(st, np.arange(st.n_features), cam).uv, before, atol=1e-8)
    # The offset table follows: every feature's parameters are where its kind says.
    assert list(st.starts) == list(CAMERA_DIM + np.concatenate([[0], np.cumsum(FEATURE_DIMS[st.kinds])[:-1]]))
    # The converted point's covariance is J P_yy J^T.
    st.guard("test")


def test_linearity_index_falls_with_parallax():
    """A ray seen again from the same place has no depth information (large index); seen from a
    camera far to the side with a small sigma_rho, the index is small."""
    y = np.array([0, 0, 0, 0.0, 0.0, 0.5])           # 2 m along the anchor's z
    A = np.eye(3)
    same = inverse_depth.linearity_index(y, A, 0.5, np.zeros(3))
    side = inverse_depth.linearity_index(y, A, 0.01, np.array([1.0, 0, 0]))
    assert same > 1.0 and side < 0.1


def test_remove_features_keeps_the_table():
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(2)
    st = state_with_features(rng, cam, n_points=3, n_inverse=3)
    params = [st.feature(k).copy() for k in range(st.n_features)]
    st.remove_features([1, 4])
    kept = [params[k] for k in range(6) if k not in (1, 4)]
    for k, p in enumerate(kept):
        np.testing.assert_array_equal(st.feature(k), p)


def test_update_moves_towards_the_measurement_and_shrinks_covariance():
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(9)
    st = state_with_features(rng, cam, n_points=4, n_inverse=2)
    ks = np.arange(st.n_features)
    pred = predict(st, ks, cam)
    z = pred.uv + rng.normal(0, 3.0, pred.uv.shape)
    P0 = st.P.copy()
    res = update(st, ks, z, cam, 1.0)
    after = predict(st, ks, cam).uv
    assert np.linalg.norm(after - z) < np.linalg.norm(pred.uv - z)
    assert np.all(np.diag(st.P) <= np.diag(P0) + 1e-12)
    assert res.nis > 0


def test_scene_prior_is_the_median_inverse_depth_seen_from_the_camera():
    """Points 0.5-10 m from the camera centre (not the origin): the prior is the median of their
    inverse distances with the configured relative width, or (a deep scene) the points' own
    spread of inverse distances where that is wider; fewer than five finite points (a NaN one
    does not count) leave the configured prior."""
    rng = np.random.default_rng(3)
    r = np.array([0.3, -0.2, 0.1])
    dirs = rng.normal(size=(6, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    d = np.array([0.5, 0.8, 2.0, 4.0, 5.0, 10.0])           # inverse: 2, 1.25, 0.5, 0.25, 0.2, 0.1
    Y = r + dirs * d[:, None]
    rho, sigma = inverse_depth.scene_prior(Y, r, 1.0, 0.5, spread=False)
    assert rho == pytest.approx(0.375) and sigma == pytest.approx(0.1875)
    assert inverse_depth.scene_prior(Y, r, 2.0, 0.5, spread=False) == pytest.approx((0.375, 0.09375))
    # The 16th and 84th percentiles of the inverse distances (linear between the sorted six):
    # 0.1 + 0.8 * 0.1 = 0.18 and 1.25 + 0.2 * 0.75 = 1.4; half their range is wider than 0.1875.
    assert inverse_depth.scene_prior(Y, r, 1.0, 0.5) == pytest.approx((0.375, 0.61))
    # A shallow scene (2.0-2.2 m) keeps the relative width: its spread is narrower.
    shallow = r + dirs * np.linspace(2.0, 2.2, 6)[:, None]
    rho, sigma = inverse_depth.scene_prior(shallow, r, 1.0, 0.5)
    assert sigma == pytest.approx(0.5 * rho) and rho == pytest.approx(1 / 2.1, rel=1e-3)
    # A relative width of its own (the map's: a new feature may be nearer than any matched one).
    assert inverse_depth.scene_prior(Y, r, 1.0, 0.5, spread=False, relative_width=2.0) == pytest.approx((0.375, 0.75))
    assert inverse_depth.scene_prior(Y, r, 1.0, 0.5, relative_width=2.0) == pytest.approx((0.375, 0.75))
    few = Y[:5].copy()
    few[0] = np.nan
    assert inverse_depth.scene_prior(few, r, 1.0, 0.5) == (1.0, 0.5)
    assert inverse_depth.scene_prior(np.zeros((0, 3)), r, 1.0, 0.5) == (1.0, 0.5)
