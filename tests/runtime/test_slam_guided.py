"""Guided search (guided.guided_regions): the first features' matches give the rest posterior
search regions. Checked against the filter itself: an EKF update with those matches, then the
rest predicted, must give the same predictions and ellipses (to first order), an outlier among
the first must be left out, and too few agreeing matches must leave the rest unguided."""

from __future__ import annotations

import numpy as np
from test_slam_ransac import CAM, scene

from runtime.slam.config import RansacSettings
from runtime.slam.filter import innovation_covariances, update
from runtime.slam.guided import guided_regions
from runtime.slam.measurement import predict

RANSAC = RansacSettings()


def _oracle(s, ks, z, used):
    """The rest's predictions and ellipses after a real EKF update with the matches ``used``."""
    o = s.copy()
    update(o, ks[used], z[used], CAM, 1.0)
    rest = np.setdiff1d(ks, ks[:10])
    p = predict(o, rest, CAM)
    return p.uv, innovation_covariances(o, p, 1.0)


def test_the_rest_are_predicted_as_after_an_ekf_update_with_the_first():
    shifts, shrink = [], []
    for seed in range(8):
        s, ks, z, pred, S_prior, _, _ = scene(seed, outlier_fraction=0.0)
        first = np.arange(10)
        g = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=0.0)
        assert g is not None and g.used.all()
        uv_o, S_o = _oracle(s, ks, z, first[g.used])
        rest = np.arange(10, len(ks))
        # First order: the same as the update (which relinearises the rest at the new mean).
        np.testing.assert_allclose(g.uv, uv_o, atol=0.1)
        np.testing.assert_allclose(np.linalg.det(g.S) / np.linalg.det(S_o), 1.0, atol=0.06)   # the ellipses' areas
        np.testing.assert_allclose(np.diagonal(g.S, axis1=1, axis2=2), np.diagonal(S_o, axis1=1, axis2=2), rtol=0.04)
        shifts.append(np.median(np.linalg.norm(uv_o - pred.uv[rest], axis=1)))
        shrink.append(np.median(np.linalg.det(g.S) / np.linalg.det(S_prior[rest])))
        # The true matches lie in the guided 3-sigma ellipses.
        nu = z[rest] - g.uv
        d2 = np.einsum("ia,iab,ib->i", nu, np.linalg.inv(g.S), nu)
        assert (d2 < 9.0).mean() >= 0.95
    # Not a no-op: the guidance moved the predictions and shrank the ellipses.
    assert np.median(shifts) > 0.5 and np.median(shrink) < 0.3


def test_an_outlier_among_the_first_is_left_out():
    for seed in range(6):
        s, ks, z, pred, S_prior, out, _ = scene(seed, outlier_fraction=0.3)
        first = np.arange(10)
        g = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=0.0)
        good = first[~out[first]]
        assert out[first].any() and g is not None
        assert np.array_equal(g.used, ~out[first])
        uv_o, _ = _oracle(s, ks, z, first[g.used])
        np.testing.assert_allclose(g.uv, uv_o, atol=0.1)


def test_too_few_agreeing_matches_leave_the_rest_unguided():
    s, ks, z, pred, S_prior, _, _ = scene(0, outlier_fraction=0.0)
    first = np.arange(10)
    zf = z[first].copy()
    zf[2:] = np.nan                               # two found: below the three needed
    assert guided_regions(s, pred, S_prior, first, zf, RANSAC, floor_px=0.0) is None
    g = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=1.5)
    g0 = guided_regions(s, pred, S_prior, first, z[first], RANSAC, floor_px=0.0)
    np.testing.assert_allclose(g.S - g0.S, np.broadcast_to(1.5 ** 2 * np.eye(2), g.S.shape))
