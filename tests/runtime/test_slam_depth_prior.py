"""New inverse-depth features start at the depths the map holds (inverse_depth.scene_prior),
through the tracker's own feature addition (mapping.MapManager.add)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import slam_testing as st
from runtime.sequence import Target
from runtime.slam.config import DEFAULT_CONFIG, MapSettings
from runtime.slam.corners import grey
from runtime.slam.features import INVERSE_DEPTH
from runtime.slam.filter import convert_to_point
from runtime.slam.system import FrameStats, MonoSLAM, SearchView

CAM = st.PINHOLE
RECT = st.rectangle(0.21, 0.15)


def tracker_with_points(settings: MapSettings):
    """A tracker on a textured card whose natural features are points at chosen distances along
    their rays; returns it, the image and the natural features' indices."""
    r0 = np.array([0.05, -0.55, 0.25])
    R0 = st.look_at(r0, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    img = st.render_target_scene(CAM, R0, r0, RECT, card_margin=0.03, background=st.texture(1))
    slam = MonoSLAM(CAM, DEFAULT_CONFIG, settings, imu=False)
    slam.start(img, 0.0, Target(RECT, st.pixels(CAM, R0, r0, RECT)))
    for i in (1, 2):
        slam.process(img, i / 30)
    natural = [k for k, f in enumerate(slam.track.features) if not f.known]
    assert len(natural) >= 8
    convert_to_point(slam.state, natural)
    return slam, img, natural


def place(slam, ks, distances) -> None:
    """Feature ``ks``' points moved along their rays from the camera to ``distances``, m."""
    state = slam.state
    for k, d in zip(ks, distances):
        sl = state.feature_slice(k)
        ray = state.x[sl] - state.r
        state.x[sl] = state.r + ray / np.linalg.norm(ray) * d


def add_after(slam, img, used_ks, remove_first: int | None = None) -> list[int]:
    """The tracker's feature addition after a frame that used features ``used_ks``, with feature
    ``remove_first`` deleted in between (as _delete may); returns the new features' indices."""
    track = slam.track
    ks = np.arange(len(track.features))
    used = np.isin(ks, used_ks)
    track.map.last = SearchView(np.array([f.id for f in track.features]), np.zeros((len(ks), 2)),
                                np.tile(np.eye(2), (len(ks), 1, 1)), np.zeros((len(ks), 2)), used, ks)
    if remove_first is not None:
        track.map.remove([remove_first], FrameStats(frame=3, t=0.1))
    before = len(track.features)
    track.mapping.add(grey(img), track.map, FrameStats(frame=3, t=0.1), 3, 0)
    new = list(range(before, len(track.features)))
    assert new and (slam.state.kinds[new] == INVERSE_DEPTH).all()
    return new


def rho_and_sigma(slam, k) -> tuple[float, float]:
    s = slam.state.feature_slice(k).start + 5
    return float(slam.state.x[s]), float(np.sqrt(slam.state.P[s, s]))


def test_new_features_start_at_the_median_depth_of_the_frames_matches():
    """Five used points at 1.5-6 m (median 3 m) and the unused ones at 20 m: the new features'
    inverse depth is 1/3, not the configured 1 m; the deletion before the addition renumbers the
    map, and the used points are still the ones read. With the relative width 0.5 (a target's
    map) the width is 1/6, or with the scene's spread half the 16th-84th percentile range of
    their inverse depths (1/6, 0.2, 1/3, 0.5, 2/3: 0.188 to 0.56), 0.186, which is wider; with a
    two-view start's relative width (2) it is 2/3, wider than either."""
    for spread, relative, width in ((False, None, 1 / 6), (True, None, 0.186), (True, 2.0, 2 / 3)):
        settings = MapSettings(use_imu=False, scene_depth_spread=spread)
        if relative is not None:
            settings = replace(settings, inverse_depth=replace(settings.inverse_depth, scene_relative_width=relative))
        slam, img, natural = tracker_with_points(settings)
        used, unused = natural[1:6], [natural[0]] + natural[6:]
        place(slam, used, [1.5, 2.0, 3.0, 5.0, 6.0])
        place(slam, unused, [20.0] * len(unused))
        new = add_after(slam, img, used, remove_first=natural[0])
        for k in new:
            rho, sigma = rho_and_sigma(slam, k)
            assert rho == pytest.approx(1 / 3) and sigma == pytest.approx(width, rel=1e-6)


@pytest.mark.parametrize("case", ["four used", "fixed by the settings"])
def test_the_configured_prior_without_enough_matches_or_when_fixed(case):
    settings = MapSettings(use_imu=False)
    if case == "fixed by the settings":
        settings = replace(settings, scene_depth_prior=False)
    slam, img, natural = tracker_with_points(settings)
    place(slam, natural, [3.0] * len(natural))
    used = natural[:4] if case == "four used" else natural
    for k in add_after(slam, img, used):
        rho, sigma = rho_and_sigma(slam, k)
        idp = settings.inverse_depth
        assert rho == pytest.approx(idp.rho0) and sigma == pytest.approx(idp.sigma_rho, rel=1e-6)
