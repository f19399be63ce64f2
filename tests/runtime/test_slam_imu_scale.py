"""The visual-inertial scale: a camera trajectory of known metric motion, seen in map units, and
its IMU synthesised from the motion's derivatives (independently of the estimator's
pre-integration): the scale and gravity are recovered, and a turn-free or still camera is not
trusted."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from runtime.slam.imu_scale import GRAVITY_M_S2, estimate_scale, gravity_aligned, preintegrate

G_WORLD = np.array([0.0, 0.0, -9.81])


def _motion(T=4.0, rate=200.0, amp=0.15, turn=0.3, seed=0):
    """Positions (metric), rotations, and the ideal IMU (camera frame) of a swaying, turning camera."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.4, 1.2, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    t = np.arange(0.0, T, 1.0 / rate)
    p = amp * np.sin(2 * np.pi * f * t[:, None] + ph)
    a = -amp * (2 * np.pi * f) ** 2 * np.sin(2 * np.pi * f * t[:, None] + ph)
    # Rotation: a slow turn about a tilted axis plus a wobble; body rates from the exact derivative.
    rv = lambda tt: np.column_stack([turn * np.sin(0.7 * tt), 0.4 * turn * tt, 0.2 * np.cos(1.3 * tt)])  # noqa: E731
    R = Rotation.from_rotvec(rv(t)).as_matrix()
    h = 1e-5
    Rp, Rm = Rotation.from_rotvec(rv(t + h)).as_matrix(), Rotation.from_rotvec(rv(t - h)).as_matrix()
    W = np.einsum("nji,njk->nik", R, (Rp - Rm) / (2 * h))          # R^T dR/dt = [w]_x
    w = np.column_stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]])
    f_body = np.einsum("nji,nj->ni", R, a - G_WORLD)                # specific force, camera frame
    return t, p, R, w, f_body


def test_preintegration_matches_the_motion():
    t, p, R, w, f = _motion()
    i, j = 100, 160
    dR, dv, dp = preintegrate(t, w, f, t[i], t[j])
    # Velocity from the exact position derivative (central difference of the known motion).
    v = np.gradient(p, t, axis=0)
    dt = t[j] - t[i]
    np.testing.assert_allclose(R[i] @ dR, R[j], atol=2e-3)
    np.testing.assert_allclose(R[i] @ dv + G_WORLD * dt, v[j] - v[i], atol=5e-3)
    np.testing.assert_allclose(R[i] @ dp + v[i] * dt + 0.5 * G_WORLD * dt**2, p[j] - p[i], atol=1e-3)


def test_scale_and_gravity_are_recovered_from_map_units():
    t, p, R, w, f = _motion(seed=1)
    s_true = 0.37                                                    # metres per map unit
    cam = slice(0, None, 7)                                          # frames at about 30 Hz
    est = estimate_scale(t[cam], p[cam] / s_true, R[cam], t, w, f, stride_s=0.3)
    assert est is not None
    assert abs(est.scale / s_true - 1) < 0.01
    assert np.degrees(np.arccos(est.g_world @ G_WORLD / (GRAVITY_M_S2 * 9.81))) < 1.0
    # The gravity-aligned frame turns the map's gravity straight down.
    up = gravity_aligned(est.g_world)
    np.testing.assert_allclose(up @ est.g_world / GRAVITY_M_S2, [0, 0, -1], atol=1e-9)
    np.testing.assert_allclose(up @ up.T, np.eye(3), atol=1e-12)


def test_a_biased_accelerometer_on_a_turning_camera():
    t, p, R, w, f = _motion(T=6.0, turn=0.8, seed=2)
    s_true = 2.2
    b = np.array([0.08, -0.05, 0.1])
    est = estimate_scale(t[::7], p[::7] / s_true, R[::7], t, w, f + b, stride_s=0.3)
    assert abs(est.scale / s_true - 1) < 0.03


def test_too_few_frames_give_no_estimate():
    t, p, R, w, f = _motion(T=0.5)
    assert estimate_scale(t[::7], p[::7], R[::7], t, w, f, stride_s=0.3) is None


def test_the_scale_s_convergence_is_reported_over_longer_and_longer_starts_of_the_run():
    """scale_from_imu's history: the estimate over the run's first 1, 2, 4, 8 s and the whole run,
    each from its own frames. With 4 mm of noise on the map's positions the first second's
    estimate is 5% off and the scale settles (within 2% of the whole run's for good) from 2 s;
    its uncertainty falls as the run lengthens. Without noise it has settled from the first second."""
    from types import SimpleNamespace

    from runtime.slam.run import IMU_SCALE_SETTLED_REL, scale_from_imu

    t, p, R, w, f = _motion(T=16.0, turn=0.6, seed=3)
    s_true = 0.5
    cam = slice(0, None, 7)
    tc, Rc = t[cam], R[cam]
    T = np.tile(np.eye(4), (len(tc), 1, 1))
    T[:, :3, :3] = Rc
    T[:, :3, 3] = (p[cam] + np.random.default_rng(2).normal(0, 0.004, p[cam].shape)) / s_true
    imu = SimpleNamespace(t=t, gyro=w, accel=f)
    r = scale_from_imu(tc, T, imu)
    h = r["history"]
    assert [x["seconds"] for x in h[:4]] == [1.0, 2.0, 4.0, 8.0] and h[-1]["seconds"] == pytest.approx(tc[-1] - tc[0])
    assert h[-1]["scale"] == r["scale"] and abs(r["scale"] / s_true - 1) < 0.01
    sig = [x["sigma_rel"] for x in h]
    assert all(a > b for a, b in zip(sig, sig[1:]))                  # more motion, a firmer scale
    assert abs(h[0]["scale"] / r["scale"] - 1) > IMU_SCALE_SETTLED_REL
    within = [abs(x["scale"] / r["scale"] - 1) <= IMU_SCALE_SETTLED_REL for x in h[:-1]]
    first_for_good = next(i for i in range(len(within)) if all(within[i:]))
    assert r["settled_s"] == h[first_for_good]["seconds"] == 2.0
    assert "from the run's first 2 s on" in r["said"]
    T[:, :3, 3] = p[cam] / s_true
    assert scale_from_imu(tc, T, imu)["settled_s"] == 1.0


def test_the_hand_over_estimates_as_the_whole_run_s_estimate_would_and_writes_k():
    """imu_handover.ImuHandover fed frame by frame: each estimate it returns is estimate_scale's
    over every pose so far, to the bit (it pre-integrates each interval once instead); none before
    handover_min_s or with fewer than MIN_TRIPLETS triplets; the hand-over writes k = 1 / scale
    with at least handover_scale_sigma, uncorrelated, and the estimate's accelerometer bias."""
    from runtime.slam.config import MapSettings
    from runtime.slam.imu_handover import GRAVITY_MAGNITUDE_SIGMA, MIN_TRIPLETS, ImuHandover
    from runtime.slam.layout import BA_SLICE, CAMERA_DIM_SCALED, G_SLICE, SCALE_INDEX
    from runtime.slam.state import State

    t, p, R, w, f = _motion(T=4.0, seed=2)
    s_true = 0.6
    rows = np.column_stack([t, w, f])
    settings = MapSettings(handover_max_sigma=1.0)
    h = ImuHandover(settings)
    cam = np.arange(0, len(t), 7)
    first = None
    for n, j in enumerate(cam):
        e = h.add(t[j], p[j] / s_true, R[j], rows)
        if e is None:
            continue
        ref = estimate_scale(t[cam[:n + 1]], p[cam[:n + 1]] / s_true, R[cam[:n + 1]], t, w, f)
        assert e.scale == ref.scale and np.array_equal(e.g_world, ref.g_world) and e.sigma_rel == ref.sigma_rel
        assert e.triplets >= MIN_TRIPLETS and t[j] - t[0] >= settings.imu.handover_min_s
        first = first if first is not None else (j, e)
    assert first is not None and abs(first[1].scale / s_true - 1) < 0.02
    state = State.from_camera(np.r_[np.zeros(3), 1.0, np.zeros(16), 1.0, 0.0, 0.0, -9.81], np.eye(CAMERA_DIM_SCALED) * 0.01)
    state.P[SCALE_INDEX, 0] = state.P[0, SCALE_INDEX] = 0.005
    state.P[G_SLICE.start, 1] = state.P[1, G_SLICE.start] = 0.005
    done = h.hand_over(state, first[1])
    k = 1 / first[1].scale
    assert state.x[SCALE_INDEX] == k and done.k == k
    assert state.P[SCALE_INDEX, SCALE_INDEX] == (k * max(first[1].sigma_rel, settings.imu.handover_scale_sigma)) ** 2
    assert not state.P[SCALE_INDEX, :SCALE_INDEX].any()
    assert np.array_equal(state.x[BA_SLICE], first[1].accel_bias)
    # Gravity: the estimate's, uncorrelated, its direction's prior across it and its magnitude's along it.
    g = np.asarray(first[1].g_world)
    u = g / np.linalg.norm(g)
    assert np.array_equal(state.x[G_SLICE], g) and not state.P[G_SLICE, :G_SLICE.start].any()
    P_g = state.P[G_SLICE, G_SLICE]
    np.testing.assert_allclose(u @ P_g @ u, GRAVITY_MAGNITUDE_SIGMA**2, rtol=1e-9)
    across = np.cross(u, [1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    np.testing.assert_allclose(across @ P_g @ across, (9.81 * settings.imu.handover_gravity_sigma) ** 2, rtol=1e-3)


def test_gravity_direction_sigma_counts_only_the_spread_across_gravity():
    """stats.json's g_sigma_deg: gravity's direction with sigma rad per axis across it is sigma sqrt(2)
    rad over both axes, whatever its magnitude's variance along it."""
    from runtime.slam.run import gravity_direction_sigma_deg

    g = np.array([1.0, 7.0, -6.8])
    u = g / np.linalg.norm(g)
    for sigma in (0.05, 0.004):
        across = (np.linalg.norm(g) * sigma) ** 2 * (np.eye(3) - np.outer(u, u))
        for along in (0.0, 0.05**2, 4.0):
            np.testing.assert_allclose(gravity_direction_sigma_deg(g, across + along * np.outer(u, u)),
                                       np.degrees(sigma * np.sqrt(2)), rtol=1e-12)
