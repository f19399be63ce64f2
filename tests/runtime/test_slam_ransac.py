"""1-point RANSAC (ransac.one_point_ransac) on simulated matches with known inliers and gross
outliers: it must keep every inlier and reject every outlier (a constant or no-op selection
fails), rescue a consistent match just above the low-innovation threshold, adapt its number of
hypotheses, and leave the state updated with the inliers' information only."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

import slam_testing as st
from runtime.slam.config import MapSettings, RansacSettings, SlamConfig
from runtime.slam.features import POINT
from runtime.slam.filter import innovation_covariances, update
from runtime.slam.measurement import predict
from runtime.slam.motion import predict as predict_motion
from runtime.slam.quaternion import dq_dtheta_right, quat_multiply, quat_to_rotation, rotvec_to_quat
from runtime.slam.ransac import one_point_ransac
from runtime.slam.state import State

CAM = st.PINHOLE
S = MapSettings()
#: The tests hold the algorithm to Civera et al.'s 99% rescue gate (chi-square, 2 dof); the
#: default setting is a stricter, tuned one (config.py).
RESCUE_99 = 9.21


def ransac(state, ks, z, pred, S_prior, rng_seed=0, R_pix=1.0, threshold=S.ransac.threshold_px,
           max_hypotheses=S.ransac.max_hypotheses):
    return one_point_ransac(state, ks, z, CAM, R_pix, pred, S_prior,
                            RansacSettings(threshold, max_hypotheses, S.ransac.confidence, RESCUE_99),
                            np.random.default_rng(rng_seed))


def draw_camera(s: State, rng: np.random.Generator):
    """A camera (r (3,), R (3, 3)) drawn from the state's own pose covariance about its mean."""
    G = np.zeros((7, 6))
    G[:3, 3:] = np.eye(3)
    G[3:7, :3] = dq_dtheta_right(s.q)
    Gi = np.linalg.pinv(G)
    P6 = Gi @ s.P[:7, :7] @ Gi.T
    d = rng.multivariate_normal(np.zeros(6), 0.5 * (P6 + P6.T))
    return s.r + d[3:], quat_to_rotation(quat_multiply(s.q, rotvec_to_quat(d[:3])))


def scene(seed: int, m: int = 30, outlier_fraction: float = 0.3, noise_px: float = 0.3, gap_px: float = 12.0,
          camera_sigma=(0.002, 0.002, 0.05, 0.1)):
    """A map of ``m`` points 1.5 to 5 m ahead (known to 3 mm), the camera predicted one frame
    (1/30 s, the default hand-held impulses) from a converged estimate, the true camera drawn
    from that prediction's own covariance, the true points from the map's. Inlier matches are
    the true projections with ``noise_px``; a known fraction are replaced by gross outliers:
    positions inside the feature's 3-sigma search ellipse (where the active search finds its
    matches) at least ``gap_px`` from the true projection (a repeated texture, an occluding
    contour). Returns the state, ks, z, the prior predictions and ellipses, the outlier mask and
    the true camera (r, R)."""
    rng = np.random.default_rng(seed)
    R0 = st.look_at([0, 0, 0], [0.1, 1.0, 0.0], up=(0, 0, 1))
    q0 = st.quat_of(R0)
    x_v = np.r_[0.0, 0.0, 0.0, q0, rng.normal(0, 0.3, 3), rng.normal(0, 0.5, 3)]
    s = State.from_camera(x_v, st.camera_covariance(q0, *camera_sigma))
    uv = rng.uniform([30, 30], [CAM.width - 30, CAM.height - 30], (m, 2))
    depth = rng.uniform(1.5, 5.0, m)
    rays = np.column_stack([(uv - [CAM.cx, CAM.cy]) / [CAM.fx, CAM.fy], np.ones(m)])
    Y = (rays * (depth / np.linalg.norm(rays, axis=1))[:, None]) @ R0.T
    sig_y = 0.003
    for y in Y:
        s.add_feature(POINT, y, sig_y**2 * np.eye(3), np.zeros((3, s.n)))
    predict_motion(s, 1 / 30, SlamConfig(motion_noise_interval=1 / 30))   # the prior these scenes were drawn with
    r_true, R_true = draw_camera(s, rng)
    Y_true = Y + rng.normal(0, sig_y, Y.shape)
    ks = np.arange(m)
    pred = predict(s, ks, CAM)
    S_prior = innovation_covariances(s, pred, 1.0)
    z = st.pixels(CAM, R_true, r_true, Y_true) + rng.normal(0, noise_px, (m, 2))
    out = np.zeros(m, bool)
    out[rng.choice(m, int(round(outlier_fraction * m)), replace=False)] = True
    for i in np.flatnonzero(out):
        L = np.linalg.cholesky(S_prior[i])
        for _ in range(100_000):
            w = rng.uniform(-3, 3, 2)
            c = pred.uv[i] + L @ w
            if w @ w < 9 and np.linalg.norm(c - z[i]) > gap_px:
                z[i] = c
                break
        else:
            raise AssertionError("no room for an outlier in the ellipse")
    return s, ks, z, pred, S_prior, out, (r_true, R_true)


@pytest.mark.parametrize("outlier_fraction", [0.3, 0.4])
def test_keeps_every_inlier_and_rejects_every_outlier(outlier_fraction):
    errors_before, errors_after, tried, rescued = [], [], [], 0
    for seed in range(20):
        s, ks, z, pred, S_prior, out, (r_true, R_true) = scene(seed, outlier_fraction=outlier_fraction)
        oracle = s.copy()
        e0 = np.linalg.norm(s.r - r_true)
        res = ransac(s, ks, z, pred, S_prior, seed)
        assert np.array_equal(res.used, ~out), (seed, np.flatnonzero(res.used != ~out), out.sum())
        assert not (res.low & res.rescued).any() and np.array_equal(res.used, res.low | res.rescued)
        assert res.n_inliers == (~out).sum() and res.n_outliers == out.sum()
        # The state holds the inliers' information, as one batch update with the true inliers
        # does (RANSAC's two batches relinearise in between: close, not equal).
        update(oracle, ks[~out], z[~out], CAM, 1.0)
        assert np.linalg.norm(s.r - oracle.r) < 1e-3
        assert st.rotation_error_rad(quat_to_rotation(s.q), quat_to_rotation(oracle.q)) < 5e-4
        np.testing.assert_allclose(np.diag(s.P)[:7], np.diag(oracle.P)[:7], rtol=0.05, atol=1e-12)
        errors_before.append(e0)
        errors_after.append(np.linalg.norm(s.r - r_true))
        tried.append(res.hypotheses)
        rescued += res.rescued.sum()
    print(f"\n{outlier_fraction:.0%} outliers: camera error {1000 * np.median(errors_before):.1f} -> "
          f"{1000 * np.median(errors_after):.1f} mm (median), hypotheses {min(tried)}..{max(tried)}, rescued {rescued}")
    assert np.median(errors_after) < 0.6 * np.median(errors_before)
    assert rescued > 0                                # both steps of the algorithm at work
    # Fewer inliers take more hypotheses (log(1 - p) / log(1 - w)).
    assert max(tried) <= S.ransac.max_hypotheses


def test_half_outliers():
    """With as many outliers as inliers a set of outliers can now and then outvote the inliers
    (their hypotheses gather only the few matches within 2 px): right in nearly every frame."""
    right = 0
    for seed in range(20):
        s, ks, z, pred, S_prior, out, _ = scene(seed, outlier_fraction=0.5)
        right += np.array_equal(ransac(s, ks, z, pred, S_prior, seed).used, ~out)
    print(f"\n50% outliers: every match right in {right} of 20 frames")
    assert right >= 18


def test_most_matches_are_classified_right_with_pixel_noise_and_closer_outliers():
    """1 px matching noise (the filter's own) and outliers only 8 px off: no guarantee for each
    match (a chi-square gate at 99% rejects 1% of good matches), but nearly all right."""
    kept, inliers, rejected, outliers = 0, 0, 0, 0
    for seed in range(30):
        s, ks, z, pred, S_prior, out, _ = scene(100 + seed, noise_px=1.0, gap_px=8.0)
        res = ransac(s, ks, z, pred, S_prior, seed)
        kept += (res.used & ~out).sum()
        inliers += (~out).sum()
        rejected += (~res.used & out).sum()
        outliers += out.sum()
    print(f"\n1 px noise, 8 px outliers: inliers kept {kept / inliers:.1%}, outliers rejected {rejected / outliers:.1%}")
    assert kept / inliers > 0.95 and rejected / outliers > 0.95


def tight_scene():
    """A camera known to 1 mrad (predictions within half a pixel), 12 points known exactly:
    hypotheses from any inlier predict every other inlier within the low-innovation threshold."""
    rng = np.random.default_rng(7)
    R0 = st.look_at([0, 0, 0], [0, 1.0, 0.0], up=(0, 0, 1))
    q0 = st.quat_of(R0)
    s = State.from_camera(np.r_[0.0, 0.0, 0.0, q0, np.zeros(6)], st.camera_covariance(q0, 5e-4, 1e-3, 0.01, 0.01))
    uv = rng.uniform([60, 60], [CAM.width - 60, CAM.height - 60], (12, 2))
    rays = np.column_stack([(uv - [CAM.cx, CAM.cy]) / [CAM.fx, CAM.fy], np.ones(12)])
    Y = (rays * rng.uniform(2.0, 4.0, 12)[:, None]) @ R0.T
    for y in Y:
        s.add_feature(POINT, y, 1e-10 * np.eye(3), np.zeros((3, s.n)))
    d = np.r_[0.8e-3, -0.5e-3, 0.6e-3]                    # the true camera: a small rotation off
    z = st.pixels(CAM, R0 @ st.to_scipy(rotvec_to_quat(d)).as_matrix(), s.r, Y)
    ks = np.arange(12)
    pred = predict(s, ks, CAM)
    return s, ks, z, pred


def test_a_consistent_match_just_above_the_threshold_is_rescued():
    """With R = 2 px^2 the rescue gate (chi-square 9.21) is about 4.4 px: a match 3 px off its
    true position (above the 2 px low-innovation threshold) is rescued, one 6 px off is not."""
    s, ks, z, pred = tight_scene()
    R_pix = 2.0
    S_prior = innovation_covariances(s, pred, R_pix)
    z = z.copy()
    z[3] += [3.0, 0.0]                                    # just above the threshold, consistent
    z[8] += [0.0, -6.0]                                   # inconsistent
    res = ransac(s, ks, z, pred, S_prior, 1, R_pix=R_pix)
    assert not res.low[3] and res.rescued[3] and res.used[3]
    assert not res.low[8] and not res.rescued[8] and not res.used[8]
    others = np.setdiff1d(ks, [3, 8])
    assert res.low[others].all() and not res.rescued[others].any()
    # All good, one hypothesis suffices (every match supports it: w = 1).
    s2, ks2, z2, pred2 = tight_scene()
    res2 = ransac(s2, ks2, z2, pred2, innovation_covariances(s2, pred2, R_pix), 1, R_pix=R_pix)
    assert res2.used.all() and res2.low.all() and res2.hypotheses == 1


def test_hypotheses_adapt_to_the_inlier_ratio_and_respect_the_cap():
    s, ks, z, pred, S_prior, out, _ = scene(3, outlier_fraction=0.5)
    res = ransac(s.copy(), ks, z, pred, S_prior, 3, max_hypotheses=4)
    assert res.hypotheses <= 4
    res = ransac(s.copy(), ks, z, pred, S_prior, 3)
    w = res.low.sum() / len(ks)
    needed = math.ceil(math.log(1 - S.ransac.confidence) / math.log(1 - w))
    assert min(needed, S.ransac.max_hypotheses, len(ks)) <= res.hypotheses <= S.ransac.max_hypotheses


def test_no_match_and_one_match():
    s, ks, z, pred = tight_scene()
    S_prior = innovation_covariances(s, pred, 1.0)
    x0, P0 = s.x.copy(), s.P.copy()
    none = ransac(s, ks[:0], z[:0], predict(s, ks[:0], CAM), S_prior[:0])
    assert none.hypotheses == 0 and none.n_inliers == 0 and np.array_equal(s.x, x0) and np.array_equal(s.P, P0)
    # One match inside its own ellipse: nothing to vote on; it is used, as update() would.
    one = ransac(s, ks[4:5], z[4:5], predict(s, ks[4:5], CAM), S_prior[4:5])
    assert one.used.all() and one.low.all()
    ref = State(x0, P0, s.cam_dim, s.kinds, s.anchors)
    update(ref, ks[4:5], z[4:5], CAM, 1.0)
    st.assert_close(s.x, ref.x, 1e-12)
    st.assert_close(s.P, ref.P, 1e-10)


def two_camera_scene(seed: int, n_a: int = 12, n_b: int = 18):
    """Matches of two self-consistent groups: ``n_a`` at the true camera's projections and
    ``n_b`` (more) at those of another camera drawn from the same prior, as a cluster of new
    features whose depths are still guesses can agree on a wrong motion. Returns the state, ks,
    z, predictions, ellipses, group A's mask and the median gap between the groups' pixels."""
    s, ks, z, pred, S_prior, _, _ = scene(seed, m=n_a + n_b, outlier_fraction=0.0, noise_px=0.2)
    rng = np.random.default_rng(1000 + seed)
    r_b, R_b = draw_camera(s, rng)
    Y = np.array([s.feature(k) for k in ks])
    a = np.zeros(len(ks), bool)
    a[rng.choice(len(ks), n_a, replace=False)] = True
    z_b = st.pixels(CAM, R_b, r_b, Y) + rng.normal(0, 0.2, (len(ks), 2))
    gap = float(np.median(np.linalg.norm(z_b - z, axis=1)))
    z = np.where(a[:, None], z, z_b)
    return s, ks, z, pred, S_prior, a, gap


def test_votes_choose_the_hypothesis_reliable_features_support():
    """A larger group of matches agreeing on a wrong camera, made by features that have failed
    most of their searches (each vote 0.25), against fewer from established features (vote 1):
    unweighted, the larger group wins; weighted by the features' records, the established one.
    A vote that is ignored, or read the wrong way round, fails."""
    tried = flipped = 0
    for seed in range(40):
        s, ks, z, pred, S_prior, a, gap = two_camera_scene(seed)
        inside = [np.linalg.solve(S_prior[i], z[i] - pred.uv[i]) @ (z[i] - pred.uv[i]) < 9 for i in range(len(ks))]
        if gap < 10.0 or not all(inside):
            continue                       # the two groups must be apart and both searchable
        tried += 1
        plain = one_point_ransac(s.copy(), ks, z, CAM, 1.0, pred, S_prior,
                                 RansacSettings(S.ransac.threshold_px, len(ks), 1 - 1e-12, RESCUE_99),
                                 np.random.default_rng(seed))
        votes = np.where(a, 1.0, 0.25)
        # Every match tried as a hypothesis (the adaptive count could stop before drawing one of the
        # smaller group: that is the sampling's chance, not the vote's).
        weighted = one_point_ransac(s, ks, z, CAM, 1.0, pred, S_prior,
                                    RansacSettings(S.ransac.threshold_px, len(ks), 1 - 1e-12, RESCUE_99),
                                    np.random.default_rng(seed), votes=votes)
        assert np.array_equal(weighted.used, a), (seed, gap)
        flipped += np.array_equal(plain.used, ~a)
    print(f"\ntwo groups apart in {tried} scenes; unweighted, the larger wrong group won in {flipped}")
    assert tried >= 8 and flipped >= tried // 2


def test_the_tracker_votes_by_each_features_record():
    """The tracker's votes (measure.Measurement.votes): inlier matches + 1 over searches + 2, so a
    feature at its first search votes a third and one matched in 60 of 60 nearly 1, and the
    votes follow the features asked for, in their order; a corner the target's sides placed
    this frame votes ``known_vote``."""
    from runtime.slam.config import MapSettings
    from runtime.slam.measure import Measurement
    from runtime.slam.map_feature import MapFeature

    measurement = Measurement(CAM, MapSettings(), 1.0, 0, None)
    records = [(1, 0), (60, 60), (10, 5), (4, 1)]
    features = [MapFeature(i, np.zeros((5, 5), np.float32), 0, np.zeros(3), attempts=a, successes=s)
                for i, (a, s) in enumerate(records)]
    np.testing.assert_allclose(measurement.votes(features, np.array([0, 1, 2, 3])), [1 / 3, 61 / 62, 0.5, 1 / 3])
    np.testing.assert_allclose(measurement.votes(features, np.array([3, 1])), [1 / 3, 61 / 62])
    # A target corner placed by the target's sides this frame votes MapSettings.ransac.known_vote.
    measurement.settings = MapSettings(known_vote=5.0)
    np.testing.assert_allclose(measurement.votes(features, np.array([3, 1, 2]), np.array([True, False, False])),
                               [5.0, 61 / 62, 0.5])
    np.testing.assert_allclose(measurement.votes(features, np.array([3, 1]), np.array([False, False])), [1 / 3, 61 / 62])
    with pytest.raises(ValueError, match="known_vote"):
        MapSettings(known_vote=0.0)                   # RANSAC takes positive votes only


def test_updates_refused_before_they_are_written_leave_the_state_as_it_was():
    """``accept`` sees the frame's updates before the state does: the mean and the variances it
    is shown are the ones a commit writes; refused, the state is bit for bit as before and no
    match is used; accepted, the result is RANSAC's without the hook."""
    s, ks, z, pred, S_prior, out, _ = scene(3)
    x0, P0 = s.x.copy(), s.P.copy()
    seen = []

    def look(fu):
        seen.append((fu.x.copy(), fu.variances(slice(0, 13))))
        return False

    res = one_point_ransac(s, ks, z, CAM, 1.0, pred, S_prior, replace(S.ransac, rescue_chi2=RESCUE_99),
                           np.random.default_rng(0), accept=look)
    assert res.refused and not res.used.any() and len(seen) == 1
    assert np.array_equal(s.x, x0) and np.array_equal(s.P, P0)
    plain = s.copy()
    res_plain = ransac(plain, ks, z, pred, S_prior, 0)
    res_ok = one_point_ransac(s, ks, z, CAM, 1.0, pred, S_prior, replace(S.ransac, rescue_chi2=RESCUE_99),
                              np.random.default_rng(0), accept=lambda fu: True)
    assert not res_ok.refused and np.array_equal(res_ok.used, res_plain.used) and res_plain.used.any()
    assert np.array_equal(s.x, plain.x) and np.array_equal(s.P, plain.P)
    x_seen, var_seen = seen[0]
    np.testing.assert_array_equal(x_seen, plain.x)
    keep = np.r_[0:3, 7:13]                    # the quaternion's rows change at the commit's normalisation
    np.testing.assert_allclose(var_seen[keep], np.diag(plain.P)[keep], rtol=1e-9)
    assert (var_seen[keep] < np.diag(P0)[keep]).all()
