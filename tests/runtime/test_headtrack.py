"""Head tracking (runtime.vision2d.headtrack) against MuJoCo renders of a head at known poses
(runtime.vision2d.headscene): the renderer's own consistency, sweeps in yaw and pitch within the
error budget (5 deg RMS), lost heads reported, the servo mapping's signs and limits, bad input."""

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import numpy as np
import pytest

from kinematics import reference_head
from kinematics.camera import CameraIntrinsics, project
from runtime.vision2d.headscene import HeadScene, render_head_sequence
from kinematics.rays import RayCaster
from kinematics.transforms import rotation_angle as rotation_error_rad
from runtime.gaze.slaving import head_to_joint_targets
from runtime.vision2d.headmodel import head_pose, polyhedral_head, rotation_from_ypr, ypr_from_rotation
from runtime.vision2d.headtrack import HeadTracker, HeadTrackerConfig

#: Small frames for speed: default_camera() halved (320x240, f = 257.35 px), head 0.6 m away.
CAM = CameraIntrinsics(width=320, height=240, fx=257.35, fy=257.35, cx=159.5, cy=119.5)
DIST = 0.6
BUDGET_DEG = 5.0


@pytest.fixture(scope="module")
def scene():
    with HeadScene(CAM, DIST, seed=0) as s:
        yield s


def _errors_deg(results, ypr_true, T_true):
    assert not any(r.lost for r in results), [r.reason for r in results if r.lost]
    est = np.array([r.ypr for r in results])
    rms = np.degrees(np.sqrt(np.mean((est - ypr_true) ** 2, axis=0)))
    geo = np.degrees(rotation_error_rad(np.stack([r.T_cam_head[:3, :3] for r in results]), T_true[:, :3, :3]))
    return rms, float(np.sqrt(np.mean(geo ** 2)))


# -- conventions --------------------------------------------------------------------------------

def test_ypr_convention_and_round_trip():
    # Yaw +90 deg turns the face to the person's left, which faces the camera's +x (image right).
    forward = np.array([1.0, 0.0, 0.0])
    assert np.allclose(rotation_from_ypr([math.pi / 2, 0, 0]) @ forward, [1, 0, 0], atol=1e-12)
    assert np.allclose(rotation_from_ypr([0, 0, 0]) @ forward, [0, 0, -1])        # faces the camera
    assert np.allclose(rotation_from_ypr([0, math.pi / 2, 0]) @ forward, [0, -1, 0], atol=1e-12)  # looks up
    # Roll +90 deg lowers the right ear: the head's left (+y) goes up (-y in the image).
    assert np.allclose(rotation_from_ypr([0, 0, math.pi / 2]) @ [0, 1, 0], [0, -1, 0], atol=1e-12)
    rng = np.random.default_rng(1)
    ypr = rng.uniform([-1.4, -1.2, -1.4], [1.4, 1.2, 1.4], (50, 3))
    assert np.allclose(ypr_from_rotation(rotation_from_ypr(ypr)), ypr, atol=1e-9)


def intersect_rays(vertices, faces, origins, directions):
    return RayCaster(vertices, faces).first_hit(origins, directions)


def test_intersect_rays_against_the_ellipsoid():
    # Rays from outside toward the centre of a fine polyhedral ellipsoid land within its facet
    # error of the analytic ellipsoid, on the near side.
    model = polyhedral_head((0.2, 0.16, 0.24), n_lon=64, n_lat=40, nose_m=0.0)
    rng = np.random.default_rng(2)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = 1.0 * d
    t, face = intersect_rays(model.vertices, model.faces, origins, -d)
    assert np.all(face >= 0)
    X = origins - t[:, None] * d
    a, b, c = 0.1, 0.08, 0.12
    level = (X[:, 0] / a) ** 2 + (X[:, 1] / b) ** 2 + (X[:, 2] / c) ** 2
    assert np.all(np.abs(level - 1) < 0.01)
    assert np.all(np.einsum("nk,nk->n", X, d) > 0)                     # the near side
    t_miss, f_miss = intersect_rays(model.vertices, model.faces, [[1.0, 1.0, 1.0]], [[1.0, 0.0, 0.0]])
    assert np.isnan(t_miss[0]) and f_miss[0] == -1


# -- the renderer -------------------------------------------------------------------------------

@pytest.mark.parametrize("ypr_deg", [(0, 0, 0), (40, 10, 5), (-50, -20, 10)])
def test_renderer_pose_is_self_consistent(scene, ypr_deg):
    T = head_pose(np.radians(ypr_deg), DIST)
    image = scene.render(T)
    # MuJoCo's own kinematics agree with the pose given.
    assert np.allclose(scene.T_cam_head_from_mujoco(), T, atol=1e-6)
    # The model's silhouette projected with the pose covers what MuJoCo drew as the head.
    drawn = scene.head_mask(T)
    tracker = HeadTracker(CAM, scene.head)
    projected = tracker._region_mask(T[:3, :3], T[:3, 3], 0.0) > 0
    assert (drawn & projected).sum() / (drawn | projected).sum() > 0.9
    # Landmarks projected with the pose land on their features: eyes dark (iris), mouth red.
    R, t = T[:3, :3], T[:3, 3]
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(float)
    skin = np.median(grey[drawn])
    for name in ("left_eye", "right_eye", "mouth"):
        X = scene.head.landmarks[name]
        n_cam = R @ X / np.linalg.norm(X)
        if -n_cam @ (R @ X + t) / np.linalg.norm(R @ X + t) < 0.3:
            continue                                                       # turned away
        u, v = np.round(project(CAM, (R @ X + t)[None])[0]).astype(int)
        patch = image[v - 1: v + 2, u - 1: u + 2].reshape(-1, 3).astype(float)
        if name == "mouth":
            assert np.max(patch[:, 0] - patch[:, 1]) > 60, (name, patch)
        else:
            assert grey[v - 1: v + 2, u - 1: u + 2].min() < skin - 60, (name, skin)
    # The left eye (head +y) is on the image's right when the head faces the camera.
    if ypr_deg == (0, 0, 0):
        uv = project(CAM, np.stack([R @ scene.head.landmarks[k] + t for k in ("left_eye", "right_eye")]))
        assert uv[0, 0] > uv[1, 0] + 10


# -- tracking -----------------------------------------------------------------------------------

def test_tracks_a_yaw_sweep():
    n = 41
    ypr = np.column_stack([np.radians(np.linspace(0, 40, n)), np.zeros(n), np.zeros(n)])
    images, T, cam = render_head_sequence(ypr, DIST, camera=CAM)
    tracker = HeadTracker(cam)
    results = tracker.track(images, T[0])
    rms, geo = _errors_deg(results, ypr, T)
    assert np.all(rms < BUDGET_DEG) and geo < BUDGET_DEG, (rms, geo)
    assert abs(math.degrees(results[-1].yaw) - 40) < BUDGET_DEG
    assert np.linalg.norm(results[-1].translation_m - T[-1][:3, 3]) < 0.03
    assert tracker.counts["lost"] == 0 and all(r.inliers >= 12 for r in results)


def test_tracks_a_pitch_sweep_with_roll():
    n = 31
    ypr = np.column_stack([np.zeros(n), np.radians(np.linspace(0, -25, n)), np.radians(np.linspace(0, 10, n))])
    images, T, cam = render_head_sequence(ypr, DIST, camera=CAM)
    results = HeadTracker(cam).track(images, T[0])
    rms, geo = _errors_deg(results, ypr, T)
    assert np.all(rms < BUDGET_DEG) and geo < BUDGET_DEG, (rms, geo)
    assert abs(math.degrees(results[-1].pitch) + 25) < BUDGET_DEG


def test_a_lost_head_is_reported_and_reacquired(scene):
    ypr = np.radians([[0, 0, 0], [3, 0, 0], [6, 0, 0], [9, 1, 0], [12, 2, 0]])
    T = head_pose(ypr, DIST)
    images = [scene.render(t) for t in T]
    tracker = HeadTracker(CAM)
    tracker.start(images[0], T[0])
    assert not tracker.update(images[1]).lost
    blank = np.full_like(images[0], 128)
    black = np.zeros_like(images[0])
    background_only = scene.render(head_pose((0, 0, 0), 5.0))   # the head far behind the backdrop
    for frame in (black, blank, None):
        r = tracker.update(frame)
        assert r.lost and np.all(np.isnan(r.ypr)) and r.reason.startswith("bad frame")
    r = tracker.update(background_only)
    assert r.lost and not r.reinitialised and np.all(np.isnan(r.T_cam_head))
    assert tracker.counts["bad_frames"] == 3 and tracker.counts["lost"] == 4
    # The head comes back: the colour blob re-initialises (reported lost), then it is tracked.
    r = tracker.update(images[3])
    assert r.lost and r.reinitialised
    r = tracker.update(images[4])
    assert not r.lost
    assert math.degrees(rotation_error_rad(r.T_cam_head[:3, :3], T[4][:3, :3])) < BUDGET_DEG
    assert tracker.counts["reinitialisations"] == 1


# -- servoing -----------------------------------------------------------------------------------

def test_servo_mapping_signs_and_limits():
    yaw, pitch, roll = 0.3, -0.2, 0.1
    q = head_to_joint_targets([yaw, pitch, roll])
    # (elevation, pan, cyclotorsion): the head turning left pans left, looking down lowers the
    # gaze, rolling right-ear-down turns the image the same way.
    assert np.allclose(q, [pitch, yaw, roll])
    assert np.allclose(head_to_joint_targets([yaw, pitch, roll], gain=0.5), 0.5 * q)
    assert np.allclose(head_to_joint_targets([yaw, pitch, roll], gain=[1, 0, 2]), [0, yaw, 2 * roll])
    limits = np.radians([[-20, -45, -10], [20, 45, 10]])
    q = head_to_joint_targets(np.radians([80, -30, 25]), limits=limits)
    assert np.allclose(q, np.radians([-20, 45, 10]))
    assert np.allclose(head_to_joint_targets([0.1, 0.05, 0.0], limits=limits, rest=[0.1, 0.0, 0.0]),
                       [0.15, 0.1, 0.0])
    # A HeadGeometry's own ranges (the reference head: +-80 deg).
    head = reference_head()
    q = head_to_joint_targets([3.0, -3.0, 0.0], limits=head)
    assert np.allclose(q, [head.lower[0], head.upper[1], 0.0])


def test_bad_input_raises_clear_errors(scene):
    with pytest.raises(ValueError, match="ypr"):
        head_to_joint_targets([0.1, 0.2])
    with pytest.raises(ValueError, match="lost"):
        head_to_joint_targets([np.nan, 0, 0])
    with pytest.raises(ValueError, match="limits"):
        head_to_joint_targets([0, 0, 0], limits=[[1, 2, 3]])
    with pytest.raises(ValueError, match="radians"):
        render_head_sequence(np.array([[90.0, 0, 0]]), DIST, camera=CAM)
    with pytest.raises(ValueError, match="poses_ypr"):
        render_head_sequence(np.zeros(3), DIST, camera=CAM)
    tracker = HeadTracker(CAM)
    image = scene.render(head_pose((0, 0, 0), DIST))
    with pytest.raises(ValueError, match="start"):
        tracker.update(image)
    with pytest.raises(ValueError, match="camera is 320x240"):
        tracker.start(np.zeros((480, 640, 3), np.uint8), head_pose((0, 0, 0), DIST))
    with pytest.raises(ValueError, match="RGB"):
        tracker.start(image[..., 0], head_pose((0, 0, 0), DIST))
    behind = head_pose((0, 0, 0), DIST)
    behind[2, 3] = -DIST
    with pytest.raises(ValueError, match="in front of the camera"):
        tracker.start(image, behind)
    with pytest.raises(ValueError, match="cannot start"):
        tracker.start(np.zeros_like(image), head_pose((0, 0, 0), DIST))
    with pytest.raises(ValueError, match="max_features"):
        HeadTrackerConfig(max_features=2)
    with pytest.raises(ValueError, match="n_lon"):
        polyhedral_head(n_lon=7)
