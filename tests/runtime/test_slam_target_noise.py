"""The printed target's corners are measured with their own, smaller noise (known_sigma_px):
their innovation covariances are the natural features' with R scaled, and the camera's
uncertainty after a frame of target measurements shrinks accordingly."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import test_slam_startup as su
from runtime.sequence import Target
from runtime.slam.config import MapSettings
from runtime.slam.measurement import predict
from runtime.slam.system import MonoSLAM


def started(known_sigma_px: float) -> MonoSLAM:
    img, uv = su.scene("near oblique")
    s = MonoSLAM(su.CAM, settings=replace(MapSettings(use_imu=False), known_sigma_px=known_sigma_px))
    s.start(img, 0.0, Target(su.RECT, uv + 2.0))
    return s


def test_target_corners_use_their_own_noise_and_natural_features_the_view_scaled_one():
    s = started(0.5)
    tr = s.track
    ok, scale = tr.map.views(predict(tr.state, np.arange(tr.state.n_features), s.cam), tr.world_points(), s.cam, s.settings,
                             s.cfg.sigma_pixel)
    known = np.array([f.known for f in tr.features])
    assert known.sum() == 4 and ok[known].all()
    np.testing.assert_allclose(scale[known], (0.5 / s.cfg.sigma_pixel) ** 2)
    assert (scale[~known] >= 1.0).all()


def test_the_target_at_half_a_pixel_tightens_the_pose_more_than_at_one():
    img, _ = su.scene("near oblique")
    sig = {}
    for k in (0.5, 1.0):
        s = started(k)
        s.process(img, 1 / 30)
        sig[k] = np.sqrt(np.trace(s.state.P[:3, :3]))
    assert sig[0.5] < 0.8 * sig[1.0], sig


def test_measure_settings_keep_new_features_below_what_is_measured():
    import pytest

    s = MapSettings().with_measure(30)
    assert (s.measure.measure_max, s.measure.visible_min) == (30, 24)
    assert MapSettings().with_measure(3).measure.visible_min == 3
    with pytest.raises(ValueError, match="visible_min = 48 exceeds measure_max = 30"):
        replace(MapSettings(), measure_max=30)
