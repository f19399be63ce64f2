"""Calibration: intrinsics recovered from chessboard images rendered through a known camera,
and the IMU's still biases from a simulated IMU, written into rig.toml."""

import threading
import time

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, load_camera, unproject
from runtime.drivers.calibrate import calibrate_camera, calibrate_imu, parse_board
from runtime.drivers.rig import load_rig
from runtime.twin.hil import PtyDevice

COLS, ROWS, SQ = 9, 6, 0.025


def render_board(cam: CameraIntrinsics, R_cam_board, t_cam_board) -> np.ndarray:
    """The chessboard (inner corners COLS x ROWS, a square of margin) as ``cam`` sees it: each
    pixel's ray met with the board's plane, coloured by the square it falls in."""
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    rays = unproject(cam, np.column_stack([u.ravel(), v.ravel()]).astype(float))
    d = rays @ R_cam_board                                  # ray directions in the board frame
    o = -R_cam_board.T @ t_cam_board                        # the camera centre in the board frame
    s = -o[2] / d[:, 2]
    p = o + s[:, None] * d
    i, j = np.floor(p[:, 0] / SQ) + 1, np.floor(p[:, 1] / SQ) + 1
    inside = (s > 0) & (i >= 0) & (i <= COLS) & (j >= 0) & (j <= ROWS)
    img = np.full(len(s), 255, np.uint8)
    img[inside & ((i + j) % 2 == 0)] = 0
    return cv2.GaussianBlur(img.reshape(cam.height, cam.width), (3, 3), 0.7)


def render_set(tmp_path, true, n=10, seed=3):
    rng = np.random.default_rng(seed)
    centre = np.array([(COLS - 1) * SQ / 2, (ROWS - 1) * SQ / 2, 0.0])
    for k in range(n):
        R = Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, 3)).as_matrix()
        t = np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), rng.uniform(0.3, 0.45)]) - R @ centre
        cv2.imwrite(str(tmp_path / f"b{k:02d}.png"), render_board(true, R, t))


@pytest.mark.parametrize("model, true", [
    ("fisheye", CameraIntrinsics(width=640, height=480, fx=300.0, fy=300.0, cx=318.0, cy=242.0, model="fisheye",
                                 k1=0.05, k2=-0.01)),
    ("radial-sqrt", CameraIntrinsics(width=640, height=480, fx=400.0, fy=400.0, cx=321.0, cy=238.0, model="radial-sqrt",
                                     kd1=2e-7)),
])
def test_wide_angle_models_are_recovered(tmp_path, model, true):
    render_set(tmp_path, true)
    res = calibrate_camera(tmp_path, f"chessboard:{COLS}x{ROWS}:{SQ}", model, tmp_path / "camera.toml")
    cam = load_camera(tmp_path / "camera.toml")
    assert cam.model == model and res.rms_px < 0.5
    assert abs(cam.fx - true.fx) / true.fx < 0.02 and abs(cam.cx - true.cx) < 4
    if model == "radial-sqrt":
        assert abs(cam.kd1 - true.kd1) < 0.3 * true.kd1


def test_camera_intrinsics_recovered_from_rendered_boards(tmp_path):
    true = CameraIntrinsics(width=640, height=480, fx=520.0, fy=518.0, cx=322.0, cy=236.0, k1=-0.12, k2=0.05)
    rng = np.random.default_rng(3)
    centre = np.array([(COLS - 1) * SQ / 2, (ROWS - 1) * SQ / 2, 0.0])
    for k in range(10):
        R = Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, 3)).as_matrix()
        t = np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), rng.uniform(0.3, 0.45)]) - R @ centre
        cv2.imwrite(str(tmp_path / f"b{k:02d}.png"), render_board(true, R, t))
    res = calibrate_camera(tmp_path, f"chessboard:{COLS}x{ROWS}:{SQ}", "brown", tmp_path / "camera.toml")
    cam = load_camera(tmp_path / "camera.toml")
    assert res.images_used >= 8 and res.rms_px < 0.5
    assert abs(cam.fx - true.fx) / true.fx < 0.01 and abs(cam.fy - true.fy) / true.fy < 0.01
    assert abs(cam.cx - true.cx) < 3 and abs(cam.cy - true.cy) < 3 and abs(cam.k1 - true.k1) < 0.03
    assert "RMS reprojection error" in (tmp_path / "camera.toml").read_text()


def test_bad_board_spec_and_no_images_are_one_line(tmp_path):
    with pytest.raises(ValueError, match="chessboard:COLSxROWS"):
        parse_board("checker:9x6")
    with pytest.raises(ValueError, match="no images"):
        calibrate_camera(tmp_path, "chessboard:9x6:0.025")


def test_imu_still_biases_are_written_into_rig_toml(tmp_path):
    from test_drivers import RIG, write_rig

    dev = PtyDevice(None, "imu")
    rig = write_rig(tmp_path, RIG.format(port="/dev/ttyACM0").replace('driver = "bno085-rvc"', 'driver = "text"')
                    .replace('port = "/dev/ttyUSB0"', f'port = "{dev.path}"\n# keep this comment'))
    bias_w, bias_a = np.array([0.003, -0.002, 0.001]), np.array([0.0, 0.0, 0.12])
    stop = threading.Event()
    rng = np.random.default_rng(0)

    def stream():
        t = 0.0
        while not stop.is_set():
            lines = []
            for _ in range(10):
                t += 0.005
                w = bias_w + rng.normal(0, 0.001, 3)
                a = np.array([0.0, 0.0, 9.81]) + bias_a + rng.normal(0, 0.01, 3)
                lines.append(f"{t:.3f} " + " ".join(f"{x:.6f}" for x in (*w, *a)))
            dev.write(("\n".join(lines) + "\n").encode())
            time.sleep(0.05)
    th = threading.Thread(target=stream)
    th.start()
    try:
        res = calibrate_imu(rig, seconds=1.0)
    finally:
        stop.set()
        th.join()
        dev.close()
    np.testing.assert_allclose(res.gyro_bias, bias_w, atol=3e-4)
    np.testing.assert_allclose(res.accel_bias, bias_a, atol=3e-3)
    cfg = load_rig(rig)
    np.testing.assert_allclose(cfg.gyro_bias, res.gyro_bias, atol=1e-6)
    assert "# keep this comment" in rig.read_text()
