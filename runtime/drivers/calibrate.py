"""Calibration for the rig: the camera's intrinsics from chessboard images (OpenCV), and the IMU's
still biases (written into rig.toml)."""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import tomli_w

from kinematics.camera import CameraIntrinsics, project

from . import DriverError

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


@dataclass(frozen=True)
class CameraCalibration:
    camera: CameraIntrinsics
    rms_px: float
    images_used: int
    images_total: int
    path: Path | None


def parse_board(spec: str) -> tuple[int, int, float]:
    """``chessboard:COLSxROWS:SQUARE_M`` (inner corners, square side in metres)."""
    m = re.fullmatch(r"chessboard:(\d+)x(\d+):([0-9.eE+-]+)", spec.strip())
    if not m:
        raise ValueError(f"--board {spec!r}: write chessboard:COLSxROWS:SQUARE_M, the inner corners and the square's "
                         f"side in metres, e.g. chessboard:9x6:0.025")
    cols, rows, sq = int(m.group(1)), int(m.group(2)), float(m.group(3))
    if cols < 3 or rows < 3 or not (math.isfinite(sq) and sq > 0):
        raise ValueError(f"--board {spec!r}: at least 3x3 inner corners and a positive square size")
    return cols, rows, sq


def find_corners(images_dir: str | Path, cols: int, rows: int) -> tuple[list[np.ndarray], tuple[int, int], int]:
    paths = sorted(p for p in Path(images_dir).iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES) \
        if Path(images_dir).is_dir() else []
    if not paths:
        raise ValueError(f"--images {images_dir}: no images (png, jpg, bmp, tif) in that folder")
    found, size = [], None
    for p in paths:
        grey = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            continue
        if size is None:
            size = grey.shape[::-1]
        elif grey.shape[::-1] != size:
            raise ValueError(f"{p}: {grey.shape[1]}x{grey.shape[0]} differs from the first image's {size[0]}x{size[1]}; "
                             f"use images from one camera at one resolution")
        ok, c = cv2.findChessboardCorners(grey, (cols, rows), cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if ok:
            c = cv2.cornerSubPix(grey, c, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
            found.append(c.reshape(-1, 2))
    return found, size, len(paths)


def calibrate_camera(images_dir, board: str, model: str = "brown", out: str | Path | None = None) -> CameraCalibration:
    """Intrinsics from chessboard images: OpenCV's calibrateCamera (brown: k1 k2 p1 p2 k3),
    cv2.fisheye.calibrate (fisheye: k1..k4), or MonoSLAM's one-parameter radial-sqrt model fitted
    by least squares from the brown solution. Writes camera.toml with the RMS reprojection error
    in its header comment."""
    cols, rows, sq = parse_board(board)
    corners, size, total = find_corners(images_dir, cols, rows)
    if len(corners) < 3:
        raise ValueError(f"--images {images_dir}: the {cols}x{rows} board was found in {len(corners)} of {total} images; "
                         f"at least 3 are needed (check --board's inner-corner count, lighting, focus)")
    obj = np.zeros((rows * cols, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * sq
    w, h = size
    objs = [obj.copy() for _ in corners]
    imgs = [c.astype(np.float32) for c in corners]
    if model == "fisheye":
        K = np.eye(3)
        D = np.zeros((4, 1))
        flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
        rms, K, D, _, _ = cv2.fisheye.calibrate([o.reshape(1, -1, 3).astype(np.float64) for o in objs],
                                                [i.reshape(1, -1, 2).astype(np.float64) for i in imgs], size, K, D,
                                                flags=flags, criteria=(cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-9))
        cam = CameraIntrinsics(width=w, height=h, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                               model="fisheye", k1=float(D[0, 0]), k2=float(D[1, 0]), k3=float(D[2, 0]), k4=float(D[3, 0]))
    else:
        rms, K, D, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, size, None, None)
        D = D.ravel()
        cam = CameraIntrinsics(width=w, height=h, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                               k1=float(D[0]), k2=float(D[1]), p1=float(D[2]), p2=float(D[3]), k3=float(D[4]))
        if model == "radial-sqrt":
            cam, rms = _fit_radial_sqrt(cam, objs, imgs, rvecs, tvecs)
    cam.validate("the calibration")
    path = None
    if out is not None:
        path = Path(out)
        header = (f"# wvr calibrate camera: {len(corners)} of {total} images of a {cols}x{rows} chessboard "
                  f"({sq} m squares), model {model}\n# RMS reprojection error {rms:.4f} px\n")
        path.write_text(header + tomli_w.dumps(cam.to_dict()))
    return CameraCalibration(cam, float(rms), len(corners), total, path)


def _fit_radial_sqrt(init: CameraIntrinsics, objs, imgs, rvecs, tvecs):
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    n = len(objs)
    x0 = np.r_[init.fx, init.fy, init.cx, init.cy, 0.0, np.concatenate([np.r_[r.ravel(), t.ravel()] for r, t in zip(rvecs, tvecs)])]

    def cam_of(x):
        return CameraIntrinsics(width=init.width, height=init.height, fx=x[0], fy=x[1], cx=x[2], cy=x[3],
                                model="radial-sqrt", kd1=x[4] * 1e-6)

    def residuals(x):
        cam = cam_of(x)
        res = []
        for k in range(n):
            p = x[5 + 6 * k:11 + 6 * k]
            P = objs[k] @ Rotation.from_rotvec(p[:3]).as_matrix().T + p[3:]
            uv = project(cam, P)
            res.append(np.nan_to_num(uv - imgs[k], nan=1e3).ravel())
        return np.concatenate(res)

    sol = least_squares(residuals, x0, x_scale="jac", max_nfev=200)
    r = residuals(sol.x).reshape(-1, 2)
    return cam_of(sol.x), float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))


@dataclass(frozen=True)
class ImuCalibration:
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    samples: int
    seconds: float


def still_biases(gyro: np.ndarray, accel: np.ndarray, g: float = 9.81) -> tuple[np.ndarray, np.ndarray]:
    """Biases from a still period: the gyro's mean, and the accelerometer's mean less gravity
    along the measured direction (only the error along gravity is observable without turning)."""
    if len(gyro) < 10:
        raise ValueError(f"{len(gyro)} IMU samples are too few to estimate biases; hold still longer")
    f = accel.mean(axis=0)
    return gyro.mean(axis=0), f - g * f / np.linalg.norm(f)


def calibrate_imu(rig_path, seconds: float = 10.0) -> ImuCalibration:
    """Read the rig's IMU for ``seconds`` while the head is still, and write the biases into
    rig.toml's [imu] (gyro_bias, accel_bias, camera frame; the old values are replaced and the
    rest of the file kept as it is)."""
    from .imu import ImuReader
    from .rig import load_rig

    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"--seconds {seconds}: give a positive duration")
    cfg = load_rig(rig_path)
    if cfg.imu_driver == "none":
        raise ValueError(f"{rig_path}: [imu] driver is \"none\"; there is no IMU to calibrate")
    imu = ImuReader.open(cfg.imu_port, cfg.imu_driver, cfg.imu_baud, R_cam_imu=cfg.R_cam_imu,
                         anchor="arrival" if cfg.imu_anchor == "camera" else cfg.imu_anchor, period_s=1.0 / cfg.imu_rate_hz)
    try:
        t_end = time.monotonic() + seconds
        parts = []
        while time.monotonic() < t_end:
            time.sleep(0.05)
            parts.append(imu.take_until(math.inf))
    finally:
        imu.close()
    from ..robot import ImuSamples

    s = ImuSamples.concat(parts)
    if len(s) == 0:
        raise DriverError(f"IMU on {cfg.imu_port}: no samples in {seconds:g} s; check the cable and the baud rate")
    gb, ab = still_biases(s.gyro, s.accel)
    write_imu_biases(Path(rig_path), gb, ab)
    return ImuCalibration(gb, ab, len(s), float(s.t[-1] - s.t[0]) if len(s) > 1 else 0.0)


def write_imu_biases(path: Path, gyro_bias, accel_bias) -> None:
    """Set [imu] gyro_bias and accel_bias in rig.toml, keeping every other line."""
    lines = path.read_text().splitlines()
    out, in_imu, done = [], False, False
    new = [f"gyro_bias = [{', '.join(f'{v:.6g}' for v in gyro_bias)}]",
           f"accel_bias = [{', '.join(f'{v:.6g}' for v in accel_bias)}]"]
    for line in lines:
        s = line.strip()
        if s.startswith("["):
            if in_imu and not done:
                out += new
                done = True
            in_imu = s == "[imu]"
        if in_imu and re.match(r"(gyro_bias|accel_bias)\s*=", s):
            continue
        out.append(line)
    if in_imu and not done:
        out += new
        done = True
    if not done:
        raise ValueError(f"{path}: no [imu] table to write the biases into")
    tmp = path.with_name(path.name + ".part")
    tmp.write_text("\n".join(out) + "\n")
    tmp.replace(path)
