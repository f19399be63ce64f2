"""Placement scores against analytic cases, and the body model's structure."""

import math

import numpy as np
import pytest
import trimesh

from placement.body import SEGMENT_INDEX, SEGMENTS, BodyError, Motion, Pose, make_body
from placement.motions import default_motions, default_poses
from kinematics.rays import RayCaster
from placement.scores import fov_fraction, handling_space, motion_scores

BODY = make_body()


def test_body_structure():
    assert 1700 <= BODY.face_count <= 1900
    assert set(np.unique(BODY.face_segment)) == set(range(16))
    assert BODY.stature_m == pytest.approx(1.75)
    assert BODY.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    # Facing -Y with the left side towards +X; every segment a closed, outward mesh.
    assert BODY.joints[SEGMENT_INDEX["upper_arm_l"], 0] > 0 > BODY.joints[SEGMENT_INDEX["upper_arm_r"], 0]
    toes = BODY.vertices[BODY.vertex_segment == SEGMENT_INDEX["foot_l"]]
    assert toes[:, 1].min() < BODY.joints[SEGMENT_INDEX["foot_l"], 1] - 0.1
    for i in range(16):
        m = trimesh.Trimesh(BODY.vertices, BODY.faces[BODY.face_segment == i], process=False)
        m.remove_unreferenced_vertices()
        assert m.is_watertight and m.volume > 0, SEGMENTS[i]
    assert make_body(1.60).stature_m == pytest.approx(1.60)
    with pytest.raises(BodyError, match="metres"):
        make_body(175)


def test_posing_is_rigid_per_segment_and_follows_the_tree():
    pose = Pose.from_dict({"thigh_l": (-0.5, 0, 0), "pelvis": (0, 0, 0.3)}, root_m=(0.1, 0.0, 0.0))
    v = BODY.posed_vertices(pose)
    for i in range(16):
        sel = BODY.vertex_segment == i
        a, b = BODY.vertices[sel], v[sel]
        # Rigid: pairwise distances preserved.
        np.testing.assert_allclose(np.linalg.norm(a[1:] - a[0], axis=1), np.linalg.norm(b[1:] - b[0], axis=1), atol=1e-12)
    G = BODY.segment_transforms(pose)
    # The knee rides on the thigh, which rides on the pelvis.
    knee = BODY.joints[SEGMENT_INDEX["shank_l"]]
    expect = G[SEGMENT_INDEX["thigh_l"]] @ np.r_[knee, 1]
    np.testing.assert_allclose(G[SEGMENT_INDEX["shank_l"]] @ np.r_[knee, 1], expect, atol=1e-12)


def test_point_above_a_sphere_sees_the_analytic_fraction():
    R, d = 0.3, 0.05
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=R)
    cam = np.array([[0.0, 0.0, R + d]])
    got = fov_fraction(RayCaster(sphere.vertices, sphere.faces), cam, rays=8192)[0]
    t = math.asin(R / (R + d))
    expected = 1 - (1 - math.cos(t)) / 2
    assert got == pytest.approx(expected, abs=2e-3)


def test_point_above_an_infinite_plane_sees_half_and_alone_sees_all():
    L = 1e4
    plane = trimesh.Trimesh([[-L, -L, 0], [L, -L, 0], [L, L, 0], [-L, L, 0]], [[0, 1, 2], [0, 2, 3]])
    occ = RayCaster(plane.vertices, plane.faces)
    assert fov_fraction(occ, np.array([[0.0, 0.0, 0.02]]), rays=2048)[0] == pytest.approx(0.5, abs=1e-12)
    assert fov_fraction(occ, np.array([[5 * L, 5 * L, 1.0]]), rays=2048)[0] > 0.49
    tiny = trimesh.creation.box((1e-3, 1e-3, 1e-3))
    assert fov_fraction(RayCaster(tiny.vertices + 100.0, tiny.faces), np.zeros((1, 3)), 2048)[0] == 1.0


def test_occluder_agrees_with_trimesh():
    body_mesh = BODY.mesh()
    rng = np.random.default_rng(0)
    o = rng.uniform([-0.5, -0.5, 0], [0.5, 0.5, 1.8], (20000, 3))
    d = rng.normal(size=(20000, 3)); d /= np.linalg.norm(d, axis=1)[:, None]
    ours = RayCaster(body_mesh.vertices, body_mesh.faces).blocked(o, d)
    theirs = body_mesh.ray.intersects_any(o, d)
    assert np.mean(ours == theirs) > 0.999


def test_static_pose_has_zero_motion():
    still = Motion("still", np.arange(5) * 0.1, np.zeros((5, 16, 3)), np.zeros((5, 3)))
    m = motion_scores(BODY, [still])
    for k, v in m.items():
        assert np.abs(v).max() < 1e-9, k


def test_rotating_one_segment_moves_only_its_polygons_by_the_arc():
    theta = math.radians(40)
    rv = np.zeros((2, 16, 3))
    rv[1, SEGMENT_INDEX["forearm_l"], 0] = -theta           # elbow flexion about the left-right axis
    m = motion_scores(BODY, [Motion("elbow", np.array([0.0, 1.0]), rv, np.zeros((2, 3)))], standoff_m=0.02)
    c, n = BODY.face_frames()
    cams = c + 0.02 * n
    moving = np.isin(BODY.face_segment, [SEGMENT_INDEX["forearm_l"], SEGMENT_INDEX["hand_l"]])
    elbow = BODY.joints[SEGMENT_INDEX["forearm_l"]]
    r = np.linalg.norm((cams - elbow)[:, 1:], axis=1)       # distance from the X axis through the elbow
    # Two frames: each is half the chord from the mean position, and half the angle from the mean.
    np.testing.assert_allclose(m["motion_mm"][moving], 1000 * r[moving] * math.sin(theta / 2), rtol=1e-9)
    np.testing.assert_allclose(m["motion_deg"][moving], math.degrees(theta) / 2, rtol=1e-9)
    assert np.abs(m["motion_mm"][~moving]).max() < 1e-9


def test_walking_at_steady_speed_is_not_counted_but_bounce_is():
    t = np.linspace(0, 2, 21)
    root = np.column_stack([np.zeros_like(t), -1.3 * t, np.zeros_like(t)])
    glide = Motion("glide", t, np.zeros((21, 16, 3)), root)
    assert motion_scores(BODY, [glide])["motion_mm"].max() < 1e-9
    root[:, 2] = 0.02 * np.sin(2 * np.pi * t)
    bob = Motion("bob", t, np.zeros((21, 16, 3)), root)
    assert motion_scores(BODY, [bob])["motion_mm"].min() > 5


def test_handling_space_lies_in_front_within_reach():
    pts = handling_space(BODY, 400)
    assert 300 <= len(pts) <= 520
    chest_front = BODY.vertices[BODY.vertex_segment == SEGMENT_INDEX["chest"], 1].min()
    assert pts[:, 1].max() < chest_front
    sh = BODY.joints[[SEGMENT_INDEX["upper_arm_l"], SEGMENT_INDEX["upper_arm_r"]]]
    assert np.min(np.linalg.norm(pts[:, None] - sh[None], axis=2), axis=1).max() <= BODY.arm_length_m + 1e-9


def test_procedural_motions_keep_feet_near_the_floor_and_body_upright():
    for m in default_motions(BODY):
        v = BODY.posed_vertices(m.subsample(10))
        assert v[..., 2].min() > -0.08, m.name      # no sinking through the floor
        head = BODY.segment_transforms(m.subsample(10))[:, SEGMENT_INDEX["head"]]
        assert np.all(head[:, 2, 2] > 0.7), m.name  # the head stays roughly upright
    assert set(default_poses(BODY)) == {"standing", "walking", "seated", "reaching"}
