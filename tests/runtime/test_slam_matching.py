"""The frame's active search (matching.match_features) against synthetic images with known
answers: a match is where the template's content moved to, and a match whose ellipse holds a
second copy of a repeated pattern is reported with the second place."""

import cv2
import numpy as np

from kinematics.camera import default_camera
from runtime.slam.matching import match_features
from runtime.slam.search import extract_template
from runtime.slam.templates import MapFeature

PERIOD = 16     # px, the repeated pattern's period in u and v


def textured(seed: int, size=(480, 640)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, size).astype(np.float32), (0, 0), 1.5)


def tiled(seed: int, size=(480, 640)) -> np.ndarray:
    """A random tile repeated every PERIOD px (shelving, print, tiles), with a little noise so
    that the copies are alike, not identical."""
    rng = np.random.default_rng(seed)
    tile = textured(seed, (PERIOD, PERIOD))
    img = np.tile(tile, (size[0] // PERIOD, size[1] // PERIOD))
    return (img + rng.normal(0, 1.0, img.shape)).astype(np.float32)


def search_at(img: np.ndarray, uv_true, shift, sigma_px: float):
    """Match the template cut at ``uv_true`` in ``img`` moved by ``shift`` px, predicted at
    ``uv_true`` with a round search ellipse of ``sigma_px``: (z (2,), found, z2 (2,): a second
    matching place, NaN if none)."""
    cam = default_camera()
    f = MapFeature(0, extract_template(img, uv_true), 0, np.zeros(3))
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REFLECT)
    x_v = np.r_[np.zeros(3), 1.0, np.zeros(9)]
    z, _, found, z2 = match_features(moved, [f], np.zeros(1, bool), np.zeros((1, 3)), x_v, cam,
                                     np.array([uv_true], float), np.array([np.eye(2) * sigma_px**2]), 0.25, 1e6)
    return z[0], bool(found[0]), z2[0]


def test_a_distinct_feature_is_found_where_it_moved_in_a_wide_ellipse():
    for seed in range(5):
        uv = np.array([320.0 + 7 * seed, 240.0 - 5 * seed])
        shift = np.array([4.3, -3.6])
        z, found, z2 = search_at(textured(seed), uv, shift, sigma_px=8.0)
        assert found and np.isnan(z2).all(), seed
        np.testing.assert_allclose(z, uv + shift, atol=0.15)


def test_a_repeated_pattern_is_ambiguous_only_when_its_ellipse_holds_two_copies():
    for seed in range(5):
        img = tiled(seed)
        uv = np.array([320.0 + 3 * seed, 240.0 + 2 * seed])
        shift = np.array([2.4, -1.7])
        # An ellipse of 3 sigma = 24 px holds copies 16 px apart: found, and a second place a
        # whole period from the first.
        z, found, z2 = search_at(img, uv, shift, sigma_px=8.0)
        assert found, seed
        d = np.abs(z2 - z)
        assert max(d) > PERIOD - 1.5 and np.all((d < 1.5) | (np.abs(d - PERIOD) < 1.5)), (seed, z, z2)
        # One of 3 sigma = 4.5 px holds only the true copy: matched where it moved, unambiguous.
        z, found, z2 = search_at(img, uv, shift, sigma_px=1.5)
        assert found and np.isnan(z2).all(), seed
        np.testing.assert_allclose(z, uv + shift, atol=0.2)
