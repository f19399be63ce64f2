"""Tests for runtime.slam.filter.SequentialUpdate, MonoSLAM's per-frame sequential update with
the low-rank covariance: it must equal the one-at-a-time path (innovation_covariances +
update_one, dense Joseph form) to rounding, refuse bad updates without changing anything, never
let NaN in, and leave the State alone until commit. Also the exact-symmetry bookkeeping that lets
check_covariance skip its n x n symmetrisation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kinematics.camera import project
from runtime.slam.filter import (
    FeatureNotMeasurable,
    SequentialUpdate,
    add_point_feature,
    innovation_covariances,
    update_one,
)
from runtime.slam.motion import apply_quaternion_jacobian, normalise_quaternion_jacobian, predict
from runtime.slam.state import (
    CAMERA_DIM,
    DEFAULT_CONFIG,
    Q_SLICE,
    SlamNumericalError,
    State,
    check_covariance,
    feature_slice,
    quat_to_rotation,
)

import test_slam_core as core   # its map state and cameras (pytest puts this folder on sys.path)

STEP_CFG = replace(DEFAULT_CONFIG, check_psd=False)   # as MonoSLAM.process runs the updates
# The lens models of test_slam_core (the same cameras), plus the plain pinhole.
CAMERAS = {"pinhole": core.PINHOLE, **core.CAMERAS}


def map_state(rng, n_features: int) -> tuple[State, np.ndarray]:
    """test_slam_core's map state (a camera looking along world +Z at points 2-4 m ahead, full
    correlated covariance, q block tangent to q) with the feature estimates 2 cm off the true
    points, after one prediction. Returns the state and the true points (world, m)."""
    s, Y = core.map_state(rng, n_features)
    s.x[CAMERA_DIM:] += rng.normal(0, 0.02, Y.size)
    predict(s, 1 / 30, STEP_CFG)
    return s, Y


def measure(x_v: np.ndarray, y: np.ndarray, cam, rng) -> np.ndarray:
    """A simulated match (px) of the world point y (3,) seen from the camera x_v, 1 px noise."""
    return project(cam, ((y - x_v[:3]) @ quat_to_rotation(x_v[3:7]))[None])[0] + rng.normal(0, 1, 2)


def assert_close(a, b, rel: float = 1e-9) -> None:
    """Agreement relative to the largest entry (covariance entries span many magnitudes)."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    scale = max(np.abs(b).max(), 1e-300)
    assert np.abs(a - b).max() <= rel * scale, f"relative error {np.abs(a - b).max() / scale:.3g}"


# -- equality with the one-at-a-time path ------------------------------------------------------

@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_sequential_update_equals_update_one(model):
    """20 updates (more than the initial capacity of U; features repeated), each preceded by
    its innovation: every ellipse, every result and the committed state equal
    innovation_covariances + update_one on a copy."""
    cam = CAMERAS[model]
    rng = np.random.default_rng(1)
    s, Y = map_state(rng, 12)
    ref = s.copy()
    su = SequentialUpdate(s, cam, np.diag([1.5, 0.8]), STEP_CFG)
    ks = list(rng.permutation(12)) + [3, 7, 0, 11, 5, 5, 2, 9]
    for k in ks:
        uv, S, valid = su.innovation(k)
        uv_ref, S_ref, valid_ref = innovation_covariances(ref, [k], cam, np.diag([1.5, 0.8]))
        assert valid and valid_ref[0]
        assert_close(uv, uv_ref[0], 1e-12)
        assert_close(S, S_ref[0])
        z = measure(su.x_v, Y[k], cam, rng)
        res = su.update(k, z)
        res_ref = update_one(ref, k, z, cam, np.diag([1.5, 0.8]), STEP_CFG)
        assert_close(res.uv, res_ref.uv, 1e-12)
        assert_close(res.nu, res_ref.nu, 1e-9)
        assert_close(res.S, res_ref.S)
        # The current mean and covariance track the reference after every update.
        assert_close(su.x, ref.x)
        assert_close(su.covariance(), ref.P)
    assert su.n_updates == len(ks)
    su.commit()
    assert_close(s.x, ref.x)
    assert_close(s.P, ref.P)
    assert np.array_equal(s.P, s.P.T)
    assert abs(np.linalg.norm(s.q) - 1.0) < 1e-15
    # q's norm direction stays the covariance's null direction, as update_one keeps it.
    assert np.abs(s.P[:, Q_SLICE] @ s.q).max() <= 1e-12 * np.abs(s.P).max()


def test_state_is_untouched_until_commit_and_mean_is_current():
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(2)
    s, Y = map_state(rng, 6)
    x0, P0 = s.x, s.P
    x0_copy, P0_copy = s.x.copy(), s.P.copy()
    su = SequentialUpdate(s, cam, 1.0, STEP_CFG)
    uv0, S0, _ = su.innovation(2)
    su.update(2, measure(su.x_v, Y[2], cam, rng))
    assert s.x is x0 and s.P is P0
    assert np.array_equal(s.x, x0_copy) and np.array_equal(s.P, P0_copy)
    assert not np.array_equal(su.x, x0_copy)            # the mean moved ...
    assert np.array_equal(su.x_v, su.x[:13]) and np.array_equal(su.feature(4), su.x[feature_slice(4)])
    assert np.array_equal(su.features[4], su.feature(4)) and su.features.shape == (6, 3)
    uv1, S1, _ = su.innovation(2)                        # ... and the ellipse shrank
    assert np.linalg.det(S1) < 0.5 * np.linalg.det(S0)
    su.commit()
    assert np.array_equal(s.x, su.x)
    with pytest.raises(RuntimeError, match="committed"):
        su.innovation(0)
    with pytest.raises(RuntimeError, match="committed"):
        su.commit()


def test_no_updates_commit_leaves_the_arrays():
    s, _ = map_state(np.random.default_rng(3), 3)
    x0, P0 = s.x, s.P
    su = SequentialUpdate(s, CAMERAS["pinhole"], 1.0, STEP_CFG)
    su.innovation(1)
    su.commit()
    assert s.x is x0 and s.P is P0


def test_state_changed_behind_its_back_is_an_error():
    cam = CAMERAS["pinhole"]
    s, Y = map_state(np.random.default_rng(4), 4)
    su = SequentialUpdate(s, cam, 1.0, STEP_CFG)
    predict(s, 1 / 30, STEP_CFG)
    with pytest.raises(RuntimeError, match="state was changed"):
        su.innovation(0)
    su = SequentialUpdate(s, cam, 1.0, STEP_CFG)
    s.remove_feature(3)
    with pytest.raises(RuntimeError, match="state was changed"):
        su.update(0, [320.0, 240.0])
    su = SequentialUpdate(s, cam, 1.0, STEP_CFG)
    with pytest.raises(IndexError, match="feature 3 does not exist"):
        su.innovation(3)


# -- refusals ----------------------------------------------------------------------------------

def snapshot(su: SequentialUpdate) -> tuple:
    return su.x, su.covariance(), su.n_updates


def assert_unchanged(su: SequentialUpdate, snap: tuple) -> None:
    x, P, m = snap
    assert su.n_updates == m
    assert np.array_equal(su.x, x) and np.array_equal(su.covariance(), P)
    assert np.isfinite(su.x).all() and np.isfinite(su.covariance()).all()


def test_refused_updates_change_nothing_and_the_frame_goes_on():
    """NaN measurements, a point behind the camera and a non-positive-definite S are refused;
    nothing changes, and the frame continues exactly as if they had not been tried."""
    cam = CAMERAS["brown"]
    rng = np.random.default_rng(5)
    s, Y = map_state(rng, 6)
    # Feature 5 behind the camera.
    s.x[feature_slice(5)] = s.r - 2.0 * quat_to_rotation(s.q)[:, 2]
    twin = s.copy()
    su = SequentialUpdate(s, cam, 1.0, STEP_CFG)
    su_twin = SequentialUpdate(twin, cam, 1.0, STEP_CFG)
    z1 = measure(su.x_v, Y[1], cam, rng)
    su.update(1, z1)
    su_twin.update(1, z1)

    snap = snapshot(su)
    with pytest.raises(FeatureNotMeasurable, match="NaN/Inf"):
        su.update(2, [np.nan, 100.0])
    with pytest.raises(FeatureNotMeasurable, match="NaN/Inf"):
        su.update(2, [np.inf, 100.0])
    uv, S, valid = su.innovation(5)
    assert not valid and np.isnan(uv).all() and np.isnan(S).all()
    with pytest.raises(FeatureNotMeasurable, match="feature 5 has no predicted image point"):
        su.update(5, [320.0, 240.0])
    assert_unchanged(su, snap)

    # A negative pixel variance large enough to make S indefinite.
    su_bad_R = SequentialUpdate(twin.copy(), cam, -1e9, STEP_CFG)
    with pytest.raises(SlamNumericalError, match="not positive definite"):
        su_bad_R.update(0, [320.0, 240.0])
    assert su_bad_R.n_updates == 0

    z3 = measure(su.x_v, Y[3], cam, rng)
    su.update(3, z3)
    su_twin.update(3, z3)
    su.commit()
    su_twin.commit()
    assert np.array_equal(s.x, twin.x) and np.array_equal(s.P, twin.P)


def indefinite_state(rng, cam) -> tuple[State, np.ndarray]:
    """A state whose covariance claims an impossible correlation (|corr| = 10) between features
    0 and 1: measuring feature 0 precisely then removes more variance from feature 1 than it
    has. (State refuses such a P, so it is put in afterwards.)"""
    s, Y = map_state(rng, 3)
    P = s.P.copy()
    f0, f1 = feature_slice(0), feature_slice(1)
    c = 10.0 * np.sqrt(np.diag(P)[f0] * np.diag(P)[f1])
    P[f0, f1] = np.diag(c)
    P[f1, f0] = np.diag(c)
    s.P = P
    return s, Y


def test_negative_variance_is_refused_like_update_one():
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(6)
    s, Y = indefinite_state(rng, cam)
    z = measure(s.x_v, Y[0], cam, rng)
    ref = State.__new__(State)            # a copy without State's validation: P is indefinite
    ref.x, ref.P = s.x.copy(), s.P.copy()
    with pytest.raises(SlamNumericalError, match="negative variance"):
        update_one(ref, 0, z, cam, 0.01, STEP_CFG)
    su = SequentialUpdate(s, cam, 0.01, STEP_CFG)
    snap = snapshot(su)
    with pytest.raises(SlamNumericalError, match=r"negative variance P\[1[6-8],1[6-8]\].*feature 1"):
        su.update(0, z)
    assert_unchanged(su, snap)


def test_commit_check_failure_keeps_the_frame_start():
    """With the full PSD check in cfg, commit refuses an indefinite covariance and the state keeps
    its pre-frame mean and covariance."""
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(7)
    s, Y = indefinite_state(rng, cam)
    x0, P0 = s.x, s.P
    su = SequentialUpdate(s, cam, 1.0, DEFAULT_CONFIG)
    su.update(2, measure(su.x_v, Y[2], cam, rng))        # feature 2 is not in the bad pair
    with pytest.raises(SlamNumericalError, match="not positive semi-definite"):
        su.commit()
    assert s.x is x0 and s.P is P0


# -- a frame in a running filter ---------------------------------------------------------------

def test_frames_with_new_features_match_the_reference():
    """Several frames of predict / sequential updates / add a feature: the filter through
    SequentialUpdate stays equal to the one through update_one."""
    cam = CAMERAS["fisheye"]
    rng = np.random.default_rng(8)
    s, Y = map_state(rng, 5)
    ref = s.copy()
    for frame in range(5):
        predict(s, 1 / 30, STEP_CFG)
        predict(ref, 1 / 30, STEP_CFG)
        _, S, valid = innovation_covariances(s, np.arange(s.n_features), cam, 1.0)
        order = np.argsort(-np.linalg.det(S))
        su = SequentialUpdate(s, cam, 1.0, STEP_CFG)
        for k in order:
            if k >= len(Y):
                continue
            z = measure(su.x_v, Y[k], cam, rng)
            su.update(k, z)
            update_one(ref, int(k), z, cam, 1.0, STEP_CFG)
        su.commit()
        s.P = check_covariance(s.P, "frame", DEFAULT_CONFIG)
        ref.P = check_covariance(ref.P, "frame", DEFAULT_CONFIG)
        assert_close(s.x, ref.x)
        assert_close(s.P, ref.P, 1e-8)
        uv = np.array([300.0 + 10 * frame, 200.0])
        add_point_feature(s, uv, 2.5, 0.25, 1.0, cam, STEP_CFG)
        add_point_feature(ref, uv, 2.5, 0.25, 1.0, cam, STEP_CFG)


# -- exact symmetry, so that check_covariance can skip the symmetrisation ----------------------

def test_predict_commit_and_quaternion_jacobian_keep_P_exactly_symmetric():
    cam = CAMERAS["pinhole"]
    rng = np.random.default_rng(9)
    s, Y = map_state(rng, 8)
    assert np.array_equal(s.P, s.P.T)
    predict(s, 1 / 30, STEP_CFG)
    assert np.array_equal(s.P, s.P.T)
    su = SequentialUpdate(s, cam, 1.0, STEP_CFG)
    for k in range(8):
        su.update(k, measure(su.x_v, Y[k], cam, rng))
    P = su.covariance()
    assert np.array_equal(P, P.T)
    assert check_covariance(P, "", STEP_CFG) is P      # nothing to symmetrise
    # apply_quaternion_jacobian equals the dense T P T^T.
    _, J = normalise_quaternion_jacobian(s.q * 1.01)
    T = np.eye(s.n)
    T[Q_SLICE, Q_SLICE] = J
    P2 = P.copy()
    apply_quaternion_jacobian(P2, J)
    assert np.array_equal(P2, P2.T)
    assert_close(P2, T @ P @ T.T, 1e-14)


def test_check_covariance_still_catches_nan_inf_and_asymmetry():
    P = np.eye(4)
    P[1, 2] = P[2, 1] = np.inf
    with pytest.raises(SlamNumericalError, match=r"NaN/Inf.*first at \(1, 2\)"):
        check_covariance(P)
    P = np.eye(4)
    P[3, 3] = np.nan
    with pytest.raises(SlamNumericalError, match=r"NaN/Inf.*first at \(3, 3\)"):
        check_covariance(P)
    P = np.array([[2.0, 0.5], [0.5 + 1e-9, 1.0]])
    out = check_covariance(P)
    assert out is not P and np.array_equal(out, out.T) and out[0, 1] == 0.5 * (0.5 + 0.5 + 1e-9)
    F = np.asfortranarray(np.array([[2.0, 0.3], [0.3, 1.0]]))
    assert np.array_equal(check_covariance(F), F)
