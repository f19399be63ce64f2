"""Stabilisation with a software fovea: rotations recovered from frames the test renders itself
(a random texture seen through known pure rotations, H = K R K^-1), bad frames, the fovea's
placement, the IMU's pre-warp, the files written, and one short run on the twin."""

from __future__ import annotations

import json
import math
import os

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, default_camera, unproject
from runtime.sequence import SequenceWriter, read_trajectory
from runtime.eval import rotation_errors_deg
from runtime.vision2d.stabilise import (FEW_CORNERS_PREV, FEW_TRACKS, Stabiliser, StabiliseSettings,
                                        fovea_window, frame_rotation, gyro_rotation, residual_motion,
                                        stabilise_sequence, to_grey)

CAM = default_camera()
# The texture is a wider pinhole view from the first camera's centre, so every rotated frame lies
# inside it (no black borders whose edges would move unlike the scene).
SRC_W, SRC_H = 1400, 1100
K_SRC = np.array([[CAM.fx, 0, (SRC_W - 1) / 2], [0, CAM.fy, (SRC_H - 1) / 2], [0, 0, 1.0]])


def _texture(seed: int = 0) -> np.ndarray:
    """(SRC_H, SRC_W, 3) uint8: blurred, upsampled noise (corners at several scales) plus shapes."""
    rng = np.random.default_rng(seed)
    img = np.zeros((SRC_H, SRC_W, 3), np.float32)
    for cell, weight in ((8, 0.5), (24, 0.5)):
        noise = rng.uniform(0, 255, (SRC_H // cell + 1, SRC_W // cell + 1, 3)).astype(np.float32)
        img += weight * cv2.resize(noise, (SRC_W, SRC_H), interpolation=cv2.INTER_CUBIC)
    for _ in range(60):
        c = tuple(int(v) for v in rng.integers(0, 255, 3))
        x, y = (int(v) for v in rng.integers(0, [SRC_W, SRC_H]))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(15, 80)), y + int(rng.integers(15, 80))), c, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(8, 40)), c, -1)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 1.0), 0, 255).astype(np.uint8)


TEXTURE = _texture()


def render(R_cam0_cam: np.ndarray, cam: CameraIntrinsics = CAM) -> np.ndarray:
    """The texture as the camera sees it after turning by R_cam0_cam (no translation).

    Pinhole cameras: warpPerspective with H = K_src R_cam0_cam K^-1 (frame pixel -> texture pixel).
    A lens model: each pixel's ray (kinematics.camera.unproject), rotated, projected in the texture.
    """
    if cam.model == "brown" and cam.k1 == cam.k2 == cam.k3 == cam.p1 == cam.p2 == 0:
        H = K_SRC @ R_cam0_cam @ np.linalg.inv(cam.K)
        return cv2.warpPerspective(TEXTURE, H, (cam.width, cam.height),
                                   flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    rays = unproject(cam, np.column_stack([u.ravel(), v.ravel()])) @ R_cam0_cam.T
    src = rays @ K_SRC.T
    m = (src[:, :2] / src[:, 2:3]).astype(np.float32).reshape(cam.height, cam.width, 2)
    return cv2.remap(TEXTURE, m[..., 0], m[..., 1], cv2.INTER_LINEAR)


def angle_deg(R_a, R_b) -> float:
    return math.degrees(Rotation.from_matrix(np.asarray(R_a).T @ R_b).magnitude())


def rot(rotvec_deg) -> np.ndarray:
    return Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()


def random_path(n: int, step_deg: float, seed: int) -> list[np.ndarray]:
    """n orientations R_cam0_cam, the first the identity, each a random step (all three axes,
    roll included) from the previous one."""
    rng = np.random.default_rng(seed)
    Rs = [np.eye(3)]
    for _ in range(n - 1):
        Rs.append(Rs[-1] @ rot(rng.normal(0, step_deg, 3)))
    return Rs


def write_sequence(root, Rs, images=None, dt=1 / 30, gyro=False, imu_rate=200.0):
    """A sequence folder of the given frames, with ground truth (and a gyro log, constant rate
    between frames, so its integral is exact)."""
    images = images if images is not None else [render(R) for R in Rs]
    with SequenceWriter(root, CAM) as w:
        for k, (R, img) in enumerate(zip(Rs, images)):
            T = np.eye(4)
            T[:3, :3] = R
            w.add_frame(k * dt, img)
            w.add_groundtruth(k * dt, T)
            if gyro and k + 1 < len(Rs):
                rate = Rotation.from_matrix(R.T @ Rs[k + 1]).as_rotvec() / dt
                for ti in np.arange(k * dt, (k + 1) * dt - 1e-9, 1 / imu_rate):
                    w.add_imu(ti, rate, [0.0, 0.0, 9.81])
    return root


# ---------------------------------------------------------------------------------------------

def test_recovers_pure_rotations_to_005_deg():
    settings = StabiliseSettings()
    Rs = random_path(8, 1.5, seed=1)
    frames = [to_grey(render(R)) for R in Rs]
    for k in range(1, len(Rs)):
        truth = Rs[k - 1].T @ Rs[k]
        r = frame_rotation(frames[k - 1], frames[k], CAM, settings)
        assert not r.flagged
        assert r.inliers > 100
        assert angle_deg(r.R_prev_cur, truth) < 0.05, k
    # The no-rotation case is not trivially passed: a 0.3 degree step is resolved too.
    r = frame_rotation(frames[0], to_grey(render(rot([0.3, 0, 0]))), CAM, settings)
    assert angle_deg(r.R_prev_cur, rot([0.3, 0, 0])) < 0.02


def test_any_lens_model_via_undistort():
    # A strongly distorted lens: a pixel-space homography would not fit; bearings do.
    cam = CameraIntrinsics(640, 480, 400.0, 400.0, 322.0, 236.0, model="brown", k1=-0.25, k2=0.06)
    Rs = [np.eye(3), rot([1.0, -2.0, 1.5])]
    a, b = (to_grey(render(R, cam)) for R in Rs)
    r = frame_rotation(a, b, cam, StabiliseSettings())
    assert not r.flagged
    assert angle_deg(r.R_prev_cur, Rs[1]) < 0.05
    # Ignoring the distortion (a pinhole with the same K) gets it measurably wrong.
    pinhole = CameraIntrinsics(640, 480, 400.0, 400.0, 322.0, 236.0)
    r_wrong = frame_rotation(a, b, pinhole, StabiliseSettings(min_inliers=3))
    assert r_wrong.flagged or angle_deg(r_wrong.R_prev_cur, Rs[1]) > 0.1


def test_large_rotation_tracked_with_the_gyro_prediction():
    truth = rot([0, 14.0, 0])  # ~130 px of image motion, beyond the flow pyramid's reach
    a, b = to_grey(render(np.eye(3))), to_grey(render(truth))
    settings = StabiliseSettings()
    blind = frame_rotation(a, b, CAM, settings)
    assert blind.flagged or angle_deg(blind.R_prev_cur, truth) > 1.0
    # A gyro that is 1 degree off: vision measures the remainder.
    predicted = truth @ rot([0.5, -0.7, 0.5])
    r = frame_rotation(a, b, CAM, settings, R_prev_cur_pred=predicted)
    assert not r.flagged
    assert angle_deg(r.R_prev_cur, truth) < 0.05


def test_gyro_rotation_integrates_body_rates():
    dt = 0.005
    t = np.arange(0, 0.1 + 1e-9, dt)
    w = np.tile([0.3, -1.0, 0.5], (len(t), 1))
    # Constant rate: exp(w T), from any start to any end between samples.
    R = gyro_rotation(t, w, 0.012, 0.071)
    assert angle_deg(R, Rotation.from_rotvec(np.array([0.3, -1.0, 0.5]) * 0.059).as_matrix()) < 1e-9
    # Two rates in turn compose in time order on the right (body rates): exp(w1 T1) exp(w2 T2).
    w2 = np.where(t[:, None] < 0.05, [2.0, 0, 0], [0, 2.0, 0])
    R = gyro_rotation(t, w2, 0.0, 0.1)
    expected = rot(np.degrees([0.1, 0, 0])) @ rot(np.degrees([0, 0.1, 0]))
    assert angle_deg(R, expected) < 0.6  # the rate is interpolated over the switch sample
    assert angle_deg(R, expected.T @ np.eye(3)) > angle_deg(R, expected)
    assert np.allclose(gyro_rotation(t, w, 0.05, 0.05), np.eye(3))


def test_fovea_moves_opposite_to_the_rotation_and_stays_inside():
    fw, fh = 320, 240
    cx, cy = CAM.cx, CAM.cy
    # The camera turns right (about its y axis, optical frame y down): the scene, and the first
    # frame's centre, move left in the image, by f tan(angle).
    for yaw in (3.0, 8.0):
        win = fovea_window(CAM, rot([0, yaw, 0]), np.eye(3), (fw, fh))
        assert win.centre[0] == pytest.approx(cx - CAM.fx * math.tan(math.radians(yaw)), abs=1e-6)
        assert win.centre[1] == pytest.approx(cy, abs=1e-6)
        assert not win.clamped
    # Tilting up (about x, a positive turn takes z towards -y, up): the centre moves down.
    win = fovea_window(CAM, rot([5.0, 0, 0]), np.eye(3), (fw, fh))
    assert win.centre[1] == pytest.approx(cy + CAM.fy * math.tan(math.radians(5.0)), abs=1e-6)
    assert win.centre[0] == pytest.approx(cx, abs=1e-6)
    # Too far: clamped to the edge, window inside the image; also behind the camera.
    for R in (rot([0, 40.0, 0]), rot([-30.0, 0, 0]), rot([0, 180.0, 0]), rot([20, -35, 50])):
        for derotate in (False, True):
            win = fovea_window(CAM, R, np.eye(3), (fw, fh), derotate)
            assert win.clamped
            c, s = abs(math.cos(win.angle_rad)), abs(math.sin(win.angle_rad))
            hx, hy = (c * fw + s * fh) / 2, (s * fw + c * fh) / 2
            assert -0.5 - 1e-9 <= win.centre[0] - hx and win.centre[0] + hx <= CAM.width - 0.5 + 1e-9
            assert -0.5 - 1e-9 <= win.centre[1] - hy and win.centre[1] + hy <= CAM.height - 0.5 + 1e-9
    # Derotating: the camera rolls by +6 degrees about its axis (x towards y), so the scene turns
    # by -6 degrees in the image, and the window turns with the scene.
    win = fovea_window(CAM, rot([0, 0, 6.0]), np.eye(3), (fw, fh), derotate=True)
    assert math.degrees(win.angle_rad) == pytest.approx(-6.0, abs=1e-3)


def test_sequence_fovea_cancels_the_motion_and_files_load(tmp_path):
    # Yaw and pitch wobble (no roll, which a sliding window cannot cancel).
    rng = np.random.default_rng(3)
    n = 12
    angles = np.cumsum(rng.normal(0, 1.2, (n, 2)), axis=0) * [1, 0.7]
    angles[0] = 0
    Rs = [rot([a[1], a[0], 0.0]) for a in angles]
    seq = write_sequence(tmp_path / "seq", Rs)
    stats = stabilise_sequence(seq, tmp_path / "out", fovea=(320, 240), progress=False)
    assert stats.frames == n and stats.flagged == 0 and stats.clamped == 0
    assert stats.rotation_rms_error_deg < 0.05
    # The fovea's background is (nearly) still: far less motion than the raw frames'.
    assert stats.raw_motion_px > 5.0
    assert stats.fovea_motion_px < stats.raw_motion_px / 5

    traj = read_trajectory(tmp_path / "out" / "rotations.tum")
    assert len(traj) == n and np.allclose(traj.p_world_cam, 0)
    for R_est, R in zip(traj.R_world_cam(), Rs):
        assert angle_deg(R_est, R) < 0.1
    assert len(list((tmp_path / "out" / "fovea").glob("*.png"))) == n
    first = cv2.imread(str(tmp_path / "out" / "fovea" / "000000.png"))
    assert first.shape == (240, 320, 3)
    rows = np.loadtxt(tmp_path / "out" / "fovea.csv", delimiter=",", skiprows=1)
    assert rows.shape == (n, 6)
    # fovea.csv's centres are where the first frame's centre ray is imaged, by the truth.
    for (t, x, y, clamped, flagged, inliers), R in zip(rows, Rs):
        ray = R.T @ [0, 0, 1.0]
        assert x == pytest.approx(CAM.cx + CAM.fx * ray[0] / ray[2], abs=0.5)
        assert y == pytest.approx(CAM.cy + CAM.fy * ray[1] / ray[2], abs=0.5)
    saved = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert saved["frames"] == n and "raw / fovea" in (tmp_path / "out" / "report.md").read_text()


def test_bad_frames_are_flagged_counted_and_recovered(tmp_path):
    Rs = random_path(9, 1.0, seed=5)
    images = [render(R) for R in Rs]
    black = np.zeros_like(images[0])
    saturated = np.full_like(images[0], 255)
    flat = np.full_like(images[0], 128)
    images[0] = black            # the very first frame: nothing to start from
    images[3] = saturated
    images[5] = flat
    images[6] = black            # two bad frames in a row
    seq = write_sequence(tmp_path / "seq", Rs, images)
    # One unreadable file as well (a truncated PNG).
    (tmp_path / "seq" / "rgb" / "0.266667.png").write_bytes(b"\x89PNG\r\n")
    stats = stabilise_sequence(seq, tmp_path / "out", progress=False)
    assert stats.skipped_unreadable == 1
    assert stats.frames == 8
    # Flagged: the bad frames, and frame 1 (its reference, frame 0, has nothing to track).
    assert stats.flagged == 5
    rows = np.loadtxt(tmp_path / "out" / "fovea.csv", delimiter=",", skiprows=1)
    assert rows[:, 4].tolist() == [1, 1, 0, 1, 0, 1, 1, 0]
    # Good frames after bad ones are measured against the last good one, so the orientations
    # relative to frame 1 (the first with texture) stay right. Rows are frames 0..7 (8 unreadable).
    R_est = read_trajectory(tmp_path / "out" / "rotations.tum").R_world_cam()
    for k in (2, 4, 7):
        assert angle_deg(R_est[1].T @ R_est[k], Rs[1].T @ Rs[k]) < 0.1, k


def test_stabiliser_flags_without_crashing():
    s = Stabiliser(CAM, (320, 240))
    img = render(np.eye(3))
    s.step(0.0, img)
    for t, bad in ((0.033, np.zeros((480, 640), np.uint8)), (0.066, np.full((480, 640, 3), 255, np.uint8))):
        r = s.step(t, bad)
        assert r.flagged and r.reason == FEW_TRACKS
        assert np.allclose(r.R_prev_cur, np.eye(3))
        assert r.fovea.shape[:2] == (240, 320)
    # A black reference frame advances the reference to the next frame.
    s2 = Stabiliser(CAM, (320, 240))
    s2.step(0.0, np.zeros((480, 640, 3), np.uint8))
    r = s2.step(0.033, img)
    assert r.flagged and r.reason == FEW_CORNERS_PREV
    r = s2.step(0.066, render(rot([0, 1.0, 0])))
    assert not r.flagged and angle_deg(r.R_prev_cur, rot([0, 1.0, 0])) < 0.05
    assert math.isnan(residual_motion(np.zeros((480, 640), np.uint8), np.zeros((480, 640), np.uint8),
                                      StabiliseSettings()))


def test_imu_sequence_tracks_fast_rotation(tmp_path):
    # 12 degrees per frame about y and x: only tracked with the gyro's pre-warp.
    Rs = [np.eye(3), rot([4, 12, 0]), rot([0, 0, 0]), rot([-6, -10, 2])]
    seq = write_sequence(tmp_path / "seq", Rs, gyro=True)
    with_imu = stabilise_sequence(seq, tmp_path / "imu", use_imu=True, progress=False)
    assert with_imu.flagged == 0 and with_imu.rotation_rms_error_deg < 0.05
    blind = stabilise_sequence(seq, tmp_path / "blind", use_imu=False, progress=False)
    assert blind.flagged > 0 or blind.rotation_rms_error_deg > 1.0


def test_bad_input_raises_value_errors(tmp_path):
    Rs = [np.eye(3), rot([0, 1, 0])]
    seq = write_sequence(tmp_path / "seq", Rs)
    with pytest.raises(ValueError, match="imu.txt"):
        stabilise_sequence(seq, tmp_path / "o", use_imu=True, progress=False)
    with pytest.raises(ValueError, match="does not fit"):
        stabilise_sequence(seq, tmp_path / "o", fovea=(640, 240), progress=False)
    with pytest.raises(ValueError, match="width, height"):
        stabilise_sequence(seq, tmp_path / "o", fovea="320x240", progress=False)
    (seq / "rgb.txt").write_text("# timestamp filename\n")
    with pytest.raises(ValueError, match=r"rgb.txt: lists no frames; give a sequence with images"):
        stabilise_sequence(seq, tmp_path / "empty", progress=False)
    assert not (tmp_path / "empty").exists()
    with pytest.raises(ValueError, match="ransac_threshold_rad"):
        StabiliseSettings(ransac_threshold_rad=2.0)
    with pytest.raises(ValueError, match="lk_window_px"):
        StabiliseSettings(lk_window_px=20)
    with pytest.raises(ValueError, match="leak_per_s"):
        StabiliseSettings(leak_per_s=-1.0)


def test_leaky_reference_follows_a_steady_pan():
    # Panning steadily: held still, the fovea runs to the edge; with a leak it settles at a lag.
    n, step = 60, 0.6
    Rs = [rot([0, step * k, 0]) for k in range(n)]
    imgs = [render(R) for R in Rs]
    held = Stabiliser(CAM, (320, 240))
    leaky = Stabiliser(CAM, (320, 240), StabiliseSettings(leak_per_s=3.0))
    for k, img in enumerate(imgs):
        rh = held.step(k / 30, img)
        rl = leaky.step(k / 30, img)
    assert rh.window.clamped
    assert not rl.window.clamped
    # First-order lag: the reference trails the camera by rate / leak = 18 deg/s / 3/s = 6 deg.
    lag = math.degrees(math.atan((CAM.cx - rl.window.centre[0]) / CAM.fx))
    assert lag == pytest.approx(step * 30 / 3.0, rel=0.15)


def test_rotation_errors_against_ground_truth():
    from runtime.sequence import Trajectory
    Rs = random_path(5, 2.0, seed=9)
    t = np.arange(5) / 30
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, :3, :3] = Rs
    gt = Trajectory.from_T_world_cam(t, T)
    R_pc = np.array([np.eye(3)] + [Rs[k - 1].T @ Rs[k] for k in range(1, 5)])
    assert np.allclose(rotation_errors_deg(t, R_pc, gt), 0, atol=1e-6)
    R_pc[2] = R_pc[2] @ rot([0, 0, 0.5])
    err = rotation_errors_deg(t, R_pc, gt)
    assert err[1] == pytest.approx(0.5, abs=1e-6) and np.allclose(err[[0, 2, 3]], 0, atol=1e-6)


@pytest.mark.slow
def test_twin_sit_down_against_ground_truth(tmp_path):
    os.environ.setdefault("MUJOCO_GL", "egl")
    from runtime.twin.recorder import record
    from wvr.cli import make_twin

    seq = record(make_twin(), "sit-down", tmp_path / "seq", seconds=2, seed=0, progress=False)
    stats = stabilise_sequence(seq, tmp_path / "out", use_imu=True, progress=False)
    assert stats.flagged == 0 and stats.skipped_unreadable == 0
    # Measured 0.66 deg RMS (max 1.11) on these 2 s, with or without the IMU: the 2 s sit-down is
    # fast (0.78 deg and 10.6 mm per frame) and the rotation-only model reads the translation's
    # parallax on the near workbench as rotation (bench_stabilise.py splits the error; on 6 s it
    # is 0.19 deg). The bound leaves a third for renderer differences.
    assert stats.rotation_rms_error_deg < 0.9
    assert stats.mean_inliers > 60
    # The fovea cancels most of the image motion while it is not held at the image's edge
    # (measured 5.6 times less motion than the raw frames).
    assert stats.motion_ratio_unclamped > 3.0
