"""The map's size cap: which natural features leave a full map (system.cap_victims and
mapping.MapManager.delete)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import slam_testing as st
from runtime.sequence import Target
from runtime.slam.config import DEFAULT_CONFIG, MapSettings
from runtime.slam.features import INVERSE_DEPTH, POINT
from runtime.slam.filter import convert_to_point
from runtime.slam.system import NARROW_WIDTH_PX, FrameStats, MonoSLAM, cap_victims

CAM = st.PINHOLE
RECT = st.rectangle(0.21, 0.15)


def test_cap_victims_order():
    """Out of view before in view; out of view, inverse-depth before points even when a point is
    older; the longest unseen first within a kind."""
    #                 0   1   2   3   4   5
    last_seen = np.array([50, 10, 40, 5, 30, 60])
    in_view = np.array([True, False, False, False, False, True])
    is_point = np.array([False, True, False, True, False, True])
    assert cap_victims(2, last_seen, in_view, is_point).tolist() == [4, 2]
    assert cap_victims(4, last_seen, in_view, is_point).tolist() == [4, 2, 3, 1]
    # Beyond everything out of view: the in-view ones, inverse-depth first.
    assert cap_victims(5, last_seen, in_view, is_point).tolist() == [4, 2, 3, 1, 0]
    assert cap_victims(0, last_seen, in_view, is_point).tolist() == []


def test_a_full_map_drops_unsettled_features_out_of_view_first():
    """Through the tracker's own deletion step: with the map over its cap by two, the two
    inverse-depth features out of view go, though the points out of view were seen longer ago
    and every feature in view is older still."""
    r0 = np.array([0.05, -0.55, 0.25])
    R0 = st.look_at(r0, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    img = st.render_target_scene(CAM, R0, r0, RECT, card_margin=0.03, background=st.texture(1))
    slam = MonoSLAM(CAM, DEFAULT_CONFIG, MapSettings(use_imu=False), imu=False)
    slam.start(img, 0.0, Target(RECT, st.pixels(CAM, R0, r0, RECT)))
    for i in (1, 2, 3):                       # four new features a frame
        slam.process(img, i / 30)
    track, state = slam.track, slam.state
    natural = [k for k, f in enumerate(track.features) if not f.known]
    assert len(natural) >= 8 and (state.kinds[natural] == INVERSE_DEPTH).all()
    # Two of them become points; each is given a history: in view or not, seen when.
    convert_to_point(state, natural[:2])
    assert (state.kinds[natural[:2]] == POINT).all()
    story = {natural[0]: (False, 3), natural[1]: (False, 4),        # points out of view, seen longest ago
             natural[2]: (False, 8), natural[3]: (False, 9),        # inverse-depth out of view
             natural[4]: (True, 1), natural[5]: (True, 2)}          # in view, oldest of all
    for k in natural[6:]:
        story[k] = (True, 10)
    track.map.in_view_ids = {track.features[k].id for k, (seen, _) in story.items() if seen}
    for k, (_, last) in story.items():
        track.features[k].last_seen = last
        track.features[k].attempts = track.features[k].successes = 0     # no deletion for failing
    ids = {k: track.features[k].id for k in natural}
    track.mapping.settings = replace(slam.settings, max_features=len(track.features) - 2)
    track.mapping.delete(track.map, FrameStats(frame=11, t=11 / 30), 11)
    left = {f.id for f in track.features if not f.known}
    assert left == {ids[k] for k in natural} - {ids[natural[2]], ids[natural[3]]}
    assert state.n_features == len(track.features)


def test_inverse_depth_features_convert_below_the_threshold_for_the_image_width():
    """The linearity threshold follows the image's width (MapSettings.inverse_depth.linearity_threshold from
    NARROW_WIDTH_PX wide, linearity_threshold_narrow below), and the tracker's conversion step
    takes exactly the inverse-depth features whose linearity index is below the one in force."""
    settings = MapSettings(use_imu=False, linearity_threshold=0.3, linearity_threshold_narrow=0.7)
    for width in (640, NARROW_WIDTH_PX, NARROW_WIDTH_PX - 2, 320):
        s = width / CAM.width
        cam = replace(CAM, width=width, height=int(CAM.height * s), fx=CAM.fx * s, fy=CAM.fy * s,
                      cx=CAM.cx * s, cy=CAM.cy * s)
        assert MonoSLAM(cam, DEFAULT_CONFIG, settings).linearity_threshold == (0.3 if width >= NARROW_WIDTH_PX else 0.7)

    r0 = np.array([0.05, -0.55, 0.25])
    R0 = st.look_at(r0, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    img = st.render_target_scene(CAM, R0, r0, RECT, card_margin=0.03, background=st.texture(1))
    slam = MonoSLAM(CAM, DEFAULT_CONFIG, MapSettings(use_imu=False), imu=False)
    slam.start(img, 0.0, Target(RECT, st.pixels(CAM, R0, r0, RECT)))
    for i in (1, 2, 3):
        slam.process(img, i / 30)
    track = slam.track
    _, L = track.map.points_and_linearity()
    natural = [k for k, f in enumerate(track.features) if not f.known and slam.state.kinds[k] == INVERSE_DEPTH]
    assert len(natural) >= 8
    assert not track.mapping.conversions(track.map, FrameStats(frame=4, t=4 / 30))[0]       # still far from linear
    track.mapping.linearity_threshold = float(np.median(L[natural]))
    ks = track.mapping.conversions(track.map, FrameStats(frame=4, t=4 / 30))[0]
    assert set(ks) == {k for k in natural if L[k] < track.mapping.linearity_threshold}
    assert 0 < len(ks) < len(natural)
