"""The rotation module against analytic cases and scipy; the ray caster against geometry."""

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from kinematics.rays import RayCaster
from kinematics.transforms import (matrix_from_quat_wxyz, nearest_rotation, quat_conjugate_wxyz,
                                   quat_multiply_wxyz, quat_wxyz_from_matrix, rotation_angle, rotation_between,
                                   skew, so3_exp, so3_log)

RNG = np.random.default_rng(3)
R_RANDOM = Rotation.random(50, random_state=4).as_matrix()


def test_exp_log_and_skew_analytic():
    np.testing.assert_allclose(so3_exp([0, 0, math.pi / 2]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    w = RNG.normal(size=(20, 3))
    w *= (RNG.uniform(0.01, 3.0, 20) / np.linalg.norm(w, axis=1))[:, None]
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-10)
    u = RNG.normal(size=3)
    np.testing.assert_allclose(skew(w[0]) @ u, np.cross(w[0], u), atol=1e-12)
    # exp([w]x) by its series: I + [w]x + [w]x^2 / 2 + ...
    S = skew(0.3 * np.array([0.2, -0.5, 0.8]))
    series = np.eye(3) + S + S @ S / 2 + S @ S @ S / 6 + S @ S @ S @ S / 24 + S @ S @ S @ S @ S / 120
    np.testing.assert_allclose(so3_exp(0.3 * np.array([0.2, -0.5, 0.8])), series, atol=1e-6)


def test_quaternions_wxyz():
    q = quat_wxyz_from_matrix(R_RANDOM)
    assert q.shape == (50, 4) and np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(matrix_from_quat_wxyz(q), R_RANDOM, atol=1e-12)
    # A half turn about z is (0, 0, 0, 1); the product is the composition, the conjugate the inverse.
    np.testing.assert_allclose(quat_wxyz_from_matrix(so3_exp([0, 0, math.pi])), [0, 0, 0, 1], atol=1e-12)
    qa, qb = q[0], q[1]
    np.testing.assert_allclose(matrix_from_quat_wxyz(quat_multiply_wxyz(qa, qb)), R_RANDOM[0] @ R_RANDOM[1],
                               atol=1e-12)
    np.testing.assert_allclose(quat_multiply_wxyz(qa, quat_conjugate_wxyz(qa)), [1, 0, 0, 0], atol=1e-12)


def test_rotation_angle_and_nearest_rotation():
    for a in (0.0, 1e-4, 0.7, math.pi - 1e-3):
        R = so3_exp(a * np.array([0.6, 0.0, 0.8]))
        assert rotation_angle(np.eye(3), R) == pytest.approx(a, abs=1e-7)
    np.testing.assert_allclose(rotation_angle(R_RANDOM, R_RANDOM), 0.0, atol=1e-7)
    noisy = R_RANDOM + 1e-4 * RNG.normal(size=R_RANDOM.shape)
    Rn = nearest_rotation(noisy)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", Rn, Rn), np.broadcast_to(np.eye(3), Rn.shape), atol=1e-12)
    assert np.all(np.linalg.det(Rn) > 0) and np.all(rotation_angle(Rn, R_RANDOM) < 1e-3)
    # A reflection's nearest rotation has det +1 (not the reflection itself).
    assert np.linalg.det(nearest_rotation(np.diag([1.0, 1.0, -1.0]))) == pytest.approx(1.0)


def test_rotation_between():
    for a, b in [([1, 0, 0], [0, 1, 0]), ([0.3, -0.2, 0.9], [0.1, 0.8, -0.1]), ([0, 0, 2], [0, 0, -5]),
                 ([1, 1, 0], [2, 2, 0])]:
        a, b = np.array(a, float), np.array(b, float)
        R = rotation_between(a, b)
        np.testing.assert_allclose(R @ a / np.linalg.norm(a), b / np.linalg.norm(b), atol=1e-12)
        expected = math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))
        assert rotation_angle(np.eye(3), R) == pytest.approx(expected, abs=1e-7)   # minimal


def test_ray_caster_first_hits_and_occlusion():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    rc = RayCaster(sphere.vertices, sphere.faces)
    d = RNG.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = 2.0 * d
    t, face = rc.first_hit(origins, -3.0 * d)            # directions need not be unit
    assert np.all(face >= 0)
    X = origins - 3.0 * t[:, None] * d
    np.testing.assert_allclose(np.linalg.norm(X, axis=1), 0.5, atol=2e-3)     # on the facetted sphere
    np.testing.assert_allclose(3.0 * t, 1.5, atol=2e-3)
    # The hit is on the triangle's plane in double precision, and the face is trimesh's too.
    n = sphere.face_normals[face]
    np.testing.assert_allclose(np.einsum("ij,ij->i", X - sphere.vertices[sphere.faces[face, 0]], n), 0.0, atol=1e-12)
    theirs = sphere.ray.intersects_first(origins, -d)
    assert np.mean(theirs == face) > 0.99
    t_miss, f_miss = rc.first_hit([[2.0, 2.0, 2.0], [0, 0, 2.0]], [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert np.all(np.isnan(t_miss)) and np.all(f_miss == -1)
    # Occlusion stops at max_dist: a ray towards the sphere is blocked only if it reaches it.
    o = np.array([[0.0, 0.0, 2.0]] * 2)
    down = np.array([[0.0, 0.0, -1.0]] * 2)
    assert rc.blocked(o, down, np.array([1.4, 1.6])).tolist() == [False, True]
