"""New features' least contrast: the image noise estimated from the image itself, and the
template contrast below which noise alone fails the match score (corners.noise_sigma,
corners.min_template_std), against synthetic images whose noise is known."""

import cv2
import numpy as np
import pytest

from runtime.slam.corners import min_template_std, new_features, noise_sigma
from runtime.slam.appearance import extract_template, search


def scene(rng, size=(240, 320)):
    """Blocks of random grey with sharp edges and blurred texture: edges and texture on a
    quarter of the pixels or more, as a real scene has."""
    h, w = size
    img = np.kron(rng.uniform(40, 215, (h // 20, w // 20)), np.ones((20, 20)))
    tex = cv2.GaussianBlur(rng.uniform(-60, 60, size).astype(np.float32), (0, 0), 2.0)
    img[: h // 2] += tex[: h // 2]
    return img


@pytest.mark.parametrize("sigma", [0.8, 2.0, 4.0])
def test_noise_sigma_recovers_the_noise_under_edges_and_texture(sigma):
    rng = np.random.default_rng(int(10 * sigma))
    img = np.clip(np.rint(scene(rng) + sigma * rng.standard_normal((240, 320))), 0, 255).astype(np.uint8)
    est = noise_sigma(img.astype(np.float32))
    # 8-bit rounding adds 1/12 grey level^2 of its own.
    assert est == pytest.approx(np.sqrt(sigma**2 + 1 / 12), rel=0.12)


def test_a_template_at_the_least_contrast_scores_the_threshold_on_noise_alone():
    # Monte Carlo of the derivation: a random pattern scaled to the least std, matched between
    # two independently noisy copies, scores 2 (1 - ZNCC) ~ match_score on average.
    sigma, match_score = 2.0, 0.25
    s_min = min_template_std(sigma, match_score)
    assert s_min == pytest.approx(2.0 * np.sqrt(8.0))
    rng = np.random.default_rng(3)
    scores = []
    for _ in range(400):
        pattern = rng.standard_normal((15, 15))
        signal = pattern / pattern.std() * np.sqrt(s_min**2 - sigma**2)     # measured std^2 = s^2 + sigma^2
        a = signal + sigma * rng.standard_normal((15, 15))
        b = signal + sigma * rng.standard_normal((15, 15))
        za, zb = (a - a.mean()) / a.std(), (b - b.mean()) / b.std()
        scores.append(2 * (1 - (za * zb).mean()))
    assert np.mean(scores) == pytest.approx(match_score, rel=0.15)
    assert min_template_std(0.1, match_score) == 2.0          # never below a flat patch's floor


def test_new_features_keep_only_corners_the_noise_lets_be_matched():
    # Two squares on a noisy grey field: one at high contrast, one at a contrast noise drowns.
    rng = np.random.default_rng(5)
    sigma = 2.0
    img = np.full((240, 320), 120.0)
    img[60:80, 60:80] += 30.0
    img[150:170, 220:240] += 8.0
    noisy = np.clip(np.rint(img + sigma * rng.standard_normal(img.shape)), 0, 255).astype(np.float32)
    floor = min_template_std(noise_sigma(noisy), 0.25)
    kept = new_features(noisy, np.zeros((0, 2)), 20, min_std=floor)
    near_faint = [uv for uv, _ in kept if 210 <= uv[0] <= 250 and 140 <= uv[1] <= 180]
    near_strong = [uv for uv, _ in kept if 50 <= uv[0] <= 90 and 50 <= uv[1] <= 90]
    assert near_strong and not near_faint
    # The faint square's corners are corners, and a 2-level floor takes them.
    loose = new_features(noisy, np.zeros((0, 2)), 20, min_std=2.0)
    faint = [(uv, t) for uv, t in loose if 210 <= uv[0] <= 250 and 140 <= uv[1] <= 180]
    assert faint
    # ... and they are what the floor is for: in a second noisy frame they fail the match score.
    again = np.clip(np.rint(img + sigma * rng.standard_normal(img.shape)), 0, 255).astype(np.float32)
    found = [search(again, t, np.asarray(uv, float), np.diag([4.0, 4.0]), max_score=0.25).found for uv, t in faint]
    assert np.mean(found) < 0.5
