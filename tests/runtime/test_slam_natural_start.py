"""Natural start-up (no target): two-view geometry against synthetic scenes of known structure,
the depth start against a known depth, and the waits (no parallax, a blank view)."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.camera import default_camera, project
from runtime.slam.natural_start import StartSettings, StartWait, TwoViewGeometry, depth_start, two_view_geometry

CAM = default_camera()


def _scene(rng, n=150):
    """Points 1.5-4 m ahead filling the view, camera a's frame."""
    z = rng.uniform(1.5, 4.0, n)
    x = rng.uniform(-0.55, 0.55, n) * z
    y = rng.uniform(-0.4, 0.4, n) * z
    return np.column_stack([x, y, z])


def _views(X_a, R_b_a, t_b_a, rng, noise_px):
    uv_a = project(CAM, X_a) + rng.normal(0, noise_px, (len(X_a), 2))
    uv_b = project(CAM, X_a @ R_b_a.T + t_b_a) + rng.normal(0, noise_px, (len(X_a), 2))
    return uv_a, uv_b


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_views_recover_pose_and_structure(seed):
    rng = np.random.default_rng(seed)
    X_a = _scene(rng)
    R_b_a = Rotation.from_rotvec(rng.normal(0, 0.06, 3)).as_matrix()
    c_b = np.array([0.15, 0.02, 0.03])                       # camera b's centre in a's frame, m
    t_b_a = -R_b_a @ c_b
    uv_a, uv_b = _views(X_a, R_b_a, t_b_a, rng, 0.3)
    geo = two_view_geometry(CAM, uv_a, uv_b)
    assert isinstance(geo, TwoViewGeometry), geo
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(geo.R_b_a @ R_b_a.T).as_rotvec()))
    assert ang < 0.3
    cos_t = geo.t_b_a @ t_b_a / np.linalg.norm(t_b_a)
    assert cos_t > np.cos(np.radians(3.0))
    # Points in baseline units: scaled by the true baseline they are the scene's.
    X = geo.X_a * np.linalg.norm(t_b_a)
    err = np.linalg.norm(X - X_a[geo.keep], axis=1) / X_a[geo.keep, 2]
    assert geo.keep.sum() > 0.8 * len(X_a)
    assert np.median(err) < 0.03


def test_a_pure_turn_waits():
    rng = np.random.default_rng(3)
    X_a = _scene(rng)
    R_b_a = Rotation.from_rotvec([0.0, 0.08, 0.01]).as_matrix()
    uv_a, uv_b = _views(X_a, R_b_a, np.zeros(3), rng, 0.3)
    w = two_view_geometry(CAM, uv_a, uv_b)
    assert isinstance(w, StartWait)
    assert "parallax" in w.reason or "homography" in w.reason or "essential" in w.reason


def test_a_short_baseline_waits_then_a_longer_one_starts():
    rng = np.random.default_rng(4)
    X_a = _scene(rng)
    short = two_view_geometry(CAM, *_views(X_a, np.eye(3), np.array([-0.01, 0.0, 0.0]), rng, 0.3))
    assert isinstance(short, StartWait) and "parallax" in short.reason
    longer = two_view_geometry(CAM, *_views(X_a, np.eye(3), np.array([-0.2, 0.0, 0.0]), rng, 0.3))
    assert isinstance(longer, TwoViewGeometry)


def _texture(rng, h=480, w=640):
    return cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.float32), (0, 0), 2.0) * 3 - 255


def test_depth_start_backprojects_at_the_measured_depth():
    rng = np.random.default_rng(5)
    grey = np.clip(_texture(rng), 0, 255).astype(np.float32)
    # A slanted plane: depth grows left to right, 1.0 to 2.0 m.
    u = np.arange(CAM.width, dtype=np.float32)
    depth = np.tile(1.0 + u / CAM.width, (CAM.height, 1)).astype(np.float32)
    depth[:, :100] = 0.0                                        # no readings on the left
    st = depth_start(CAM, grey, depth)
    assert not isinstance(st, StartWait), st
    assert st.scale == "depth" and len(st.xyz) >= StartSettings().min_points
    assert np.all(st.uv[:, 0] >= 100)
    z_true = 1.0 + np.rint(st.uv[:, 0]) / CAM.width
    np.testing.assert_allclose(st.xyz[:, 2], z_true, rtol=1e-6)
    # Each point projects back to its corner (the lens model's round trip); its covariance is the
    # sensor's z-noise (1.45e-3 z^2, scaled to range) along its ray and a pixel across it.
    np.testing.assert_allclose(project(CAM, st.xyz), st.uv, atol=1e-6)
    rng_m = np.linalg.norm(st.xyz, axis=1)
    rays = st.xyz / rng_m[:, None]
    along = np.einsum("ni,nij,nj->n", rays, st.xyz_cov, rays)
    np.testing.assert_allclose(np.sqrt(along), 1.45e-3 * z_true * rng_m, rtol=1e-6)
    ev = np.linalg.eigvalsh(st.xyz_cov)
    across = np.where(np.abs(ev - along[:, None]) < 1e-15, np.nan, ev)
    np.testing.assert_allclose(np.sqrt(np.nanmax(across, axis=1)), rng_m / CAM.fx, rtol=1e-6)


def test_depth_start_waits_on_a_blank_wall_and_refuses_an_unregistered_depth():
    grey = np.full((480, 640), 128.0, np.float32)
    w = depth_start(CAM, grey, np.full((480, 640), 1.5, np.float32))
    assert isinstance(w, StartWait) and "corners" in w.reason
    with pytest.raises(ValueError, match="registered"):
        depth_start(CAM, grey, np.ones((240, 320), np.float32))


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_a_desk_mostly_one_plane_gives_the_homography_pose(seed):
    """A desk: 90% of the points on its tilted top, the rest on boxes; the essential matrix is
    nearly degenerate there, and the pose comes from the homography's decomposition, told apart
    by the points off the plane (or the start waits)."""
    rng = np.random.default_rng(100 + seed)
    n = 90
    a, b = rng.uniform(-0.35, 0.35, n), rng.uniform(-0.25, 0.25, n)
    X_a = np.column_stack([a, b, 0.7 + 0.5 * b])               # the plane z = 0.7 + 0.5 y, m
    box = rng.random(n) < 0.1
    X_a[box, 2] -= rng.uniform(0.05, 0.15, box.sum())          # a few points nearer, on boxes
    R_b_a = Rotation.from_rotvec(rng.normal(0, 0.04, 3)).as_matrix()
    c_b = rng.normal(0, 1, 3) * [0.04, 0.04, 0.015]            # a 4-6 cm hand-held move
    t_b_a = -R_b_a @ c_b
    uv_a, uv_b = _views(X_a, R_b_a, t_b_a, rng, 0.5)
    geo = two_view_geometry(CAM, uv_a, uv_b)
    if isinstance(geo, StartWait):                             # waiting is allowed; a wrong pose is not
        assert "parallax" in geo.reason or "alike" in geo.reason
        return
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(geo.R_b_a @ R_b_a.T).as_rotvec()))
    cos_t = geo.t_b_a @ t_b_a / np.linalg.norm(t_b_a)
    assert ang < 1.0 and cos_t > np.cos(np.radians(5.0)), (ang, np.degrees(np.arccos(min(cos_t, 1))))

