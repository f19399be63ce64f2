"""Active search, new features and template warping against synthetic images with known
answers."""

from functools import lru_cache

import cv2
import numpy as np
import pytest

import slam_testing as st
from runtime.slam.corners import HALF_RESOLUTION_FROM_WIDTH, find_new_corners, grey, new_features
from runtime.slam.appearance import extract_template, search
from runtime.slam.appearance import first_view_patch, local_plane_normal, patch_half, warped_template
from runtime.slam.map_feature import MapFeature


def textured(seed=0, size=(240, 320)):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, size).astype(np.float32), (0, 0), 1.0)
    return img


def test_search_finds_a_shifted_patch_to_subpixel():
    img = textured()
    t = extract_template(img, (160, 120))
    # Shift the image by a known sub-pixel amount: the template now sits at (160 + dx, 120 + dy).
    dx, dy = 3.3, -2.6
    M = np.float32([[1, 0, dx], [0, 1, dy]])
    moved = cv2.warpAffine(img, M, (320, 240), flags=cv2.INTER_CUBIC)
    m = search(moved, t, np.array([160.0, 120.0]), np.diag([16.0, 16.0]))
    assert m.found
    np.testing.assert_allclose(m.uv, [160 + dx, 120 + dy], atol=0.2)


def test_search_stays_inside_the_ellipse():
    img = textured(1)
    t = extract_template(img, (100, 100))
    # The true match lies 20 px away but the ellipse is 3 px wide: it must not be found.
    m = search(img, t, np.array([120.0, 100.0]), np.diag([1.0, 1.0]))
    assert np.linalg.norm(m.uv - [120, 100]) <= 3.0 + 1e-9
    assert not m.found
    # A wide ellipse finds it.
    assert search(img, t, np.array([120.0, 100.0]), np.diag([64.0, 64.0])).found


def test_huge_or_outside_ellipses_are_not_searched():
    img = textured(2)
    t = extract_template(img, (50, 50))
    assert not search(img, t, np.array([50.0, 50.0]), np.diag([1e8, 1e8])).found
    assert not search(img, t, np.array([-500.0, 50.0]), np.diag([4.0, 4.0])).found


def test_new_corners_avoid_occupied_regions_and_borders():
    img = np.zeros((240, 320), np.float32)
    for x in range(40, 300, 40):
        for y in range(40, 220, 40):
            img[y:y + 10, x:x + 10] = 255
    occupied = np.array([[100.0, 100.0]])
    pts = find_new_corners(img, occupied, 50, min_distance=25)
    assert len(pts) > 10
    assert np.min(np.linalg.norm(pts - occupied, axis=1)) >= 25
    assert pts[:, 0].min() >= 20 and pts[:, 1].min() >= 20
    feats = new_features(img, occupied, 10)
    assert all(f[1].shape == (15, 15) for f in feats)
    assert grey(np.zeros((4, 4, 3), np.uint8)).shape == (4, 4)


def test_new_features_preferred_are_the_first_the_test_passes_else_the_first_of_all():
    """``prefer``/``take`` (where the motion keeps a new feature in view, mapping.MapManager.add): the
    first ``take`` candidates the test passes, in the detector's order, or the first ``take``
    of all when it passes none; the same as filtering the full list."""
    img = textured(3, (240, 320))
    occupied = np.array([[160.0, 120.0]])
    every = new_features(img, occupied, 24)
    right = [c for c in every if c[0][0] > 160]
    assert len(every) > 12 and 3 < len(right) < len(every)
    got = new_features(img, occupied, 24, prefer=lambda uv: uv[:, 0] > 160, take=3)
    assert [c[0].tolist() for c in got] == [c[0].tolist() for c in right[:3]]
    assert all(np.array_equal(g[1], r[1]) for g, r in zip(got, right))
    none = new_features(img, occupied, 24, prefer=lambda uv: np.zeros(len(uv), bool), take=4)
    assert [c[0].tolist() for c in none] == [c[0].tolist() for c in every[:4]]


def test_new_corners_take_predictions_far_outside_the_image():
    # A feature near the camera's plane predicts pixels like 1e12 (no integer holds them); the
    # disc near the image is still honoured and the far ones change nothing.
    img = np.zeros((240, 320), np.float32)
    for x in range(40, 300, 40):
        for y in range(40, 220, 40):
            img[y:y + 10, x:x + 10] = 255
    near = np.array([[100.0, 100.0], [330.0, 250.0]])
    occupied = np.array([near[0], [1e12, -3e15], [np.nan, 5.0], [-1e300, 1e300], near[1]])
    pts = find_new_corners(img, occupied, 50, min_distance=25)
    assert len(pts) > 10
    np.testing.assert_array_equal(pts, find_new_corners(img, near, 50, min_distance=25))
    assert np.min(np.linalg.norm(pts - [100.0, 100.0], axis=1)) >= 25
    assert np.min(np.linalg.norm(pts - [330.0, 250.0], axis=1)) >= 25    # a disc from just outside


def test_score_ignores_gain_and_offset_of_the_lighting():
    img = textured(3)
    t = extract_template(img, (200, 150))
    m = search(0.6 * img + 20.0, t, np.array([201.0, 149.0]), np.diag([9.0, 9.0]))
    assert m.found and m.score < 1e-3
    np.testing.assert_allclose(m.uv, [200, 150], atol=0.05)


def test_local_plane_normal_recovers_a_plane_and_refuses_what_is_not_one():
    rng = np.random.default_rng(1)
    n_true = np.array([0.2, -0.3, 0.93])
    n_true /= np.linalg.norm(n_true)
    a = np.cross(n_true, [1.0, 0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n_true, a)
    P = rng.uniform(-0.1, 0.1, (12, 2)) @ np.stack([a, b]) + np.array([0.5, 0.2, 1.0])
    n = local_plane_normal(P, 0, radius=0.3, tol=0.005)
    assert n is not None and abs(abs(n @ n_true) - 1) < 1e-9
    # 2 mm noise: still a plane within 1 cm, normal within a few degrees.
    Pn = P + rng.normal(0, 0.002, P.shape)
    n = local_plane_normal(Pn, 0, radius=0.3, tol=0.01)
    assert n is not None and np.degrees(np.arccos(min(abs(n @ n_true), 1.0))) < 5
    # A blob, a line, and too few neighbours are not planes.
    assert local_plane_normal(rng.normal(0, 0.05, (12, 3)), 0, 0.3, 0.01) is None
    line = np.outer(np.linspace(0, 0.2, 8), a) + rng.normal(0, 1e-4, (8, 3))
    assert local_plane_normal(line, 0, 0.3, 0.01) is None
    assert local_plane_normal(P[:3], 0, 0.3, 0.01) is None


def test_new_features_are_kept_only_where_the_motion_keeps_them_in_view():
    from kinematics.camera import default_camera
    from runtime.slam.system import MonoSLAM

    slam = MonoSLAM(default_camera())                   # 64 deg across; lookahead 0.6 s
    uv = np.array([[320.0, 240.0], [40.0, 240.0], [600.0, 240.0]])   # centre, left edge, right edge
    stays = {}
    for w_y in (0.0, 0.5, -0.5):                        # turning about the optical y axis, rad/s
        x_v = np.r_[0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0, w_y, 0]
        stays[w_y] = slam.stay_in_view(x_v, uv)
    assert stays[0.0].all()
    # 0.3 rad in 0.6 s: the centre stays, the edge the camera turns away from leaves, the other stays.
    for w_y in (0.5, -0.5):
        assert stays[w_y][0] and stays[w_y][1] != stays[w_y][2], stays
    assert stays[0.5][1] == stays[-0.5][2]
    # Moving sideways at 1 m/s: points 1 m away slide 0.6 m across, the leading edge's stay.
    x_v = np.r_[0, 0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0]
    moving = slam.stay_in_view(x_v, uv)
    assert not moving[1] and moving[2]


# -- template warping ----------------------------------------------------------------------------

CAM = st.PINHOLE
VIEW_A = st.look_at([0.05, -0.30, 0.40], [0.02, 0.0, 0.0], up=(0, 1, 0)), np.array([0.05, -0.30, 0.40])
VIEW_B = st.look_at([-0.25, -0.15, 0.36], [0.02, 0.0, 0.0], up=(0, 1, 0)), np.array([-0.25, -0.15, 0.36])


@lru_cache(maxsize=None)
def textured_plane(view: str) -> np.ndarray:
    """The textured plane z = 0 (no target) seen from two views 30 cm apart, 35 degrees turned."""
    R, r = VIEW_A if view == "A" else VIEW_B
    return grey(st.render_target_scene(CAM, R, r, st.rectangle(0.01, 0.01, (5.0, 5.0)), card_margin=0.0,
                                       background=st.texture(3, blur=1.5), texture_m=0.6))


def zncc(a, b) -> float:
    a, b = (a - a.mean()) / a.std(), (b - b.mean()) / b.std()
    return float((a * b).mean())


def test_a_template_warped_by_its_plane_looks_as_the_new_view_sees_it():
    """A patch of a textured plane seen in view A, warped by the plane's homography to view B,
    matches what view B sees there (ZNCC near 1), where the unwarped template does not; with the
    wrong plane the warp is worse than with the right one."""
    img_a, img_b = textured_plane("A"), textured_plane("B")
    (Ra, ra), (Rb, rb) = VIEW_A, VIEW_B
    x_b = np.r_[rb, st.quat_of(Rb)]
    t = 15
    scores = {"warped": [], "unwarped": [], "wrong plane": []}
    for X in ([0.0, 0.0, 0.0], [0.06, 0.04, 0.0], [-0.05, 0.03, 0.0], [0.03, -0.05, 0.0]):
        X = np.array(X)
        uv_a = st.pixels(CAM, Ra, ra, X[None])[0]
        uv_b = st.pixels(CAM, Rb, rb, X[None])[0]
        f = MapFeature(0, extract_template(img_a, uv_a, t), 0, ra, patch=first_view_patch(img_a, uv_a, patch_half(t)),
                       uv0=uv_a, R0=Ra, normal=np.array([0.0, 0.0, 1.0]))
        seen = extract_template(img_b, uv_b, t)
        scores["warped"].append(zncc(warped_template(f, x_b, X, CAM), seen))
        scores["unwarped"].append(zncc(f.template, seen))
        f.normal, f.rays0 = np.array([0.0, -1.0, 0.0]), None        # a wall instead of the floor
        wrong = warped_template(f, x_b, X, CAM)
        scores["wrong plane"].append(zncc(wrong, seen) if wrong is not f.template else -1.0)
    print({k: np.round(v, 3).tolist() for k, v in scores.items()})
    assert min(scores["warped"]) > 0.9
    assert max(scores["unwarped"]) < min(scores["warped"]) - 0.1
    assert max(scores["wrong plane"]) < min(scores["warped"])
    # And the active search with the warped template finds the point where view B sees it.
    X = np.array([0.06, 0.04, 0.0])
    uv_a, uv_b = st.pixels(CAM, Ra, ra, X[None])[0], st.pixels(CAM, Rb, rb, X[None])[0]
    f = MapFeature(0, extract_template(img_a, uv_a, t), 0, ra, patch=first_view_patch(img_a, uv_a, patch_half(t)),
                   uv0=uv_a, R0=Ra, normal=np.array([0.0, 0.0, 1.0]))
    m = search(img_b, warped_template(f, x_b, X, CAM), uv_b + [2.0, -1.5], np.diag([16.0, 16.0]))
    assert m.found and np.linalg.norm(m.uv - uv_b) < 0.3


def test_a_feature_without_a_patch_or_plane_keeps_its_template():
    t = np.ones((15, 15), np.float32)
    f = MapFeature(0, t, 0, np.zeros(3))
    assert warped_template(f, np.r_[0, 0, 0, 1.0, 0, 0, 0], np.array([0, 0, 1.0]), CAM) is t


@pytest.mark.parametrize("size, border, min_distance", [((120, 160), 8, 8.0), ((120, 160), 3, 8.0),
                                                        ((240, 320), 10, 15.0), ((240, 320), 3, 15.0),
                                                        ((480, 640), 20, 30.0), ((480, 640), 11, 30.0)])
def test_new_corners_searched_inside_the_border_are_those_of_the_whole_image(size, border, min_distance):
    """The detector runs on the border's inside and a frame around it: the corners, their order
    included, are OpenCV's over the whole image with the same mask."""
    img = textured(3, size)
    occ = np.random.default_rng(4).uniform([0, 0], [size[1], size[0]], size=(25, 2))
    got = find_new_corners(img, occ, 16, min_distance=min_distance, border=border)
    s = 2 if size[1] >= HALF_RESOLUTION_FROM_WIDTH else 1
    ref_img = cv2.pyrDown(img) if s == 2 else img
    h, w = ref_img.shape
    b = int(np.ceil(border / s))
    mask = np.zeros((h, w), np.uint8)
    mask[b:h - b, b:w - b] = 255
    for u, v in np.rint(occ / s).astype(int):
        cv2.circle(mask, (int(u), int(v)), int(np.ceil(min_distance / s)), 0, -1)
    ref = cv2.goodFeaturesToTrack(ref_img, maxCorners=16, qualityLevel=0.01, minDistance=min_distance / s, mask=mask,
                                  blockSize=5 if s == 1 else 3, useHarrisDetector=False).reshape(-1, 2) * s
    assert len(got) >= 8
    np.testing.assert_array_equal(got, ref)
