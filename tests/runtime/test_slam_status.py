"""The tracking status (records.TrackingStatus, MonoSLAM.status) through a start, a blank view
that loses the track, and a saved map's session that relocalises."""

from __future__ import annotations

import numpy as np

import test_slam_startup as su
from runtime.sequence import Target
from runtime.slam.config import MapSettings
from runtime.slam.map_io import load_map, save_map
from runtime.slam.records import TrackingStatus
from runtime.slam.system import MonoSLAM

SETTINGS = MapSettings(use_imu=False, lost_after=4)


def test_the_status_follows_the_start_a_loss_and_a_saved_maps_relocalisation(tmp_path):
    img, uv = su.scene("near oblique")
    slam = MonoSLAM(su.CAM, settings=SETTINGS)
    assert slam.status is TrackingStatus.INITIALISING
    slam.start(img, 0.0, Target(su.RECT, uv + 2.0))
    assert slam.status is TrackingStatus.TRACKING
    for k in range(1, 6):
        slam.process(img, k / 30)
    assert slam.status is TrackingStatus.TRACKING
    saved = load_map(save_map(tmp_path / "m.npz", slam), su.CAM)
    # A blank view matches nothing: recently lost for lost_after - 1 frames, then lost.
    blank = np.full_like(img, 128)
    seen = [slam.process(blank, (6 + k) / 30) and slam.status for k in range(SETTINGS.relocalisation.lost_after)]
    assert seen == [TrackingStatus.RECENTLY_LOST] * (SETTINGS.relocalisation.lost_after - 1) + [TrackingStatus.LOST]
    assert slam.lost and not slam.localised

    session = MonoSLAM(su.CAM, settings=SETTINGS)
    session.start_from_map(saved, 0.0)
    assert session.status is TrackingStatus.INITIALISING and not session.localised
    statuses = []
    for k in range(1, 8):
        session.process(img, k / 30)
        statuses.append(session.status)
        if statuses[-1] is not TrackingStatus.INITIALISING:
            break
    assert statuses[-1] is TrackingStatus.RELOCALISED and session.localised
    # Found, the next frame's status is the lost rule's again, from its own matches.
    st = session.process(img, (len(statuses) + 1) / 30)
    assert session.status is (TrackingStatus.TRACKING if st.matched >= 3 else TrackingStatus.RECENTLY_LOST)
