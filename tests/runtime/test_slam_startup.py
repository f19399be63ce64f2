"""Start-up from the known target (startup.py) on ray-cast images of a printed rectangle (the
twin's black rectangle on a white card, 21 x 15 cm) whose corners' true pixels are known: a
person's clicks 2-3 px off are refined to within 0.3 px, a click on a plain area or pixels that
fit no pose are refused, the pose covariance is honest (Monte Carlo NEES against its chi-square
band), and a small far frontal target keeps both planar poses while a near oblique one keeps one."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import slam_testing as st
from runtime.sequence import Target
from runtime.slam.config import MapSettings
from runtime.slam.quaternion import quat_to_rotation
from runtime.slam.startup import SlamStartError, pose_hypotheses, refine_clicks, start_hypotheses
from runtime.slam.system import MonoSLAM

CAM = st.PINHOLE
S = MapSettings()
SU = S.startup                    # the start-up's settings (click search, corner fit, ambiguity)
RECT = st.rectangle(0.21, 0.15)
CARD_MARGIN = 0.03


VIEWS = {
    "near oblique": st.viewpoint(0.45, 50.0),        # 0.45 m, 40 degrees from frontal
    "far oblique": st.viewpoint(1.3, 55.0, -60.0),
    "far frontal": st.viewpoint(1.3, 87.0),          # 1.3 m, 3 degrees from frontal: ~80 px wide
}


@lru_cache(maxsize=None)
def scene(name: str) -> tuple[np.ndarray, np.ndarray]:
    """The image of a view (textured background) and the corners' true pixels."""
    R, r = VIEWS[name]
    img = st.render_target_scene(CAM, R, r, RECT, card_margin=CARD_MARGIN, background=st.texture(1))
    return img, st.pixels(CAM, R, r, RECT)


def clicks(uv: np.ndarray, rng, lo: float = 2.0, hi: float = 3.0) -> np.ndarray:
    """The corners as a person clicks them: each ``lo`` to ``hi`` px off in a random direction."""
    a = rng.uniform(0, 2 * np.pi, len(uv))
    return uv + rng.uniform(lo, hi, (len(uv), 1)) * np.column_stack([np.cos(a), np.sin(a)])


# -- finding the corners -----------------------------------------------------------------------

@pytest.mark.parametrize("view", list(VIEWS))
def test_clicks_2_to_3_px_off_are_refined_to_0_3_px(view):
    img, uv = scene(view)
    rng = np.random.default_rng(1)
    errors = []
    exact = refine_clicks(img, Target(RECT, uv), SU.click_search_px)
    for _ in range(6):
        z = clicks(uv, rng)
        ref = refine_clicks(img, Target(RECT, z), SU.click_search_px)
        errors.append(np.linalg.norm(ref.uv - uv, axis=1))
        # The click's error is gone, not only reduced: exact clicks find the same corners.
        np.testing.assert_allclose(ref.uv, exact.uv, atol=1e-6)
        np.testing.assert_allclose(ref.moved_px, np.linalg.norm(ref.uv - z, axis=1), atol=1e-9)
        assert np.array_equal(ref.xyz, RECT)
    errors = np.array(errors)
    print(f"\n{view}: refined corners {np.median(errors):.3f} px from the truth (median), worst {errors.max():.3f}")
    assert errors.max() < 0.3
    # The clicks were 2-3 px off: the refinement moved them that far.
    assert np.median(errors) < 0.25


def test_refusals_name_the_problem():
    img, uv = scene("near oblique")
    card_corners = st.pixels(CAM, *VIEWS["near oblique"], st.rectangle(0.21 + 2 * CARD_MARGIN, 0.15 + 2 * CARD_MARGIN))
    cases = {
        # A click on the middle of the black rectangle: no corner there.
        "plain": (RECT, np.r_[uv[:3], uv.mean(axis=0, keepdims=True)], r"no corner within 6 px of point 3's click"),
        # One click on the card's outer corner instead of the rectangle's: a corner, but the
        # four make no consistent pose.
        "card corner": (RECT, np.r_[card_corners[:1], uv[1:]],
                        r"do not fit one camera pose \(reprojection RMS [0-9.]+ px > 1.5\)"),
        # The card's corners given as the rectangle's geometry: a wrong print size.
        "wrong size": (st.rectangle(0.21, 0.10), uv, r"do not fit one camera pose"),
        # xyz in another order than the clicks.
        "order": (RECT[[1, 0, 2, 3]], uv, r"(no camera pose in front|do not fit one camera pose)"),
        "border": (RECT, np.r_[uv[:3], [[2.0, 100.0]]],
                   r"point 3 at pixel \(2.0, 100.0\) is at or beyond the image border"),
        "line": (np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]], float), uv, r"on a line"),
    }
    for name, (xyz, z, message) in cases.items():
        with pytest.raises(SlamStartError, match=message):
            start_hypotheses(CAM, img, Target(xyz, z), SU.click_search_px, SU.start_pixel_sigma, SU.start_max_rms_px,
                             SU.ambiguity_ratio)
    # MonoSLAM.start refuses the same way, and has not started.
    slam = MonoSLAM(CAM)
    with pytest.raises(SlamStartError, match="no corner within"):
        slam.start(img, 0.0, Target(RECT, cases["plain"][1]))
    assert not slam.started
    # A plain image, whatever the clicks.
    with pytest.raises(SlamStartError, match="no corner within"):
        refine_clicks(np.full_like(img, 128), Target(RECT, uv), SU.click_search_px)


# -- the pose and its uncertainty --------------------------------------------------------------

def pose_nees(view: str, trials: int, seed: int, sigma_px: float = 0.5, nearest: bool = False) -> np.ndarray:
    """NEES (6 dof: small rotation in the camera frame, position) of the best pose hypothesis (or
    the one nearest the truth) over ``trials`` draws of pixel noise ``sigma_px`` on the true
    corners, against the hypothesis' own covariance."""
    R_true, r_true = VIEWS[view]
    uv = st.pixels(CAM, R_true, r_true, RECT)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(trials):
        hyps = pose_hypotheses(CAM, RECT, uv + rng.normal(0, sigma_px, uv.shape), sigma_px, SU.ambiguity_ratio)
        nees = []
        for h in hyps:
            e = np.r_[Rotation.from_matrix(h.R_world_cam.T @ R_true).as_rotvec(), r_true - h.r]
            nees.append(e @ np.linalg.solve(h.cov, e))
        out.append(min(nees) if nearest else nees[0])
    return np.array(out)


@pytest.mark.parametrize("view", ["near oblique", "far oblique"])
def test_pose_covariance_is_honest(view):
    nees = pose_nees(view, 100, 3)
    lo, hi = st.chi2_band(6, len(nees))
    print(f"\n{view}: pose NEES {nees.mean():.2f}, 95% band [{lo:.2f}, {hi:.2f}]")
    assert lo < nees.mean() < hi
    # A covariance off by a factor of 2 in standard deviation is far outside.
    assert not (lo < nees.mean() / 4 < hi) and not (lo < 4 * nees.mean() < hi)


@pytest.mark.xfail(strict=True, reason="startup.pose_hypotheses' covariance (sigma^2 (J^T J)^-1 at each IPPE pose) "
                   "is about 6x overconfident for a small, far, nearly frontal target (NEES ~35 for 6 dof at 1.3 m, "
                   "3 degrees from frontal, even scoring the hypothesis nearest the truth): the issue's 'start locks "
                   "that error in with a small covariance' case")
def test_pose_covariance_is_honest_for_a_far_frontal_target():
    nees = pose_nees("far frontal", 100, 4, nearest=True)
    lo, hi = st.chi2_band(6, len(nees))
    print(f"\nfar frontal: pose NEES {nees.mean():.2f} (nearest hypothesis), 95% band [{lo:.2f}, {hi:.2f}]")
    assert lo < nees.mean() < hi


def test_a_far_frontal_target_keeps_both_planar_poses_a_near_oblique_one_keeps_one():
    for view, expected in (("far frontal", 2), ("near oblique", 1), ("far oblique", 1)):
        img, uv = scene(view)
        R_true, r_true = VIEWS[view]
        ref, hyps = start_hypotheses(CAM, img, Target(RECT, clicks(uv, np.random.default_rng(5))), SU.click_search_px,
                                     SU.start_pixel_sigma, SU.start_max_rms_px, SU.ambiguity_ratio)
        assert len(hyps) == expected, (view, [h.chi2 for h in hyps])
        assert hyps[0].chi2 <= hyps[-1].chi2
        # Each explains the refined corners (RMS within the start's limit) ...
        assert all(h.rms_px < SU.start_max_rms_px for h in hyps)
        # ... one of them is the true pose, and they are genuinely different poses.
        err = [np.linalg.norm(h.r - r_true) for h in hyps]
        assert min(err) < 0.02 * np.linalg.norm(r_true)
        if expected == 2:
            assert np.linalg.norm(hyps[0].r - hyps[1].r) > 0.01
            assert st.rotation_error_rad(hyps[0].R_world_cam, hyps[1].R_world_cam) > np.radians(2)
        # MonoSLAM starts one track per hypothesis, each with the four target points.
        slam = MonoSLAM(CAM)
        slam.start(img, 0.0, Target(RECT, clicks(uv, np.random.default_rng(5))))
        assert len(slam._tracks) == expected and slam.stats[0].hypotheses == expected
        assert slam.state.n_features == 4 and all(f.known for f in slam.features)
        np.testing.assert_allclose(slam.refined_target.uv, ref.uv, atol=1e-9)
        T = slam.T_world_cam()
        np.testing.assert_allclose(T[:3, 3], hyps[0].r, atol=1e-12)
        np.testing.assert_allclose(T[:3, :3], hyps[0].R_world_cam, atol=1e-9)


def test_camera_prior_maps_the_pose_covariance_into_the_state():
    """The camera block's position and quaternion covariance is the pose covariance pushed
    through q(R Exp(theta)): sampled poses' quaternions have that covariance."""
    R, r = VIEWS["near oblique"]
    h = pose_hypotheses(CAM, RECT, st.pixels(CAM, R, r, RECT), 0.5, SU.ambiguity_ratio)[0]
    x_v, P = h.camera_prior(0.3, 0.5, 19)
    assert x_v.shape == (19,) and P.shape == (19, 19)
    np.testing.assert_allclose(quat_to_rotation(x_v[3:7]), h.R_world_cam, atol=1e-12)
    np.testing.assert_allclose(x_v[:3], h.r)
    np.testing.assert_allclose(np.diag(P)[7:13], [0.09] * 3 + [0.25] * 3)
    rng = np.random.default_rng(6)
    d = rng.multivariate_normal(np.zeros(6), h.cov, 20000)
    q = (Rotation.from_matrix(h.R_world_cam) * Rotation.from_rotvec(d[:, :3])).as_quat()[:, [3, 0, 1, 2]]
    q *= np.sign(q @ x_v[3:7])[:, None]
    samples = np.column_stack([h.r + d[:, 3:], q])
    C = np.cov(samples.T)
    np.testing.assert_allclose(C, P[:7, :7], atol=0.05 * np.abs(P[:7, :7]).max())
    np.testing.assert_allclose(np.diag(C), np.diag(P[:7, :7]), rtol=0.05)


# -- IMU biases from a still stretch before the first frame --------------------------------------

def _still_rows(R_world_cam, b_g, b_a, seconds, rng, t_end=0.0, rate=200.0, wobble=0.0):
    """IMU rows ending at ``t_end``: a still camera (its specific force gravity seen from
    ``R_world_cam``), with biases, white noise and an optional rate wobble (rad/s)."""
    from runtime.slam.config import SlamConfig

    cfg = SlamConfig()
    t = t_end - np.arange(int(seconds * rate), -1, -1) / rate
    f = R_world_cam.T @ np.array([0.0, 0.0, 9.81])
    w = b_g + rng.normal(0, cfg.imu.imu_gyro_noise * np.sqrt(rate), (len(t), 3)) \
        + wobble * np.sin(2 * np.pi * 1.5 * t)[:, None]
    a = f + b_a + rng.normal(0, cfg.imu.imu_accel_noise * np.sqrt(rate), (len(t), 3))
    return np.column_stack([t, w, a])


def test_a_still_stretch_before_the_start_gives_the_biases(view="near oblique"):
    img, uv = scene(view)
    R, _ = VIEWS[view]
    rng = np.random.default_rng(5)
    b_g, b_a = np.array([0.004, -0.006, 0.003]), np.array([0.08, -0.05, 0.06])
    target = Target(RECT, uv + rng.normal(0, 1.0, uv.shape))
    slam = MonoSLAM(CAM, imu=True)
    slam.add_imu(_still_rows(R, b_g, b_a, 1.0, rng))
    slam.start(img, 0.0, target)
    s = slam.state
    sd_g, sd_a = np.sqrt(np.diag(s.P)[13:16]), np.sqrt(np.diag(s.P)[16:19])
    assert slam.still is not None and slam.still.seconds == pytest.approx(1.0, abs=0.01)
    assert np.all(np.abs(s.b_g - b_g) < 3 * sd_g) and np.all(sd_g < 0.1 * slam.cfg.imu.gyro_bias_sigma0)
    # The accelerometer's bias rests on the start's attitude (its error times g): within its
    # sigma of the truth, and correlated with the attitude so that, the attitude known, it is
    # known far better than the part's prior.
    assert np.all(np.abs(s.b_a - b_a) < 3 * sd_a)
    P = s.P
    cond = P[16:19, 16:19] - P[16:19, 3:7] @ np.linalg.pinv(P[3:7, 3:7], rcond=1e-10) @ P[3:7, 16:19]
    assert np.all(np.sqrt(np.diag(cond)) < 0.1 * slam.cfg.imu.accel_bias_sigma0)
    assert np.all(np.sqrt(np.diag(cond)) < 0.5 * sd_a)
    assert any("still" in m for m in slam.messages)


@pytest.mark.parametrize("seconds, wobble", [(0.1, 0.0), (1.0, 0.05)])
def test_no_still_stretch_keeps_the_parts_prior(seconds, wobble, view="near oblique"):
    img, uv = scene(view)
    R, _ = VIEWS[view]
    rng = np.random.default_rng(6)
    slam = MonoSLAM(CAM, imu=True)
    slam.add_imu(_still_rows(R, np.array([0.004, 0.0, 0.0]), np.zeros(3), seconds, rng, wobble=wobble))
    slam.start(img, 0.0, Target(RECT, uv))
    s = slam.state
    assert slam.still is None
    np.testing.assert_allclose(np.sqrt(np.diag(s.P)[13:16]), slam.cfg.imu.gyro_bias_sigma0)
    np.testing.assert_allclose(s.b_g, 0.0)


# -- the printed quadrilateral's sides -----------------------------------------------------------

@pytest.mark.parametrize("view", list(VIEWS))
def test_the_sides_place_the_corners_better_than_the_corner_fit(view):
    """On the ray-cast views with the sensor's noise added: the corners from the sides' edge
    lines lie within 0.1 px of the truth (the corner fit alone: up to 0.3)."""
    from runtime.slam.startup import refine_by_edges

    img, uv = scene(view)
    rng = np.random.default_rng(7)
    errs_c, errs_e = [], []
    for _ in range(4):
        noisy = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
        ref = refine_clicks(noisy, Target(RECT, clicks(uv, rng)), SU.click_search_px)
        edged = refine_by_edges(CAM, noisy, ref.uv)
        assert edged is not None
        errs_c.append(np.linalg.norm(ref.uv - uv, axis=1))
        errs_e.append(np.linalg.norm(edged - uv, axis=1))
    errs_c, errs_e = np.array(errs_c), np.array(errs_e)
    print(f"\n{view}: corner fit median {np.median(errs_c):.3f} px, sides {np.median(errs_e):.3f} px "
          f"(worst {errs_c.max():.3f}, {errs_e.max():.3f})")
    assert errs_e.max() < 0.1 and np.median(errs_e) < np.median(errs_c)


@pytest.mark.parametrize("view", [(1.6, 20.0, -20.0), (2.2, 22.0, -35.0)])
def test_a_small_grazing_target_starts_from_its_sides_where_the_corner_fit_is_pixels_off(view):
    """A far target seen at a grazing angle (25 x 66 px, as the walker's first view of the bench):
    corner fits of its acute corners sit 1.5-3 px inside them, beyond the sides' per-frame
    shift limit; the start takes the sides' corners all the same (within 0.2 px of the truth),
    where keeping the corner fits started 2-14 cm off or refused the start."""
    R, r = st.viewpoint(*view)
    img = st.render_target_scene(CAM, R, r, RECT, card_margin=CARD_MARGIN, background=st.texture(1))
    uv = st.pixels(CAM, R, r, RECT)
    rng = np.random.default_rng(2)
    for _ in range(3):
        target = Target(RECT, clicks(uv, rng))
        corner_fit = refine_clicks(img, target, SU.click_search_px)
        assert np.linalg.norm(corner_fit.uv - uv, axis=1).max() > 1.5       # the case this is about
        ref, hyps = start_hypotheses(CAM, img, target, SU.click_search_px, SU.start_pixel_sigma, SU.start_max_rms_px,
                                     SU.ambiguity_ratio)
        assert np.linalg.norm(ref.uv - uv, axis=1).max() < 0.2
        assert hyps[0].rms_px < 0.2


@pytest.mark.parametrize("lens", ["brown", "fisheye"])
def test_the_sides_follow_a_distorted_lens(lens):
    """Through a strongly distorted lens the sides are curves; fitted as lines after undistortion
    they still give the corners within 0.1 px; not a quadrilateral or no edge: None."""
    from runtime.slam.startup import refine_by_edges

    cam = st.CAMERAS[lens]
    R, r = st.viewpoint(0.5, 60.0)
    img = st.render_target_scene(cam, R, r, RECT, card_margin=CARD_MARGIN, background=st.texture(1))
    uv = st.pixels(cam, R, r, RECT)
    ref = refine_clicks(img, Target(RECT, clicks(uv, np.random.default_rng(3))), SU.click_search_px)
    edged = refine_by_edges(cam, img, ref.uv)
    assert edged is not None and np.linalg.norm(edged - uv, axis=1).max() < 0.1
    assert refine_by_edges(cam, img, ref.uv[[0, 2, 1, 3]]) is None                 # a bow tie
    flat = np.full_like(img, 128)
    assert refine_by_edges(cam, flat, ref.uv) is None


@pytest.mark.parametrize("missing, off", [(2, 3), (None, 1)])
def test_the_sides_place_a_corner_its_template_missed_or_matched_pixels_off(missing, off):
    """A template cut from a small far view matches the near target a few pixels off or not at
    all; with three of the four found, every frame's sides still place all four (within 0.05 px
    of the truth): the missing one from its prediction (2 px off), the one matched 3 px off
    moved back, beyond the 1.5 px a side's fit may move a well-matched corner."""
    from runtime.slam.config import DEFAULT_CONFIG

    R0, r0 = st.viewpoint(0.6, 60.0)
    img0 = st.render_target_scene(CAM, R0, r0, RECT, card_margin=CARD_MARGIN, background=st.texture(1))
    slam = MonoSLAM(CAM, DEFAULT_CONFIG, S, imu=False)
    slam.start(img0, 0.0, Target(RECT, st.pixels(CAM, R0, r0, RECT)))
    R1, r1 = st.viewpoint(0.55, 55.0, -75.0)
    g = st.render_target_scene(CAM, R1, r1, RECT, card_margin=CARD_MARGIN, background=st.texture(1)).astype(np.float32)
    truth = st.pixels(CAM, R1, r1, RECT)
    feats = slam.features[:4]
    assert all(f.known for f in feats)
    z = truth.copy()
    z[off] += [2.4, -1.8]                                   # 3 px off
    if missing is not None:
        z[missing] = np.nan
    placed = slam.track.measurement.known_by_edges(g, feats, z, truth + [1.5, 1.3])
    assert np.isfinite(z).all() and np.linalg.norm(z - truth, axis=1).max() < 0.05
    assert placed.tolist() == [True] * 4                   # what RANSAC's vote weighs (_votes)
    # Two found: the sides are not fitted, nothing is placed and z is left to the templates.
    z2 = truth.copy()
    z2[:2] = np.nan
    assert not slam.track.measurement.known_by_edges(g, feats, z2, truth).any() and np.isnan(z2[:2]).all()


@pytest.mark.parametrize("move", [(0.02, 6.0, 4.0), (-0.03, -5.0, 6.0)])
def test_the_target_is_measured_by_its_sides_every_frame(move):
    """After the start, each frame's match of the target's corners comes from its fitted sides:
    within 0.02 px of the truth on a view the camera moved to (range m, elevation and azimuth
    deg), where the corners' templates, cut at the start and warped by the predicted pose, miss
    by 0.04-0.16 px (``known_edges`` off)."""
    from dataclasses import replace

    from runtime.slam.config import DEFAULT_CONFIG

    def measured(edges: bool) -> np.ndarray:
        R0, r0 = st.viewpoint(0.6, 60.0)
        img0 = st.render_target_scene(CAM, R0, r0, RECT, card_margin=CARD_MARGIN, background=st.texture(1))
        slam = MonoSLAM(CAM, DEFAULT_CONFIG, replace(S, known_edges=edges), imu=False)
        slam.start(img0, 0.0, Target(RECT, st.pixels(CAM, R0, r0, RECT) + 1.5))
        R1, r1 = st.viewpoint(0.6 + move[0], 60.0 + move[1], -80.0 + move[2])
        slam.process(st.render_target_scene(CAM, R1, r1, RECT, card_margin=CARD_MARGIN, background=st.texture(1)),
                     1 / 30)
        last = slam.track.last
        z = np.array([last.z[list(last.ids).index(i)] for i in range(4)])
        return np.linalg.norm(z - st.pixels(CAM, R1, r1, RECT), axis=1)

    by_sides, by_templates = measured(True), measured(False)
    print(f"\nsides {by_sides.max():.3f} px, templates {by_templates.max():.3f} px (worst corner)")
    assert by_sides.max() < 0.02 < by_templates.max()


# -- deciding between the two planar poses ----------------------------------------------------

def test_the_start_evidence_counts_the_targets_points_and_no_track_s_own_features():
    """Two tracks' natural features are each placed from its own pose, and miss by chance: a
    natural feature's miss or outlier changes nothing; a target point's costs the gate, and a
    matched one its capped NIS."""
    from runtime.slam.measure import start_evidence

    gate = SU.ambiguity_gate_chi2
    d2 = np.array([1.0, 30.0, 0.0, 2.0, 0.5])
    used = np.array([True, True, False, True, False])
    known = np.array([True, True, True, False, False])
    assert start_evidence(d2, used, known, gate) == pytest.approx(-0.5 * (1.0 + gate + gate))
    # A natural feature's miss (the fourth) or a natural feature's large innovation: the same.
    assert start_evidence(d2, np.array([True, True, False, False, False]), known, gate) == \
        start_evidence(d2, used, known, gate)
    assert start_evidence(np.array([1.0, 30.0, 0.0, 50.0, 0.5]), used, known, gate) == \
        start_evidence(d2, used, known, gate)
    # No target point searched: no evidence either way.
    assert start_evidence(d2, used, np.zeros(5, bool), gate) == 0.0
