"""Guided search (guided.guided_regions): the first features' matches give the rest posterior
search regions. Checked against the filter itself: an EKF update with those matches, then the
rest predicted, must give the same predictions and ellipses (to first order), an outlier among
the first must be left out, and too few agreeing matches must leave the rest unguided."""

from __future__ import annotations

import numpy as np
from test_slam_ransac import CAM, scene

from runtime.slam.config import RansacSettings
from runtime.slam.filter import innovation_covariances, update
from runtime.slam.guided import guided_regions
from runtime.slam.measurement import predict

RANSAC = RansacSettings()


def _oracle(s, ks, z, used):
    """The rest's predictions and ellipses after a real EKF update with the matches ``used``."""
    o = s.copy()
    update(o, ks[used], z[used], CAM, 1.0)
    rest = np.setdiff1d(ks, ks[:10])
    p = predict(o, rest, CAM)
    return p.uv, innovation_covariances(o, p, 1.0)


def test_the_rest_are_predicted_as_after_an_ekf_update_with_the_first():
    shifts, shrink = [], []
    for seed in range(8):
        s, ks, z, pred, S_prior, _, _ = scene(seed, outlier_fraction=0.0)
        first = np.arange(10)
        g = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=0.0)
        assert g is not None and g.used.all()
        uv_o, S_o = _oracle(s, ks, z, first[g.used])
        rest = np.arange(10, len(ks))
        # First order: the same as the update (which relinearises the rest at the new mean).
        np.testing.assert_allclose(g.uv, uv_o, atol=0.1)
        np.testing.assert_allclose(np.linalg.det(g.S) / np.linalg.det(S_o), 1.0, atol=0.06)   # the ellipses' areas
        np.testing.assert_allclose(np.diagonal(g.S, axis1=1, axis2=2), np.diagonal(S_o, axis1=1, axis2=2), rtol=0.04)
        shifts.append(np.median(np.linalg.norm(uv_o - pred.uv[rest], axis=1)))
        shrink.append(np.median(np.linalg.det(g.S) / np.linalg.det(S_prior[rest])))
        # The true matches lie in the guided 3-sigma ellipses.
        nu = z[rest] - g.uv
        d2 = np.einsum("ia,iab,ib->i", nu, np.linalg.inv(g.S), nu)
        assert (d2 < 9.0).mean() >= 0.95
    # Not a no-op: the guidance moved the predictions and shrank the ellipses.
    assert np.median(shifts) > 0.5 and np.median(shrink) < 0.3


def test_an_outlier_among_the_first_is_left_out():
    for seed in range(6):
        s, ks, z, pred, S_prior, out, _ = scene(seed, outlier_fraction=0.3)
        first = np.arange(10)
        g = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=0.0)
        good = first[~out[first]]
        assert out[first].any() and g is not None
        assert np.array_equal(g.used, ~out[first])
        uv_o, _ = _oracle(s, ks, z, first[g.used])
        np.testing.assert_allclose(g.uv, uv_o, atol=0.1)


def test_too_few_agreeing_matches_leave_the_rest_unguided():
    s, ks, z, pred, S_prior, _, _ = scene(0, outlier_fraction=0.0)
    first = np.arange(10)
    zf = z[first].copy()
    zf[2:] = np.nan                               # two found: below the three needed
    assert guided_regions(s, pred, S_prior, first, zf, RANSAC, floor_px=0.0) is None
    g = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=1.5)
    g0 = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=0.0)
    np.testing.assert_allclose(g.S - g0.S, np.broadcast_to(1.5 ** 2 * np.eye(2), g.S.shape))


def _measurement(width=640, **measure):
    from dataclasses import replace

    from kinematics.camera import default_camera
    from runtime.slam.config import MapSettings
    from runtime.slam.measure import Measurement

    cam = default_camera()
    cam = replace(cam, width=width, cx=width / 2)
    s = MapSettings()
    return Measurement(cam, replace(s, measure=replace(s.measure, **measure)), 1.0, 0, None), s


def test_when_most_ellipses_pass_the_cap_the_smallest_are_searched_to_guide_the_rest():
    m, s = _measurement()
    cap, n_first = s.views.max_search_area_px, s.measure.guide_first
    rng = np.random.default_rng(3)
    area = cap * rng.uniform(1.2, 4.0, 40)         # the camera's motion unknown: every ellipse over the cap
    area[[5, 9]] = 0.5 * cap                       # two under it
    area[7] = np.nan                               # one not predicted
    ok = np.isfinite(area) & (area <= cap)
    g = m._rescue_guides(area, ok)
    assert len(g) == n_first and {5, 9} <= set(g.tolist())
    over = np.setdiff1d(g, [5, 9])
    finite_over = np.flatnonzero(np.isfinite(area) & ~ok)
    assert np.all(area[over].max() <= np.delete(area, g)[np.isfinite(np.delete(area, g))].min())  # the smallest
    assert set(over.tolist()) <= set(finite_over.tolist())
    # Up to rescue_area_px (scaled with the image's width): none so small, no rescue.
    area2 = area.copy()
    area2[finite_over] = s.measure.rescue_area_px * 1.01
    assert m._rescue_guides(area2, ok) is None
    wide, _ = _measurement(width=1280)
    assert len(wide._rescue_guides(area2, ok)) == n_first          # 4x the cap at twice the width


def test_no_rescue_while_most_ellipses_are_searchable_or_enough_are():
    m, s = _measurement()
    cap, n_first = s.views.max_search_area_px, s.measure.guide_first
    area = np.full(30, 2.0 * cap)
    area[:16] = 0.1 * cap                          # most under the cap: a few young features' long ellipses
    assert m._rescue_guides(area, area <= cap) is None
    area = np.full(60, 2.0 * cap)
    area[:n_first] = 0.1 * cap                     # enough to guide, though most are over
    assert m._rescue_guides(area, area <= cap) is None
    off, _ = _measurement(guide_first=0)
    area = np.full(30, 2.0 * cap)
    assert off._rescue_guides(area, area <= cap) is None
    assert len(m._rescue_guides(area, area <= cap)) == n_first


def _plane_view(cam, tex, tx: float, depth: float = 2.0, px_per_m: float = 400.0) -> np.ndarray:
    """(H, W) float32: the textured plane z = ``depth`` m seen by a camera looking along +z from
    (``tx``, 0, 0) m (the texture's centre at the world's origin)."""
    import cv2

    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float32), np.arange(cam.height, dtype=np.float32))
    c = tex.shape[0] / 2
    mx = ((u - cam.cx) / cam.fx * depth + tx) * px_per_m + c
    my = (v - cam.cy) / cam.fy * depth * px_per_m + c
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR)


def test_a_frame_whose_ellipses_all_pass_the_cap_is_still_searched_and_matched():
    """The camera moved 0.15 m (about 39 px) while the filter, its velocity unknown, allows 0.2 m
    sd: every ellipse is over the search cap. The rescue's guides are found and the rest are
    searched in their guided regions; with the rescue off nothing is searched."""
    from dataclasses import replace

    from kinematics.camera import default_camera
    from runtime.slam.appearance.patch import extract_template
    from runtime.slam.config import MapSettings
    from runtime.slam.map_feature import MapFeature
    from runtime.slam.measure import Measurement
    from runtime.slam.views import SlamMap
    from slam_testing import state_with_points, texture

    cam, depth, tx = default_camera(), 2.0, 0.15
    tex = texture(seed=4, size=1536, blur=2.0)
    g0, g1 = _plane_view(cam, tex, 0.0), _plane_view(cam, tex, tx)
    uv0 = np.stack(np.meshgrid(np.linspace(110, 530, 6), np.linspace(90, 390, 5)), -1).reshape(-1, 2)
    X = np.column_stack([(uv0[:, 0] - cam.cx) / cam.fx * depth, (uv0[:, 1] - cam.cy) / cam.fy * depth,
                         np.full(len(uv0), depth)])
    truth = uv0 - [tx * cam.fx / depth, 0.0]
    for rescue_px, expect_found in ((MapSettings().measure.rescue_area_px, True), (0.0, False)):
        state = state_with_points(np.eye(4), X, sigma_xyz=0.2, sigma_q=1e-4, sigma_point=1e-3)
        feats = [MapFeature(i, extract_template(g0, uv, 15), 0, np.zeros(3), last_seen=0) for i, uv in enumerate(uv0)]
        s = MapSettings()
        ms = Measurement(cam, replace(s, measure=replace(s.measure, rescue_area_px=rescue_px)), 1.0, 0, None)
        pred, S, _, visible, _, z = ms.search(g1, SlamMap(state, feats))
        area = 9 * np.pi * np.sqrt(np.linalg.det(S)) if len(S) else np.zeros(0)
        assert visible == len(uv0)
        if not expect_found:
            assert len(pred.ks) == 0 and ms.over_cap == 0
            continue
        assert ms.over_cap == s.measure.guide_first and ms.guided == len(uv0) - s.measure.guide_first
        assert np.all(area > s.views.max_search_area_px)           # every prior ellipse over the cap
        found = np.isfinite(z).all(axis=1)
        assert found.sum() >= 27
        np.testing.assert_allclose(z[found], truth[pred.ks[found]], atol=0.5)


def test_an_ellipse_chosen_by_its_area_whose_box_passes_the_cap_is_not_searched_and_is_counted():
    """The stated rule between the choice and the search: a feature is chosen while its 3-sigma
    ellipse's area is within the search cap, and searched while the box around the ellipse is. A
    thin ellipse at 45 degrees (a young feature's ray across the image) has a small area and a
    large box: chosen, not searched, counted in ``outgrown``; the same shape shorter, and a round
    one, are searched and found where they are."""
    from dataclasses import replace

    from kinematics.camera import default_camera
    from runtime.slam.appearance.patch import extract_template
    from runtime.slam.config import MapSettings
    from runtime.slam.map_feature import MapFeature
    from runtime.slam.measure import Measurement
    from runtime.slam.views import SlamMap
    from slam_testing import state_with_points, texture

    cam, depth = default_camera(), 2.0
    g = _plane_view(cam, texture(seed=5, size=1536, blur=2.0), 0.0)
    uv = np.array([[200.0, 150.0], [420.0, 300.0], [320.0, 240.0]])
    X = np.column_stack([(uv[:, 0] - cam.cx) / cam.fx * depth, (uv[:, 1] - cam.cy) / cam.fy * depth,
                         np.full(len(uv), depth)])
    feats = [MapFeature(i, extract_template(g, p, 15), 0, np.zeros(3), last_seen=0) for i, p in enumerate(uv)]
    m = SlamMap(state_with_points(np.eye(4), X), feats)
    s = MapSettings()
    cap = s.views.max_search_area_px
    R45 = np.array([[1.0, -1.0], [1.0, 1.0]]) / np.sqrt(2.0)
    thin = lambda major: R45 @ np.diag([major**2, 3.0**2]) @ R45.T     # noqa: E731
    S = np.array([thin(60.0), thin(40.0), np.eye(2) * 3.0**2])
    area = 9 * np.pi * np.sqrt(np.linalg.det(S))
    box = np.prod(2 * 3 * np.sqrt(S[:, [0, 1], [0, 1]]) + 1, axis=1)
    assert np.all(area <= cap) and box[0] > cap and box[1] <= cap       # the case as stated
    pred_uv = uv + [[4.0, -3.0], [-5.0, -5.0], [2.0, 1.0]]               # predictions off the truth
    ms = Measurement(cam, replace(s), 1.0, 0, None)
    z, found = ms._match(g, m, feats, np.zeros(3, bool), X, pred_uv, S)
    assert ms.outgrown == 1
    assert not found[0] and np.isnan(z[0]).all()
    assert found[1:].all()
    np.testing.assert_allclose(z[1:], uv[1:], atol=0.5)
