"""A match's noise shaped by its template's gradients (templates.match_noise_shape): an edge's
match is uncertain along the edge (the aperture problem), a corner's is not. Checked against
analytic templates and against the scatter of independent SSD matches (OpenCV's) in noisy
images."""

from __future__ import annotations

import cv2
import numpy as np

from runtime.slam.appearance.patch import MAX_NOISE_ELONGATION, match_noise_shape
from runtime.slam.map_feature import MapFeature

T = 15


def _edge(angle: float, texture: float = 0.0, rng=None, size: int = T) -> np.ndarray:
    """A blurred step edge whose normal makes ``angle`` with the u axis, with optional texture."""
    c = (size - 1) / 2
    v, u = np.mgrid[0:size, 0:size] - c
    img = 60.0 + 80.0 / (1.0 + np.exp(-(u * np.cos(angle) + v * np.sin(angle)) / 0.8))
    if texture:
        img += texture * rng.standard_normal((size, size))
    return img.astype(np.float32)


def _corner(size: int = T) -> np.ndarray:
    """Four quadrants, dark and light in a checker: an X-corner at the centre."""
    v, u = np.mgrid[0:size, 0:size] - (size - 1) / 2
    return (60.0 + 80.0 * ((u > 0) ^ (v > 0))).astype(np.float32)


def _major_axis(A: np.ndarray) -> tuple[float, np.ndarray]:
    w, V = np.linalg.eigh(A)
    return w[1] / w[0], V[:, 1]


def test_an_edge_is_uncertain_along_itself_and_certain_across():
    for angle in (0.0, 0.5, 1.3, 2.4):
        A = match_noise_shape(_edge(angle))
        ratio, major = _major_axis(A)
        along = np.array([-np.sin(angle), np.cos(angle)])
        across = np.array([np.cos(angle), np.sin(angle)])
        assert ratio > 50
        assert abs(major @ along) > 0.999
        assert np.isclose(across @ A @ across, 1.0, atol=0.02)
        assert along @ A @ along <= MAX_NOISE_ELONGATION + 1e-9


def test_a_corner_is_near_isotropic_and_a_flat_template_gets_the_cap():
    ratio, _ = _major_axis(match_noise_shape(_corner()))
    assert ratio < 1.5
    assert np.allclose(match_noise_shape(np.full((T, T), 7.0)), MAX_NOISE_ELONGATION * np.eye(2))


def _ssd_match(image: np.ndarray, template: np.ndarray) -> np.ndarray:
    """OpenCV's SSD match with a parabola through the best score and its neighbours, px (u, v)."""
    r = cv2.matchTemplate(image, template, cv2.TM_SQDIFF)
    v, u = np.unravel_index(np.argmin(r), r.shape)
    out = np.array([u, v], float)
    for axis, (prev, nxt) in enumerate([((v, u - 1), (v, u + 1)), ((v - 1, u), (v + 1, u))]):
        if min(prev) < 0 or nxt[0] >= r.shape[0] or nxt[1] >= r.shape[1]:
            continue
        a, b, c = r[prev], r[v, u], r[nxt]
        if a - 2 * b + c > 0:
            out[axis] += 0.5 * (a - c) / (a - 2 * b + c)
    return out


def test_the_shape_follows_the_scatter_of_real_matches():
    """A weakly textured edge matched in 300 noisy images: the matches scatter along the edge,
    as the shape says; a corner's scatter is near round. A shape that ignored the gradients (the
    identity) or turned the wrong way would fail."""
    rng = np.random.default_rng(3)
    big = 41
    for angle in (0.4, 2.0):
        scene = _edge(angle, 1.5, rng, big)
        o = (big - T) // 2
        template = scene[o:o + T, o:o + T].copy()
        ratio_model, major_model = _major_axis(match_noise_shape(template))
        hits = np.array([_ssd_match(scene + rng.normal(0, 4.0, scene.shape).astype(np.float32), template)
                         for _ in range(300)])
        ratio_seen, major_seen = _major_axis(np.cov(hits.T))
        assert ratio_seen > 5 and ratio_model > 5
        assert abs(major_seen @ major_model) > np.cos(np.radians(10))
    scene = _corner(big)
    template = scene[o:o + T, o:o + T].copy()
    hits = np.array([_ssd_match(scene + rng.normal(0, 4.0, scene.shape).astype(np.float32), template)
                     for _ in range(300)])
    ratio_seen, _ = _major_axis(np.cov(hits.T) + 1e-6 * np.eye(2))
    assert ratio_seen < 3 and _major_axis(match_noise_shape(template))[0] < 1.5


def test_a_target_point_keeps_the_identity():
    f = MapFeature(0, _edge(0.3), 0, np.zeros(3), known=True)
    assert np.array_equal(f.noise_shape, np.eye(2))
    g = MapFeature(1, _edge(0.3), 0, np.zeros(3))
    assert _major_axis(g.noise_shape)[0] > 50


def _track_with(features, q_world_cam):
    from types import SimpleNamespace

    from runtime.slam.views import SlamMap
    return SlamMap(SimpleNamespace(q=np.asarray(q_world_cam, float)), features)


def test_the_shape_turns_with_the_cameras_roll_since_the_first_view():
    """An edge first seen upright (uncertain along v) and now seen with the camera rolled 90
    degrees about its optic axis is uncertain along u; unrolled, the shape is the template's."""
    from scipy.spatial.transform import Rotation

    f = MapFeature(0, _edge(0.0), 0, np.zeros(3), R0=np.eye(3))
    upright = _track_with([f], [1.0, 0.0, 0.0, 0.0]).noise_shapes(np.array([0]))[0]
    np.testing.assert_allclose(upright, f.noise_shape)
    assert abs(_major_axis(upright)[1][1]) > 0.999
    q_xyzw = Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_quat()
    rolled = _track_with([f], np.r_[q_xyzw[3], q_xyzw[:3]]).noise_shapes(np.array([0]))[0]
    assert abs(_major_axis(rolled)[1][0]) > 0.999
    np.testing.assert_allclose(np.linalg.eigvalsh(rolled), np.linalg.eigvalsh(upright))


def test_relocalisation_counts_an_edge_as_elongated_and_a_corner_not():
    """The test (relocalisation.Relocaliser.elongated) that puts edges after the rest among relocalisation's
    candidates."""
    track = _track_with([MapFeature(0, _edge(0.7), 0, np.zeros(3)), MapFeature(1, _corner(), 0, np.zeros(3))],
                        [1.0, 0.0, 0.0, 0.0])
    from runtime.slam.relocalisation import Relocaliser
    assert Relocaliser.elongated(track, 0) and not Relocaliser.elongated(track, 1)
