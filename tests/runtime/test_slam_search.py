"""Active search and new features against synthetic images with known answers."""

import cv2
import numpy as np

from runtime.slam.features import find_new_corners, grey, new_features
from runtime.slam.search import extract_template, search


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


def test_score_ignores_gain_and_offset_of_the_lighting():
    img = textured(3)
    t = extract_template(img, (200, 150))
    m = search(0.6 * img + 20.0, t, np.array([201.0, 149.0]), np.diag([9.0, 9.0]))
    assert m.found and m.score < 1e-3
    np.testing.assert_allclose(m.uv, [200, 150], atol=0.05)


def test_local_plane_normal_recovers_a_plane_and_refuses_what_is_not_one():
    from runtime.slam.system import local_plane_normal

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
    from runtime.slam.state import State
    from runtime.slam.system import MonoSLAM

    slam = MonoSLAM(default_camera())                   # 64 deg across; lookahead 0.6 s
    uv = np.array([[320.0, 240.0], [40.0, 240.0], [600.0, 240.0]])   # centre, left edge, right edge
    stays = {}
    for w_y in (0.0, 0.5, -0.5):                        # turning about the optical y axis, rad/s
        slam.state = State.from_camera(np.r_[0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0, w_y, 0], np.eye(13) * 1e-4)
        stays[w_y] = slam._stay_in_view(uv)
    assert stays[0.0].all()
    # 0.3 rad in 0.6 s: the centre stays, the edge the camera turns away from leaves, the other stays.
    for w_y in (0.5, -0.5):
        assert stays[w_y][0] and stays[w_y][1] != stays[w_y][2], stays
    assert stays[0.5][1] == stays[-0.5][2]
