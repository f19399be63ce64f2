"""runtime.slam's core: quaternion maths, the state layout and its per-feature offset table
(through additions, removals and conversions, against a dense reference), the covariance
guard's messages, the motion model (Jacobians against central differences, the prediction
against dense F P F^T + Q, constant velocities integrated exactly), and the measurement
helpers' Jacobians."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import slam_testing as st
from kinematics.camera import project
from kinematics.transforms import matrix_from_quat_wxyz, so3_log
from runtime.slam.config import SlamConfig
from runtime.slam.features import FEATURE_DIMS, INVERSE_DEPTH, POINT, inverse_depth
from runtime.slam.filter import add_inverse_depth_feature, add_point_feature, convert_to_point
from runtime.slam.measurement import init_point_from_depth, predict as predict_h, predict_points, ray_from_pixel
from runtime.slam.motion import (
    f_and_dfdx,
    f_and_dfdx_dfdn,
    noise_covariance,
    normalise_quaternion,
    predict,
    process_noise,
)
from runtime.slam.quaternion import (
    dq_dtheta_right,
    normalise_quaternion_jacobian,
    quat_from_rotation,
    quat_multiply,
    quat_to_rotation,
    rotation_derivatives,
    rotvec_to_quat,
    rotvec_to_quat_jacobian,
)
from runtime.slam.state import (
    CAMERA_DIM,
    CAMERA_DIM_BIASED,
    CAMERA_DIM_TIMED,
    Q_SLICE,
    SlamNumericalError,
    State,
    check_covariance,
    feature_starts,
    state_size,
)

DT = 1.0 / 30.0
CFG = SlamConfig()
CAMERAS = st.CAMERAS
BOTH = [CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_TIMED]   # every camera block


# -- quaternions -------------------------------------------------------------------------------

@pytest.mark.parametrize("angle", [0.0, 1e-9, 5e-4, 2e-3, 0.7, 3.0])
def test_rotvec_to_quat_and_jacobian(angle):
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    theta = angle * axis / np.linalg.norm(axis)
    q, J = rotvec_to_quat_jacobian(theta)
    assert np.allclose(st.to_scipy(q).as_matrix(), Rotation.from_rotvec(theta).as_matrix(), atol=1e-15)
    assert abs(np.linalg.norm(q) - 1) < 1e-15
    st.assert_jacobian(J, st.fd_jacobian(rotvec_to_quat, theta))
    if angle == 0.0:
        assert np.array_equal(J, np.vstack([np.zeros(3), 0.5 * np.eye(3)]))
    assert np.allclose(so3_log(matrix_from_quat_wxyz(q)), theta, atol=1e-12)


def test_quaternion_convention_matches_scipy():
    rng = np.random.default_rng(2)
    for _ in range(5):
        q, p = st.random_quat(rng), st.random_quat(rng)
        assert np.allclose(quat_to_rotation(q), st.to_scipy(q).as_matrix(), atol=1e-15)
        # Hamilton product, p applied first: R(q * p) = R(q) R(p)
        assert np.allclose(st.to_scipy(quat_multiply(q, p)).as_matrix(), (st.to_scipy(q) * st.to_scipy(p)).as_matrix(),
                           atol=1e-15)
        R = st.to_scipy(q).as_matrix()
        assert np.allclose(quat_to_rotation(quat_from_rotation(R)), R, atol=1e-14)


def test_rotation_derivatives_and_normalisation_jacobian():
    rng = np.random.default_rng(3)
    q = 1.3 * st.random_quat(rng) + rng.normal(0, 0.1, 4)      # off the unit sphere: the formula is on R^4
    st.assert_jacobian(np.moveaxis(rotation_derivatives(q), 0, -1), st.fd_jacobian(quat_to_rotation, q))
    qn, J = normalise_quaternion_jacobian(q)
    assert abs(np.linalg.norm(qn) - 1) < 1e-15
    st.assert_jacobian(J, st.fd_jacobian(lambda a: a / np.linalg.norm(a), q))
    _, J1 = normalise_quaternion_jacobian(qn)
    assert np.allclose(J1 @ qn, 0, atol=1e-15)                # at |q| = 1 it projects out q itself
    with pytest.raises(ValueError, match="cannot normalise"):
        normalise_quaternion_jacobian(np.zeros(4))


def test_dq_dtheta_right_is_the_small_rotation_in_the_camera_frame():
    rng = np.random.default_rng(4)
    q = st.random_quat(rng)
    J_fd = st.fd_jacobian(lambda t: quat_multiply(q, rotvec_to_quat(t)), np.zeros(3))
    st.assert_jacobian(dq_dtheta_right(q), J_fd)


# -- the layout and the offset table -----------------------------------------------------------

def test_layout_of_a_mixed_state():
    kinds = np.array([INVERSE_DEPTH, POINT, POINT, INVERSE_DEPTH, POINT])
    for cd in BOTH:
        starts = feature_starts(cd, kinds)
        assert starts.tolist() == [cd, cd + 6, cd + 9, cd + 12, cd + 18]
        assert state_size(cd, kinds) == cd + 21
    assert feature_starts(CAMERA_DIM, []).tolist() == [] and state_size(CAMERA_DIM, []) == 13
    rng = np.random.default_rng(5)
    x = np.r_[st.random_camera(rng, cam_dim=19), np.arange(21.0)]
    s = State(x, np.eye(40) * 1e-2, CAMERA_DIM_BIASED, kinds)
    assert s.has_biases and s.n_features == 5 and s.n == 40
    assert np.array_equal(s.feature(0), np.arange(6.0)) and np.array_equal(s.feature(2), [9.0, 10.0, 11.0])
    assert np.array_equal(s.feature(4), [18.0, 19.0, 20.0])
    assert np.array_equal(s.b_g, x[13:16]) and np.array_equal(s.b_a, x[16:19])
    assert s.describe(14) == "camera b_g" and s.describe(17) == "camera b_a" and s.describe(4) == "camera q"
    assert s.describe(19) == "feature 0 (inverse-depth)" and s.describe(29) == "feature 2 (point)"
    assert s.describe(39) == "feature 4 (point)"
    s13 = State(np.r_[x[:13], np.arange(21.0)], np.eye(34) * 1e-2, CAMERA_DIM, kinds)
    assert not s13.has_biases and np.array_equal(s13.b_g, np.zeros(3)) and s13.describe(13) == "feature 0 (inverse-depth)"
    with pytest.raises(IndexError, match="feature 5 does not exist"):
        s.feature(5)


def test_state_refuses_inconsistent_layouts():
    x = np.r_[0, 0, 0, 1.0, 0, 0, 0, np.zeros(6)]
    with pytest.raises(ValueError, match="13 numbers, 19 with IMU biases, 20 with the IMU.s clock offset as well or 24 with the map.s scale and gravity; got 14"):
        State(np.r_[x, 0.0], np.eye(14), cam_dim=14)
    with pytest.raises(ValueError, match="has 16 numbers, got 15"):
        State(np.r_[x, 0, 0], np.eye(15), CAMERA_DIM, [POINT])
    with pytest.raises(ValueError, match="P must have shape"):
        State(np.r_[x, 0, 0, 0], np.eye(15), CAMERA_DIM, [POINT])
    with pytest.raises(ValueError, match="unknown feature kinds"):
        State(np.r_[x, 0, 0, 0], np.eye(16), CAMERA_DIM, [7])


class DenseMaster:
    """An independent record of a state under map management: every coordinate ever added
    keeps its place in one dense (x, P); removals only mark features dead, a conversion appends
    the new coordinates ``y' = f(y)`` with ``P' = T P T^T`` on the whole master and marks the old
    ones dead. The live state must equal the master restricted to the live features in order."""

    def __init__(self, state: State):
        self.x = state.x.copy()
        self.P = state.P.copy()
        self.cam = list(range(state.cam_dim))
        self.live: list[tuple[int, list[int]]] = []          # (kind, master indices) in state order

    def live_index(self) -> np.ndarray:
        return np.array(self.cam + [i for _, idx in self.live for i in idx], int)

    def add(self, kind, y, P_yy, P_yx):
        n0 = len(self.x)
        d = len(y)
        live = self.live_index()
        P = np.zeros((n0 + d, n0 + d))
        P[:n0, :n0] = self.P
        P[n0:, live] = P_yx
        P[live, n0:] = P_yx.T
        P[n0:, n0:] = P_yy
        self.x, self.P = np.r_[self.x, y], P
        self.live.append((kind, list(range(n0, n0 + d))))

    def remove(self, ks):
        self.live = [f for k, f in enumerate(self.live) if k not in set(ks)]

    def convert(self, k, kind, y_new, J):
        _, idx = self.live[k]
        n0 = len(self.x)
        d = len(y_new)
        T = np.zeros((n0 + d, n0))
        T[:n0, :n0] = np.eye(n0)
        T[n0:, idx] = J
        self.x, self.P = np.r_[self.x, y_new], T @ self.P @ T.T
        self.live[k] = (kind, list(range(n0, n0 + d)))

    def check(self, state: State):
        live = self.live_index()
        assert state.kinds.tolist() == [kd for kd, _ in self.live]
        assert state.n == len(live)
        np.testing.assert_allclose(state.x, self.x[live], rtol=0, atol=1e-12)
        st.assert_close(state.P, self.P[np.ix_(live, live)], 1e-12)
        for k, (kd, idx) in enumerate(self.live):
            np.testing.assert_allclose(state.feature(k), self.x[idx], rtol=0, atol=1e-12)
            assert state.feature_slice(k).stop - state.feature_slice(k).start == FEATURE_DIMS[kd]


@pytest.mark.parametrize("cam_dim", BOTH)
def test_offset_table_through_additions_removals_and_conversions(cam_dim):
    """Random map management on a mixed state: after every addition (either kind), removal (of
    one or several features, anywhere), conversion (State.convert_feature and
    filter.convert_to_point) and removal with conversion in one rebuild (State.edit_features),
    every feature's parameters and every covariance block are those of the dense master
    record."""
    CAMERAS["pinhole"]
    rng = np.random.default_rng(6 + cam_dim)
    x_v = st.random_camera(rng, cam_dim=cam_dim)
    s = State.from_camera(x_v, st.camera_covariance(x_v[Q_SLICE], 0.01, 0.01, 0.1, 0.1, cam_dim))
    ref = DenseMaster(s)
    ops = {"add": 0, "remove": 0, "convert": 0, "edit": 0}
    mixed = 0
    for step in range(100):
        op = rng.choice(["add", "add", "remove", "convert", "edit"]) if s.n_features > 2 else "add"
        if op == "add":
            kind = int(rng.integers(2))
            d = int(FEATURE_DIMS[kind])
            B = 0.1 * rng.normal(size=(d, s.n))              # y = B x + noise: a valid joint covariance
            if kind == INVERSE_DEPTH:
                y = np.r_[s.r + rng.normal(0, 0.05, 3), rng.uniform(-0.5, 0.5, 2), rng.uniform(0.2, 2.0)]
            else:
                y = s.r + rng.normal(0, 2.0, 3)
            P_yy, P_yx = B @ s.P @ B.T + 1e-3 * np.eye(d), B @ s.P
            k = s.add_feature(kind, y, P_yy, P_yx, anchor=st.to_scipy(st.random_quat(rng)).as_matrix(), check_psd=True)
            assert k == s.n_features - 1
            ref.add(kind, y, P_yy, P_yx)
        elif op == "remove":
            ks = rng.choice(s.n_features, size=int(rng.integers(1, 3)), replace=False).tolist()
            s.remove_features(ks)
            ref.remove(ks)
        elif op == "edit":
            ids = np.flatnonzero(s.kinds == INVERSE_DEPTH)
            if not len(ids) or s.n_features - len(ids) < 1:
                continue
            ks = rng.choice(ids, size=int(rng.integers(1, min(2, len(ids)) + 1)), replace=False).tolist()
            others = np.setdiff1d(np.arange(s.n_features), ks)
            gone = rng.choice(others, size=int(rng.integers(1, min(2, len(others)) + 1)), replace=False).tolist()
            conv = [inverse_depth.to_point(s.feature(k), s.anchors[k]) for k in ks]
            s.edit_features(remove=gone, convert=ks, kind=POINT, ys_new=[p for p, _ in conv], Js=[J for _, J in conv])
            for k, (p, J) in zip(ks, conv):
                ref.convert(k, POINT, p, J)
            ref.remove(gone)
        else:
            ids = np.flatnonzero(s.kinds == INVERSE_DEPTH)
            if not len(ids):
                continue
            if len(ids) >= 2 and step % 3 == 0:          # several at once: their joint block too
                ks = rng.choice(ids, size=int(rng.integers(2, len(ids) + 1)), replace=False).tolist()
                conv = [inverse_depth.to_point(s.feature(k), s.anchors[k]) for k in ks]
                convert_to_point(s, ks)
                for k, (p, J) in zip(ks, conv):
                    ref.convert(k, POINT, p, J)
                ops[op] += 1
                ref.check(s)
                continue
            k = int(rng.choice(ids))
            p, J = inverse_depth.to_point(s.feature(k), s.anchors[k])
            if step % 2:
                convert_to_point(s, k)
            else:
                s.convert_feature(k, POINT, p, J)
            ref.convert(k, POINT, p, J)
        ops[op] += 1
        ref.check(s)
        assert s.starts.tolist() == feature_starts(cam_dim, s.kinds).tolist()
        assert len(s.anchors) == s.n_features
        mixed += set(s.kinds.tolist()) == {POINT, INVERSE_DEPTH}
    assert min(ops.values()) >= 5 and mixed >= 20, (ops, mixed)
    s.guard("end", check_psd=True)


def test_conversion_keeps_the_anchor_order_and_refuses_bad_shapes():
    cam = CAMERAS["brown"]
    rng = np.random.default_rng(7)
    x_v = st.random_camera(rng)
    s = State.from_camera(x_v, st.camera_covariance(x_v[Q_SLICE], 0.01, 0.01, 0.1, 0.1))
    for uv in ([200.0, 150.0], [400.0, 300.0], [320.0, 100.0]):
        add_inverse_depth_feature(s, uv, cam, 0.8, 0.3, 1.0)
    anchors = s.anchors.copy()
    convert_to_point(s, 1)
    assert s.kinds.tolist() == [INVERSE_DEPTH, POINT, INVERSE_DEPTH]
    assert np.array_equal(s.anchors[0], anchors[0]) and np.array_equal(s.anchors[2], anchors[2])
    with pytest.raises(ValueError, match="not an inverse-depth one"):
        convert_to_point(s, 1)
    with pytest.raises(ValueError, match="J must be"):
        s.convert_feature(0, POINT, np.zeros(3), np.zeros((3, 3)))


# -- the guard ---------------------------------------------------------------------------------

def guarded_state(rng) -> State:
    cam = CAMERAS["pinhole"]
    x_v = st.random_camera(rng, cam_dim=CAMERA_DIM_BIASED)
    s = State.from_camera(x_v, st.camera_covariance(x_v[Q_SLICE], 0.01, 0.01, 0.1, 0.1, CAMERA_DIM_BIASED))
    add_inverse_depth_feature(s, [300.0, 200.0], cam, 1.0, 0.5, 1.0)
    add_point_feature(s, [100.0, 100.0], 2.0, 0.01, 1.0, cam)
    return s


def test_guard_names_the_problem_and_leaves_the_state_unchanged():
    rng = np.random.default_rng(8)
    s = guarded_state(rng)
    x0, P0, kinds0 = s.x.copy(), s.P.copy(), s.kinds.copy()
    with pytest.raises(SlamNumericalError, match=r"x has NaN/Inf after add_feature at indices \[28\]"):
        s.add_feature(POINT, [np.nan, 0, 1], np.eye(3), np.zeros((3, s.n)))
    with pytest.raises(SlamNumericalError, match=r"P has NaN/Inf after add_feature, first at \(28, 28\)"):
        s.add_feature(POINT, [0, 0, 1], np.full((3, 3), np.inf), np.zeros((3, s.n)))
    with pytest.raises(SlamNumericalError, match="negative variance"):
        s.add_feature(POINT, [0, 0, 1], -np.eye(3), np.zeros((3, s.n)))
    with pytest.raises(SlamNumericalError, match="not positive semi-definite"):
        s.add_feature(POINT, [0, 0, 1], np.eye(3), np.full((3, s.n), 10.0), check_psd=True)   # |corr| > 1
    with pytest.raises(ValueError, match=r"inverse-depth feature needs y \(6,\)"):
        s.add_feature(INVERSE_DEPTH, [0, 0, 1], np.eye(3), np.zeros((3, s.n)))
    assert np.array_equal(s.x, x0) and np.array_equal(s.P, P0) and np.array_equal(s.kinds, kinds0)
    with pytest.raises(SlamNumericalError, match=r"x has NaN/Inf after construction.*camera q"):
        State(np.r_[np.zeros(3), np.nan, 0, 0, 0, np.zeros(6)], np.eye(13))
    with pytest.raises(SlamNumericalError, match=r"P has NaN/Inf.*camera b_a"):
        bad = s.P.copy()
        bad[17, 17] = np.nan
        State(s.x, bad, s.cam_dim, s.kinds, s.anchors)


def test_guard_names_the_new_feature():
    s = guarded_state(np.random.default_rng(8))
    with pytest.raises(SlamNumericalError, match=r"NaN/Inf.*feature 2"):
        s.add_feature(POINT, [np.nan, 0, 1], np.eye(3), np.zeros((3, s.n)))
    with pytest.raises(SlamNumericalError, match=r"NaN/Inf.*feature 2"):
        s.add_feature(POINT, [0, 0, 1], np.full((3, 3), np.inf), np.zeros((3, s.n)))


def test_check_covariance():
    P = np.array([[1.0, 0.5], [0.5 + 1e-12, 2.0]])
    out = check_covariance(P)
    assert np.array_equal(out, out.T) and out[0, 1] == 0.5 * (1.0 + 1e-12)
    sym = np.array([[2.0, 0.3], [0.3, 1.0]])
    assert check_covariance(sym) is sym                    # nothing to symmetrise
    P = np.eye(4)
    P[1, 2] = P[2, 1] = np.inf
    with pytest.raises(SlamNumericalError, match=r"NaN/Inf.*first at \(1, 2\)"):
        check_covariance(P)
    with pytest.raises(SlamNumericalError, match="must be square"):
        check_covariance(np.eye(3)[:2])
    # The quaternion's norm direction is an exact null direction: rounding below it is accepted,
    # a real negative eigenvalue is not.
    q = st.random_quat(np.random.default_rng(9))
    Pq = np.eye(4) - np.outer(q, q)
    check_covariance(Pq - 1e-13 * np.outer(q, q))
    with pytest.raises(SlamNumericalError, match=r"smallest eigenvalue -0.001"):
        check_covariance(Pq - 1e-3 * np.outer(q, q))
    check_covariance(Pq - 1e-3 * np.outer(q, q), check_psd=False)


# -- motion model ------------------------------------------------------------------------------

@pytest.mark.parametrize("cam_dim", BOTH)
@pytest.mark.parametrize("w_scale", [0.0, 1e-7, 1.0, 20.0])
def test_motion_jacobians_F_and_G(w_scale, cam_dim):
    rng = np.random.default_rng(10)
    for _ in range(3):
        x_v = st.random_camera(rng, w_scale, cam_dim)
        x_v[Q_SLICE] *= 1.1   # F is defined on R^4; check it off the unit sphere too
        for n in (np.zeros(6), rng.normal(0, 0.2, 6)):
            x_new, F, G = f_and_dfdx_dfdn(x_v, DT, n)
            assert F.shape == (cam_dim, cam_dim) and G.shape == (cam_dim, 6)
            st.assert_jacobian(F, st.fd_jacobian(lambda a: f_and_dfdx_dfdn(a, DT, n)[0], x_v))
            st.assert_jacobian(G, st.fd_jacobian(lambda b: f_and_dfdx_dfdn(x_v, DT, b)[0], n))
            assert np.array_equal(x_new[13:], x_v[13:])        # the biases do not move in the prediction
        x0, F0 = f_and_dfdx(x_v, DT)
        assert np.array_equal(x0, f_and_dfdx_dfdn(x_v, DT)[0]) and np.array_equal(F0, f_and_dfdx_dfdn(x_v, DT)[1])


@pytest.mark.parametrize("cam_dim", BOTH)
def test_process_noise_is_G_Pn_Gt_plus_the_bias_walks(cam_dim):
    rng = np.random.default_rng(11)
    cfg = SlamConfig(sigma_a=2.0, sigma_alpha=3.0, gyro_bias_walk=1e-3, accel_bias_walk=2e-2, time_offset_walk=3e-4)
    x_v = st.random_camera(rng, cam_dim=cam_dim)
    G = f_and_dfdx_dfdn(x_v, DT)[2]
    Pn = noise_covariance(DT, cfg)
    t0 = cfg.motion.motion_noise_interval
    assert np.allclose(np.diag(Pn), [4 * DT * t0] * 3 + [9 * DT * t0] * 3)
    assert np.allclose(np.diag(noise_covariance(t0, cfg)), [(2 * t0) ** 2] * 3 + [(3 * t0) ** 2] * 3)   # MonoSLAM's
    walks = np.zeros((cam_dim, cam_dim))
    if cam_dim >= CAMERA_DIM_BIASED:
        walks[13:16, 13:16] = np.eye(3) * 1e-6 * DT
        walks[16:19, 16:19] = np.eye(3) * 4e-4 * DT
    if cam_dim == CAMERA_DIM_TIMED:
        walks[19, 19] = 9e-8 * DT
    np.testing.assert_allclose(process_noise(x_v, DT, cfg), G @ Pn @ G.T + walks, rtol=1e-12, atol=1e-18)


def mixed_state(rng, cam_dim=CAMERA_DIM, n_points=4, n_inverse=3, cam=None) -> State:
    """A camera and features of both kinds in front of it, with a random full covariance."""
    cam = cam or CAMERAS["pinhole"]
    x_v = st.random_camera(rng, 0.5, cam_dim)
    s = State.from_camera(x_v, np.eye(cam_dim) * 1e-4)
    for i in range(n_points + n_inverse):
        uv = rng.uniform([0.15 * cam.width, 0.15 * cam.height], [0.85 * cam.width, 0.85 * cam.height])
        if i < n_inverse:
            k = add_inverse_depth_feature(s, uv, cam, 1.0, 0.5, 1.0)
            s.x[s.feature_slice(k)][5] = rng.uniform(0.3, 1.5)
        else:
            add_point_feature(s, uv, rng.uniform(0.7, 3.0), 0.01, 1.0, cam)
    s.P = st.random_covariance(rng, s.n, s.q)
    return s


def dense_prediction(s: State, dt, cfg):
    """The prediction with dense matrices over the whole state."""
    cd = s.cam_dim
    x_new, F, G = f_and_dfdx_dfdn(s.x[:cd], dt)
    Fx = np.eye(s.n)
    Fx[:cd, :cd] = F
    Q = np.zeros((s.n, s.n))
    Q[:cd, :cd] = process_noise(s.x[:cd], dt, cfg)
    P = Fx @ s.P @ Fx.T + Q
    qn, J = normalise_quaternion_jacobian(x_new[Q_SLICE])
    T = np.eye(s.n)
    T[Q_SLICE, Q_SLICE] = J
    x = s.x.copy()
    x[:cd] = x_new
    x[Q_SLICE] = qn
    return x, T @ P @ T.T


@pytest.mark.parametrize("cam_dim", BOTH)
def test_predict_equals_the_dense_prediction_and_leaves_the_features(cam_dim):
    rng = np.random.default_rng(12)
    s = mixed_state(rng, cam_dim)
    x0, P0 = s.x.copy(), s.P.copy()
    x_ref, P_ref = dense_prediction(s, DT, CFG)
    predict(s, DT, CFG)
    st.assert_close(s.x, x_ref, 1e-14)
    st.assert_close(s.P, P_ref, 1e-12)
    assert np.array_equal(s.x[cam_dim:], x0[cam_dim:]) and np.array_equal(s.P[cam_dim:, cam_dim:], P0[cam_dim:, cam_dim:])
    assert np.array_equal(s.P, s.P.T)          # written exactly symmetric
    assert abs(np.linalg.norm(s.q) - 1) < 1e-15
    # A lost track's noise gain scales the impulses' variance by its square.
    s1, s2 = State(x0, P0, cam_dim, s.kinds, s.anchors), State(x0, P0, cam_dim, s.kinds, s.anchors)
    predict(s1, DT, CFG, noise_gain=2.0)
    predict(s2, DT, SlamConfig(sigma_a=2 * CFG.motion.sigma_a, sigma_alpha=2 * CFG.motion.sigma_alpha))
    st.assert_close(s1.P[:13, :13], s2.P[:13, :13], 1e-12)


def test_a_long_step_takes_the_variance_of_the_steps_it_spans():
    """The impulses are white accelerations integrated over the step: one step over three
    frames' time (two frames dropped) leaves the velocities as uncertain as three steps do, not
    three times more (``(sigma dt)^2`` would), so a gap does not grow the search ellipses past
    searching."""
    rng = np.random.default_rng(14)
    x_v = st.random_camera(rng, 0.5)
    P0 = np.diag(np.r_[np.full(3, 1e-6), np.full(4, 1e-8), np.full(3, 1e-4), np.full(3, 1e-4)])
    one, three = State.from_camera(x_v, P0.copy()), State.from_camera(x_v.copy(), P0.copy())
    predict(one, 3 * DT, CFG)
    for _ in range(3):
        predict(three, DT, CFG)
    st.assert_close(np.diag(one.P)[7:13], np.diag(three.P)[7:13], 1e-9)
    added = np.diag(one.P)[7:10] - 1e-4
    assert np.allclose(added, CFG.motion.sigma_a**2 * 3 * DT * CFG.motion.motion_noise_interval)


def test_predict_integrates_constant_velocities_exactly():
    rng = np.random.default_rng(13)
    for cam_dim in BOTH:
        r0, q0 = rng.normal(size=3), st.random_quat(rng)
        v, w = np.array([0.3, -0.2, 1.1]), np.array([0.4, 1.5, -0.7])   # w in the camera frame
        x_v = np.r_[r0, q0, v, w, np.full(cam_dim - 13, 0.01)]
        s = State.from_camera(x_v, np.zeros((cam_dim, cam_dim)))
        steps = 90
        for _ in range(steps):
            predict(s, DT, CFG)
        t = steps * DT
        assert np.allclose(s.r, r0 + v * t, atol=1e-13)
        # Constant body-frame rate about a fixed axis: R(t) = R0 Rot(w t).
        R_expected = st.to_scipy(q0).as_matrix() @ Rotation.from_rotvec(w * t).as_matrix()
        assert np.allclose(quat_to_rotation(s.q), R_expected, atol=1e-13)
        assert np.allclose(s.v, v) and np.allclose(s.w, w) and np.array_equal(s.x[13:], x_v[13:])


def test_predict_rejects_bad_dt_and_normalise_quaternion():
    s = State.from_camera(np.r_[np.zeros(3), 1, 0, 0, 0, np.zeros(6)], np.eye(13) * 1e-4)
    for dt in (-0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="dt"):
            predict(s, dt, CFG)
    s.x[Q_SLICE] = 2.0
    normalise_quaternion(s)
    assert np.allclose(s.q, 0.5)


# -- measurement helpers -----------------------------------------------------------------------

@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_ray_from_pixel_and_init_point_jacobians(model):
    cam = CAMERAS[model]
    rng = np.random.default_rng(14)
    for cam_dim in BOTH:
        x_v = st.random_camera(rng, cam_dim=cam_dim)
        uv = np.array([rng.uniform(20, cam.width - 20), rng.uniform(20, cam.height - 20)])
        lam = rng.uniform(0.5, 5.0)
        origin, d, dd_dx, dd_duv = ray_from_pixel(x_v, uv, cam)
        assert np.allclose(origin, x_v[:3]) and abs(np.linalg.norm(d) - 1) < 1e-12
        assert dd_dx.shape == (3, cam_dim)
        st.assert_jacobian(dd_dx, st.fd_jacobian(lambda a: ray_from_pixel(a, uv, cam)[1], x_v))
        st.assert_jacobian(dd_duv, st.fd_jacobian(lambda b: ray_from_pixel(x_v, b, cam)[1], uv, h=1e-4), rtol=1e-5)

        y, dy_dx, dy_duv, dy_dd = init_point_from_depth(x_v, uv, lam, cam)
        assert np.allclose(y, origin + lam * d)
        # The point projects back to the pixel, at distance lam from the optical centre.
        assert np.allclose(project(cam, ((y - x_v[:3]) @ quat_to_rotation(x_v[Q_SLICE]))[None])[0], uv, atol=1e-7)
        assert np.isclose(np.linalg.norm(y - x_v[:3]), lam)
        st.assert_jacobian(dy_dx, st.fd_jacobian(lambda a: init_point_from_depth(a, uv, lam, cam)[0], x_v))
        st.assert_jacobian(dy_duv, st.fd_jacobian(lambda b: init_point_from_depth(x_v, b, lam, cam)[0], uv, h=1e-4),
                           rtol=1e-5)
        st.assert_jacobian(dy_dd, d)


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_predictions_agree_with_the_lens_model(model):
    """measurement.predict (both kinds) and predict_points against kinematics.camera.project of
    the features' world points; features behind the camera are NaN and invalid."""
    cam = CAMERAS[model]
    rng = np.random.default_rng(15)
    s = mixed_state(rng, CAMERA_DIM, cam=cam)
    R = quat_to_rotation(s.q)
    Y = np.array([inverse_depth.world_point(s.feature(k), s.anchors[k]) if s.kinds[k] == INVERSE_DEPTH
                  else s.feature(k) for k in range(s.n_features)])
    expected = project(cam, (Y - s.r) @ R)
    pred = predict_h(s, np.arange(s.n_features), cam)
    assert pred.valid.all()
    np.testing.assert_allclose(pred.uv, expected, atol=1e-8)
    uv, H_c, valid = predict_points(s.x_v, Y, cam)
    assert valid.all()
    np.testing.assert_allclose(uv, expected, atol=1e-8)
    # Both kinds see the camera through the same point: the same d(uv)/d(r, q).
    np.testing.assert_allclose(H_c, pred.H_c, rtol=1e-9, atol=1e-9)
    # Turned about: every feature is behind the camera (an inverse-depth one's ray h_C = R^T
    # (rho (c - r) + m) points backwards).
    s.x[Q_SLICE] = quat_multiply(s.q, [0.0, 0.0, 1.0, 0.0])
    pred = predict_h(s, np.arange(s.n_features), cam)
    assert not pred.valid.any() and np.isnan(pred.uv).all() and np.isnan(pred.H_c).all() and np.isnan(pred.H_f).all()
    assert not predict_points(s.x_v, Y, cam)[2].any()
