"""A natural feature's plane normal fitted to its looks (appearance.normals.fit_normal_kernel), against a
ray-cast textured plane whose normal is known."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

import slam_testing as st
from kinematics.camera import lens_kernel_args, unproject
from runtime.slam.appearance.normals import candidate_normals, fit_normal_kernel, normal_scores_kernel
from runtime.slam.appearance import first_view_patch, patch_half
from runtime.slam.map_feature import MapFeature

CAM = st.PINHOLE
T = 15
# A rectangle far off the views: the plane z = 0 shows only its texture.
AWAY = st.rectangle(0.01, 0.01, centre=(5.0, 5.0))


@lru_cache(maxsize=None)
def view(dist: float, elevation_deg: float, azimuth_deg: float):
    R, r = st.viewpoint(dist, elevation_deg, azimuth_deg)
    img = st.render_target_scene(CAM, R, r, AWAY, card_margin=0.0, background=st.texture(3), texture_m=1.0,
                                 supersample=2, edge_supersample=2)
    return R, r, img.astype(np.float32)


def feature_and_args(first, now, point):
    """The feature cut at ``point``'s pixel in the ``first`` view, and the kernel's arguments for
    its match in the ``now`` view (the point's true projection)."""
    R0, r0, img0 = view(*first)
    R, r, img = view(*now)
    uv0 = st.pixels(CAM, R0, r0, point)[0]
    patch = first_view_patch(img0, uv0, patch_half(T))
    f = MapFeature(0, first_view_patch(img0, uv0, T // 2), 0, r0, patch=patch, uv0=uv0, R0=R0)
    rays0 = unproject(CAM, uv0 + np.array([[-7, -7], [7, -7], [7, 7], [-7, 7], [0, 0]], float)) @ R0.T
    np.testing.assert_allclose(rays0, f.first_view_rays(CAM))
    z = st.pixels(CAM, R, r, point)[0]
    model, lens = lens_kernel_args(CAM)
    return f, (img, patch.astype(np.float32), T, rays0, np.asarray(r0, float), np.asarray(point, float),
               np.asarray(r, float), R, model, lens, z)


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_candidate_normals_tilt_by_the_asked_angles_about_the_direction():
    d0 = np.array([0.3, -0.2, 0.9])
    c = candidate_normals(d0, np.array([0.0, 20.0, 45.0]), 6)
    assert c.shape == (13, 3)
    np.testing.assert_allclose(np.linalg.norm(c, axis=1), 1.0)
    tilt = np.degrees(np.arccos(c @ (d0 / np.linalg.norm(d0))))
    np.testing.assert_allclose(tilt, [0.0] + [20.0] * 6 + [45.0] * 6, atol=1e-5)
    # Evenly spread: neighbours on a ring are 360 / 6 degrees apart about d0.
    ring = c[7:] - np.outer(c[7:] @ d0, d0) / (d0 @ d0)
    np.testing.assert_allclose([angle_deg(ring[i], ring[(i + 1) % 6]) for i in range(6)], 60.0, atol=1e-6)


def test_a_plane_seen_obliquely_gets_its_true_normal_not_the_fronto_parallel_guess():
    # First seen nearly head-on, now at 40 degrees from the plane: the fronto-parallel guess
    # (facing the first view) is 14-26 degrees off the plane's normal (0, 0, 1).
    for point, first, now in [((0.05, -0.03, 0.0), (0.8, 70.0, -80.0), (0.7, 40.0, -60.0)),
                              ((-0.04, 0.02, 0.0), (0.9, 76.0, -100.0), (0.6, 45.0, -130.0))]:
        f, args = feature_and_args(first, now, np.array(point))
        guess = (f.r0 - point) / np.linalg.norm(f.r0 - point)
        assert angle_deg(guess, [0, 0, 1]) > 13.0
        n, score, current = fit_normal_kernel(*args, guess, np.array([0.0, 20.0, 40.0, 60.0]), 8, 10.0)
        assert angle_deg(n, [0, 0, 1]) < 6.0, (point, n)
        assert score < current - 0.02
        # The true normal scores as well as what was fitted, and much better than the guess.
        true = normal_scores_kernel(*args, np.array([[0.0, 0.0, 1.0]]))[0]
        assert true < current - 0.02 and true < score + 0.02


def test_a_normal_that_already_explains_the_view_is_kept():
    f, args = feature_and_args((0.8, 70.0, -80.0), (0.7, 40.0, -60.0), np.array([0.05, -0.03, 0.0]))
    n, score, current = fit_normal_kernel(*args, np.array([0.0, 0.0, 1.0]), np.array([0.0, 20.0, 40.0, 60.0]), 8, 10.0)
    # What the caller adopts must beat the current normal by its margin: here nothing does.
    assert not score < current - 0.02
    assert angle_deg(n, [0, 0, 1]) < 6.0


def test_a_match_with_no_valid_warp_scores_as_unrelated():
    f, args = feature_and_args((0.8, 70.0, -80.0), (0.7, 40.0, -60.0), np.array([0.05, -0.03, 0.0]))
    # A plane containing the first view's rays cannot be warped: score 2, the worst.
    edge_on = np.cross(f.first_view_rays(CAM)[4], [0.0, 0.0, 1.0])
    assert normal_scores_kernel(*args, edge_on[None] / np.linalg.norm(edge_on))[0] == 2.0


def orbit_frames(n: int = 36):
    """A 320 x 240 camera circling down from 80 to 45 degrees above a textured plane with the
    target at its centre, looking at it: (camera, [(image, t)], true poses)."""
    from kinematics.camera import CameraIntrinsics
    cam = CameraIntrinsics(width=320, height=240, fx=257.35, fy=257.35, cx=159.5, cy=119.5)
    rect = st.rectangle(0.21, 0.15)
    frames = []
    for i in range(n):
        s = 0.5 - 0.5 * np.cos(np.pi * i / (n - 1))          # starts and ends at rest
        R, r = st.viewpoint(0.6, 80.0 - 35.0 * s, -80.0)
        img = st.render_target_scene(cam, R, r, rect, card_margin=0.03, background=st.texture(1), supersample=2,
                                     edge_supersample=8)
        frames.append((img, i / 30, R, r))
    return cam, rect, frames


@lru_cache(maxsize=None)
def _orbit():
    return orbit_frames()


def run_orbit(normals_per_frame: int):
    from dataclasses import replace

    from runtime.sequence import Target
    from runtime.slam.config import MapSettings
    from runtime.slam.system import MonoSLAM
    cam, rect, frames = _orbit()
    img0, _, R0, r0 = frames[0]
    # No normals from the map's neighbouring points (on this one plane they would be right too).
    settings = replace(MapSettings(use_imu=False), normals_per_frame=normals_per_frame, normals_every=10**6)
    slam = MonoSLAM(cam, settings=settings, imu=False)
    slam.start(img0, 0.0, Target(rect, st.pixels(cam, R0, r0, rect)))
    for img, t, _, _ in frames[1:]:
        slam.process(img, t)
    return slam


def test_the_tracker_fits_its_features_normals_to_the_plane_as_the_view_turns():
    """Through MonoSLAM.process: natural features seen from up to 35 degrees lower than at first
    get the plane's normal from their looks; with the fitting off they keep the fronto-parallel
    guess, tens of degrees off (their view turns as the camera circles down)."""
    fitted = [f for f in run_orbit(4).features if not f.known and f.normal_view_deg > 0]
    assert len(fitted) >= 10
    err = np.array([angle_deg(f.normal, [0, 0, 1]) for f in fitted])
    assert np.median(err) < 8.0, np.sort(err)
    off = [f for f in run_orbit(0).features if not f.known and f.normal is not None]
    assert len(off) >= 10 and all(f.normal_view_deg == 0 for f in off)
    assert np.median([angle_deg(f.normal, [0, 0, 1]) for f in off]) > 20.0
