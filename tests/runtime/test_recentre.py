"""Path A's visual outer loop (runtime.apps.recentre): on frames rendered through known pure
rotations (test_stabilise's texture), each correction turns the optic axis back towards the
fovea's reference by the fraction ``1 - exp(-gain dt)``, and fed back it decays the offset
exponentially; the task refuses it where it has no meaning."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from runtime.apps.closed_loop import Task
from runtime.apps.recentre import Recentring
from test_stabilise import CAM, angle_deg, render, rot   # the same directory (pytest prepends it)

DT = 1 / 30


def _no_imu():
    return np.zeros((0, 7))


@pytest.mark.parametrize("gain", [1.0, 4.0])
def test_one_correction_turns_the_axis_back_by_the_gain_fraction(gain):
    rc = Recentring(CAM, gain)
    assert np.allclose(rc.correction(0.0, render(np.eye(3)), _no_imu()), np.eye(3))   # the reference
    R_cam0_cam = rot([0.0, 4.0, 0.0]) @ rot([-1.5, 0.0, 0.0])                      # pan 4, tilt 1.5 deg
    R_turn = rc.correction(DT, render(R_cam0_cam), _no_imu())
    # The reference's optic axis seen from the turned camera: the wanted direction.
    d = R_cam0_cam.T @ np.array([0.0, 0.0, 1.0])
    full = math.degrees(math.acos(d[2]))
    turned = Rotation.from_matrix(R_turn).as_rotvec()
    want = (1 - math.exp(-gain * DT)) * full
    assert abs(math.degrees(np.linalg.norm(turned)) - want) < 0.03 * full
    # About the axis that brings the optic axis onto d (perpendicular to both).
    axis = np.cross([0.0, 0.0, 1.0], d)
    assert np.degrees(np.arccos(np.dot(turned, axis) / np.linalg.norm(turned) / np.linalg.norm(axis))) < 2.0
    # The fovea's offset points the same way, in pixels.
    assert np.sign(rc.offset_px[0]) == np.sign(d[0]) and np.sign(rc.offset_px[1]) == np.sign(d[1])


def test_fed_back_the_offset_decays_with_the_time_constant():
    gain = 3.0
    rc = Recentring(CAM, gain)
    rc.correction(0.0, render(np.eye(3)), _no_imu())
    R = rot([0.0, -5.0, 0.0]) @ rot([2.0, 0.0, 0.0])     # a disturbance the IMU loop did not cancel
    start = angle_deg(np.eye(3), R)
    n = 30
    for k in range(1, n + 1):
        R = R @ rc.correction(k * DT, render(R), _no_imu())   # the head holds the corrected attitude
    left = angle_deg(np.eye(3), R)
    expect = start * math.exp(-gain * (n - 1) * DT)           # the first frame sets the clock
    assert abs(left - expect) < 0.15 * expect + 0.05, (left, expect)
    assert left < 0.2 * start


def test_identity_without_a_view_or_time():
    rc = Recentring(CAM, 2.0)
    blank = np.zeros((CAM.height, CAM.width, 3), np.uint8)
    assert np.allclose(rc.correction(0.0, blank, _no_imu()), np.eye(3))
    assert np.allclose(rc.correction(DT, blank, _no_imu()), np.eye(3))


def test_bad_gains_and_tasks_are_refused():
    with pytest.raises(ValueError, match="gain"):
        Recentring(CAM, 0.0)
    with pytest.raises(ValueError, match="gain"):
        Recentring(CAM, float("nan"))
    with pytest.raises(ValueError, match="stabilise only"):
        Task("fixate", np.zeros((1, 3)), recentre_per_s=2.0)
    with pytest.raises(ValueError, match="recentre_per_s"):
        Task("stabilise", recentre_per_s=-1.0)
    assert Task("stabilise", recentre_per_s=2.0).recentre_per_s == 2.0
