"""A natural feature's persistent residual (MapFeature.drift): folded in after each update and
turned into a larger measurement variance by the tracker (measure.Measurement.select)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import slam_testing as st
from runtime.sequence import Target
from runtime.slam.config import DEFAULT_CONFIG, MapSettings
from runtime.slam.system import MonoSLAM
from runtime.slam.map_feature import MapFeature

CAM = st.PINHOLE
RECT = st.rectangle(0.21, 0.15)


def _feature() -> MapFeature:
    return MapFeature(0, np.zeros((5, 5), np.float32), 0, np.zeros(3))


def test_a_persistent_residual_is_kept_and_white_residuals_average_out():
    """A residual that keeps its sign (a sliding match) stays as the drift and grows the variance
    by 1 + gain |drift|^2 / sigma^2; white residuals of the same size average to little."""
    f = _feature()
    assert f.drift is None and f.drift_variance_scale(4.0, 1.0) == 1.0
    for _ in range(40):
        f.note_residual([1.5, -0.5], 0.1)
    np.testing.assert_allclose(f.drift, [1.5, -0.5])
    np.testing.assert_allclose(f.drift_variance_scale(4.0, 1.0), 1.0 + 4.0 * 2.5)
    np.testing.assert_allclose(f.drift_variance_scale(4.0, 4.0), 1.0 + 4.0 * 2.5 / 4.0)
    # The exponential mean: a step from 0 to 1 px reaches 1 - 0.9^k after k frames.
    g = _feature()
    g.note_residual([0.0, 0.0], 0.1)
    for _ in range(10):
        g.note_residual([1.0, 0.0], 0.1)
    np.testing.assert_allclose(g.drift, [1.0 - 0.9**10, 0.0])
    # White residuals of 1.58 px rms (as large as the sliding one): drift variance 2 a / (2 - a).
    rng = np.random.default_rng(0)
    w = _feature()
    scales = []
    for r in rng.normal(0.0, np.sqrt(2.5 / 2), (2000, 2)):
        w.note_residual(r, 0.1)
        scales.append(w.drift_variance_scale(4.0, 1.0))
    assert 1.2 < np.mean(scales[100:]) < 2.0          # expected 1 + 4 * 2.5 * 0.1 / 1.9 = 1.53


def test_the_tracker_measures_a_drifting_feature_with_a_larger_variance():
    """Through measure.Measurement.select: the same feature's innovation covariance grows by its drift's
    variance scale (the target's points, never given a drift, are unchanged), and not at all
    with drift_gain 0."""
    r0 = np.array([0.05, -0.55, 0.25])
    R0 = st.look_at(r0, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    img = st.render_target_scene(CAM, R0, r0, RECT, card_margin=0.03, background=st.texture(1))
    slam = MonoSLAM(CAM, DEFAULT_CONFIG, MapSettings(use_imu=False, measure_max=200), imu=False)
    slam.start(img, 0.0, Target(RECT, st.pixels(CAM, R0, r0, RECT)))
    for i in (1, 2, 3):
        slam.process(img, i / 30)
    track = slam.track
    for f in track.features:
        f.drift = None                                # a clean slate: only the one set below
    pred0, S0, r0_scale, _, _ = track.measurement.select(track.map)
    natural = [j for j, k in enumerate(pred0.ks) if not track.features[k].known]
    assert natural, "the scene gave no natural feature in view"
    j = natural[0]
    k = int(pred0.ks[j])
    track.features[k].drift = np.array([2.0, 0.0])
    pred1, S1, r1_scale, _, _ = track.measurement.select(track.map)
    assert list(pred1.ks) == list(pred0.ks)
    scale = 1.0 + slam.settings.drift.drift_gain * 4.0 / DEFAULT_CONFIG.sigma_pixel**2
    np.testing.assert_allclose(r1_scale[j], r0_scale[j] * scale)
    # Its noise (the pixel noise times its shape, templates.match_noise_shape) grows by the scale.
    R = DEFAULT_CONFIG.sigma_pixel**2 * r0_scale[j]
    np.testing.assert_allclose(S1[j] - S0[j], (scale - 1.0) * R, atol=1e-9)
    others = [i for i in range(len(pred0.ks)) if i != j]
    np.testing.assert_allclose(S1[others], S0[others])
    track.measurement.settings = replace(slam.settings, drift_gain=0.0)
    _, S2, _, _, _ = track.measurement.select(track.map)
    np.testing.assert_allclose(S2, S0)
