"""The frame's active search (matching.match_features) against synthetic images with known
answers: a match is where the template's content moved to."""

import cv2
import numpy as np

from kinematics.camera import default_camera
from runtime.slam.appearance import match_features
from runtime.slam.appearance import extract_template
from runtime.slam.map_feature import MapFeature


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


def test_the_scores_inside_the_ellipse_are_opencvs_zncc_and_flat_windows_are_left_out():
    """The compiled search's scores against an independent ZNCC, OpenCV's TM_CCOEFF_NORMED over
    the ellipse's box: equal (2 (1 - ZNCC)) at every position inside a tilted ellipse whose
    window is not flat, and no score outside it or on a flat window."""
    from runtime.slam.appearance.zncc import FLAT_VARIANCE, _zncc_in_ellipse

    for seed in range(3):
        img = textured(seed, (240, 320))
        img[112:130, 165:190] = 77.0                           # a flat stretch some windows cover
        tpl = np.ascontiguousarray(img[60 + seed:69 + seed, 40:49])
        uv = np.array([171.3 + seed, 118.6])
        S = np.array([[40.0, 18.0], [18.0, 25.0]])
        Si = np.linalg.inv(S)
        h = tpl.shape[0] // 2
        u0, v0, nu, nv = 150, 100, 44, 38
        grid = _zncc_in_ellipse(img, tpl, u0, v0, nu, nv, uv[0], uv[1], Si[0, 0], Si[0, 1], Si[1, 1], 9.0)
        roi = img[v0 - h:v0 + nv + h, u0 - h:u0 + nu + h]
        ncc = cv2.matchTemplate(roi, tpl, cv2.TM_CCOEFF_NORMED)
        win_var = cv2.boxFilter(roi * roi, -1, (9, 9), normalize=True)[h:-h, h:-h] \
            - cv2.boxFilter(roi, -1, (9, 9), normalize=True)[h:-h, h:-h] ** 2
        jj, ii = np.mgrid[0:nv, 0:nu]
        d = np.stack([u0 + ii - uv[0], v0 + jj - uv[1]], -1)
        inside = np.einsum("...i,ij,...j->...", d, Si, d) <= 9.0
        scored = inside & (win_var >= FLAT_VARIANCE + 1e-3)
        assert scored.sum() > 300 and (inside & (win_var < FLAT_VARIANCE - 1e-3)).sum() > 50, seed
        np.testing.assert_allclose(grid[scored], 2 * (1 - ncc[scored]), atol=2e-4)
        assert np.isinf(grid[~inside]).all()
        assert np.isinf(grid[inside & (win_var < FLAT_VARIANCE - 1e-3)]).all()


def test_the_coarse_to_fine_search_scores_the_exhaustive_best_the_same_from_a_fraction_of_positions():
    """The coarse-to-fine search (one pyramid level, then descents at every pixel) against the
    exhaustive one, on integer grey levels (as decoded images are) with 15 x 15 templates in
    tilted 3-sigma ellipses of 400-1500 px, each holding the template's content twice (once with
    noise, a weaker rival): the same best position and score, to the bit, and every score it
    computes equal to the exhaustive one there, at under a fifth of the positions."""
    from runtime.slam.appearance.zncc import _best_in_grid, _zncc_coarse_to_fine, _zncc_in_ellipse

    rng = np.random.default_rng(7)
    fractions = []
    for case in range(24):
        img = np.round(textured(100 + case, (240, 320)))
        src = rng.integers((20, 20), (300, 220))
        tpl = img[src[1] - 7:src[1] + 8, src[0] - 7:src[0] + 8].copy()
        uv = np.array([160.0, 120.0]) + rng.uniform(-3, 3, 2)
        S = np.diag(rng.uniform(12.0, 40.0, 2))
        S[0, 1] = S[1, 0] = rng.uniform(-0.5, 0.5) * np.sqrt(S[0, 0] * S[1, 1])
        # The content at a true position and a noisy copy at another, both inside the ellipse
        # and apart.
        while True:
            at = np.round(uv + rng.uniform(-1.6, 1.6, (2, 2)) @ np.linalg.cholesky(S).T).astype(int)
            if np.abs(at[0] - at[1]).max() >= 16:
                break
        img[at[1, 1] - 7:at[1, 1] + 8, at[1, 0] - 7:at[1, 0] + 8] = np.clip(np.round(tpl + rng.normal(0, 12.0, tpl.shape)), 0, 255)
        img[at[0, 1] - 7:at[0, 1] + 8, at[0, 0] - 7:at[0, 0] + 8] = tpl
        Si = np.linalg.inv(S)
        hu, hv = 3 * np.sqrt(S[0, 0]), 3 * np.sqrt(S[1, 1])
        u0, v0 = int(np.floor(uv[0] - hu)), int(np.floor(uv[1] - hv))
        nu, nv = int(np.ceil(uv[0] + hu)) - u0 + 1, int(np.ceil(uv[1] + hv)) - v0 + 1
        args = (img, tpl, u0, v0, nu, nv, uv[0], uv[1], Si[0, 0], Si[0, 1], Si[1, 1], 9.0)
        full = _zncc_in_ellipse(*args)
        fast = _zncc_coarse_to_fine(*args, 3, 0.0, 10**6, 0)        # never exhaustive
        assert _best_in_grid(full) == _best_in_grid(fast), case
        i, j, score = _best_in_grid(full)
        assert score < 1e-4 and np.hypot(u0 + i - at[0, 0], v0 + j - at[0, 1]) < 0.5, case   # the copy
        seen = np.isfinite(fast)
        np.testing.assert_array_equal(fast[seen], full[seen])
        fractions.append(seen.sum() / np.isfinite(full).sum())
    assert max(fractions) < 0.2, fractions


def test_a_level_valley_is_searched_exhaustively():
    """An edge's template in an image of the edge with noise: its scores along the edge are level
    (a coarse-to-fine descent would stop at a local best), so the search is the exhaustive
    one, every score of the ellipse, unless the region is large; a distinct feature's is not."""
    from runtime.slam.appearance.zncc import (COARSE_LEVEL, COARSE_LEVEL_MOST, VALLEY_EXHAUSTIVE_MAX_PX, _best_in_grid,
                                       _zncc_coarse_to_fine, _zncc_in_ellipse)

    rng = np.random.default_rng(3)
    img = np.where(np.arange(320)[None, :] < 161, 60.0, 190.0) * np.ones((240, 1))
    img = np.round(np.clip(img + rng.normal(0, 3.0, img.shape), 0, 255))
    tpl = img[20:35, 154:169].copy()                             # the edge, far from the search
    Si = np.linalg.inv(np.diag([30.0, 30.0]))
    args = (img, tpl, 140, 100, 41, 41, 160.0, 120.0, Si[0, 0], Si[0, 1], Si[1, 1], 9.0)
    full = _zncc_in_ellipse(*args)
    edge = _zncc_coarse_to_fine(*args, 3, COARSE_LEVEL, COARSE_LEVEL_MOST, VALLEY_EXHAUSTIVE_MAX_PX)
    np.testing.assert_array_equal(edge, full)
    # In a region too large to search exhaustively (a young feature's long ellipse), the
    # descents from the valley's minima still land on the edge, for a fraction of the scores.
    Si_big = np.linalg.inv(np.diag([900.0, 900.0]))
    big = (img, tpl, 70, 30, 181, 181, 160.0, 120.0, Si_big[0, 0], Si_big[0, 1], Si_big[1, 1], 9.0)
    assert 181 * 181 > VALLEY_EXHAUSTIVE_MAX_PX
    wide = _zncc_coarse_to_fine(*big, 3, COARSE_LEVEL, COARSE_LEVEL_MOST, VALLEY_EXHAUSTIVE_MAX_PX)
    wide_full = _zncc_in_ellipse(*big)
    i, j, score = _best_in_grid(wide)
    assert abs(70 + i - 161.5) < 1.5 and score < _best_in_grid(wide_full)[2] + COARSE_LEVEL
    assert np.isfinite(wide).sum() < 0.2 * np.isfinite(wide_full).sum()
    distinct = np.round(textured(5, (240, 320)))
    tpl = distinct[113:128, 153:168].copy()
    args = (distinct, tpl) + args[2:]
    fast = _zncc_coarse_to_fine(*args, 3, COARSE_LEVEL, COARSE_LEVEL_MOST, VALLEY_EXHAUSTIVE_MAX_PX)
    assert np.isfinite(fast).sum() < 0.2 * np.isfinite(_zncc_in_ellipse(*args)).sum()


def _refined_twice(moved: np.ndarray, tpl: np.ndarray, start) -> tuple[np.ndarray, np.ndarray]:
    """The sub-pixel refinement from ``start`` after 10 iterations (the search's) and after 40."""
    from runtime.slam.appearance.refine import AFFINE_DAMPING, refine_affine_kernel

    out = []
    for iterations in (10, 40):
        u, v, ok = refine_affine_kernel(moved, tpl, float(start[0]), float(start[1]), iterations, 0.005,
                                        AFFINE_DAMPING)
        assert ok
        out.append(np.array([u, v]))
    return out[0], out[1]


def test_the_subpixel_refinement_has_a_fixed_point_on_noisy_edges():
    """A 9 x 9 template on vertical stripes (edges: along them nothing fixes the match), the
    image shifted by a known sub-pixel amount with sensor noise added, the refinement started
    within half a pixel: it converges (40 iterations end where 10 do, within 1e-3 px; a shape
    that wanders on, as when its prior was only the step's damping, moved the centre up to
    0.4 px) and puts the match across the edges within 0.3 px of the truth (median 0.1)."""
    across = []
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        stripes = rng.uniform(0, 255, (240, 40)).astype(np.float32)
        img = cv2.GaussianBlur(cv2.resize(stripes, (320, 240), interpolation=cv2.INTER_NEAREST), (0, 0), 1.0)
        uv = np.array([150.0 + 3 * seed, 110.0 + 2 * seed])
        tpl = extract_template(img, uv, 9)
        shift = rng.uniform(-2, 2, 2)
        moved = cv2.warpAffine(img, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (320, 240),
                               flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        moved = moved + rng.normal(0, 3.0, moved.shape).astype(np.float32)
        truth = uv + shift
        z10, z40 = _refined_twice(moved, tpl, np.round(truth) + rng.uniform(-0.4, 0.4, 2))
        assert np.linalg.norm(z40 - z10) <= 1e-3, seed
        across.append(abs(z10[0] - truth[0]))
    assert np.median(across) <= 0.1 and max(across) <= 0.3, across


def test_the_subpixel_refinement_fits_a_turned_and_scaled_view():
    """Texture turned by up to 4 degrees and scaled by up to 4% about the feature and shifted:
    started within half a pixel, the refinement converges and lands within 0.2 px (median 0.1)
    of where the template's centre moved, the prior on the shape notwithstanding."""
    err = []
    for seed in range(20):
        rng = np.random.default_rng(200 + seed)
        img = textured(seed, (240, 320))
        uv = np.array([150.0 + 3 * seed, 110.0 + 2 * seed])
        tpl = extract_template(img, uv, 9)
        ang, s = np.radians(rng.uniform(-4, 4)), rng.uniform(0.96, 1.04)
        shift = rng.uniform(-2, 2, 2)
        A = s * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        M = np.hstack([A, (uv + shift - A @ uv)[:, None]]).astype(np.float32)
        moved = cv2.warpAffine(img, M, (320, 240), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        truth = uv + shift
        z10, z40 = _refined_twice(moved, tpl, np.round(truth) + rng.uniform(-0.4, 0.4, 2))
        assert np.linalg.norm(z40 - z10) <= 1e-3, seed
        err.append(np.linalg.norm(z10 - truth))
    assert np.median(err) <= 0.1 and max(err) <= 0.2, err
