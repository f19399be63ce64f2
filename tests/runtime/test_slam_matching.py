"""The frame's active search (matching.match_features) against synthetic images with known
answers: a match is where the template's content moved to."""

import cv2
import numpy as np

from kinematics.camera import default_camera
from runtime.slam.matching import match_features
from runtime.slam.search import extract_template
from runtime.slam.templates import MapFeature


def textured(seed: int, size=(480, 640)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, size).astype(np.float32), (0, 0), 1.5)


def search_at(img: np.ndarray, uv_true, shift, sigma_px: float):
    """Match the template cut at ``uv_true`` in ``img`` moved by ``shift`` px, predicted at
    ``uv_true`` with a round search ellipse of ``sigma_px``: (z (2,), found)."""
    cam = default_camera()
    f = MapFeature(0, extract_template(img, uv_true), 0, np.zeros(3))
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REFLECT)
    x_v = np.r_[np.zeros(3), 1.0, np.zeros(9)]
    z, _, found = match_features(moved, [f], np.zeros(1, bool), np.zeros((1, 3)), x_v, cam,
                                 np.array([uv_true], float), np.array([np.eye(2) * sigma_px**2]), 0.25, 1e6)
    return z[0], bool(found[0])


def test_a_distinct_feature_is_found_where_it_moved_in_a_wide_ellipse():
    for seed in range(5):
        uv = np.array([320.0 + 7 * seed, 240.0 - 5 * seed])
        shift = np.array([4.3, -3.6])
        z, found = search_at(textured(seed), uv, shift, sigma_px=8.0)
        assert found, seed
        np.testing.assert_allclose(z, uv + shift, atol=0.15)


def test_a_feature_moved_outside_its_ellipse_is_not_found():
    """The search stays inside the 3-sigma ellipse: content moved 12 px away is not matched
    from a 1.5 px ellipse (3 sigma = 4.5 px)."""
    for seed in range(5):
        uv = np.array([320.0 + 7 * seed, 240.0 - 5 * seed])
        z, found = search_at(textured(seed), uv, np.array([12.0, 0.0]), sigma_px=1.5)
        assert not found, (seed, z)
