"""Stabilisation benchmark (paper section 3 item 1): records the twin's sit-down and
workbench-static scenarios (6 s, seed 0), stabilises them with and without the IMU and prints
the inter-frame rotation error against ground truth (degrees RMS), the residual background motion
of the raw frames and of the fovea and their ratio, and frames per second (processing only).

It also splits the error: the rotation a rotation-only fit gets from perfect matches (true depth
and true poses: no tracking error, only the parallax of the camera's translation), and the
gyro's own integration error."""

import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from runtime.sequence import open_sequence  # noqa: E402
from runtime.twin.recorder import record  # noqa: E402
from runtime.eval import rotation_errors_deg
from runtime.vision2d.stabilise import (StabiliseSettings, bearings, detect_corners, fit_rotation,  # noqa: E402
                                        gyro_rotation, stabilise_sequence, to_grey)
from wvr.cli import make_twin  # noqa: E402

SECONDS = 6.0
SCENARIOS = ("sit-down", "workbench-static", "sit-down-head-still")


def rms(a):
    a = np.asarray(a, float)
    return float(np.sqrt(np.nanmean(a ** 2)))


def parallax_only_error(seq, settings: StabiliseSettings) -> tuple[float, float]:
    """RMS error (deg) of the rotation-only fit on perfect matches, and the RMS (deg) of the
    translation's parallax: the angle between each corner's true current bearing and where the
    true rotation alone would put it (median per frame)."""
    R_w = seq.groundtruth.interpolate(seq.timestamps).R_world_cam()
    T = seq.groundtruth.interpolate(seq.timestamps).T_world_cam()
    errs, par = [], []
    rng = np.random.default_rng(0)
    for k in range(1, len(seq)):
        img, depth = seq.frame(k - 1).image, seq.depth(k - 1)
        if img is None or depth is None:
            continue
        uv = detect_corners(to_grey(img), settings).astype(float)
        z = depth[np.clip(np.round(uv[:, 1]).astype(int), 0, depth.shape[0] - 1),
                  np.clip(np.round(uv[:, 0]).astype(int), 0, depth.shape[1] - 1)]
        ok = np.isfinite(z) & (z > 0)
        f_prev = bearings(seq.camera, uv[ok])
        P_prev = f_prev / f_prev[:, 2:3] * z[ok, None]            # points in the previous camera frame
        T_cur_prev = np.linalg.inv(T[k]) @ T[k - 1]
        P_cur = P_prev @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3]
        f_cur = P_cur / np.linalg.norm(P_cur, axis=1, keepdims=True)
        R_gt = R_w[k - 1].T @ R_w[k]
        R_fit, _ = fit_rotation(f_prev, f_cur, settings, rng)
        errs.append(np.degrees(Rotation.from_matrix(R_fit.T @ R_gt).magnitude()))
        pred = f_prev @ R_gt                                      # true rotation only
        par.append(np.degrees(np.median(np.arccos(np.clip(np.sum(pred * f_cur, axis=1), -1, 1)))))
    return rms(errs), rms(par)


def gyro_only_error(seq) -> float:
    """RMS (deg) of the integrated gyro's inter-frame rotation against ground truth."""
    t = seq.timestamps
    R = np.array([np.eye(3)] + [gyro_rotation(seq.imu.t, seq.imu.gyro, t[k - 1], t[k]) for k in range(1, len(t))])
    return rms(rotation_errors_deg(t, R, seq.groundtruth))


def main():
    settings = StabiliseSettings()
    with tempfile.TemporaryDirectory(prefix="bench_stabilise_") as tmp:
        tmp = Path(tmp)
        for name in SCENARIOS:
            seq_dir = tmp / name
            t0 = time.perf_counter()
            record(make_twin(), name, seq_dir, seconds=SECONDS, seed=0, progress=False, depth=True)
            print(f"{name}: recorded {SECONDS:g} s in {time.perf_counter() - t0:.0f} s", flush=True)
            print(f"  {'mode':<22} {'rot RMS deg':>11} {'max deg':>8} {'raw px':>7} {'fovea px':>8} "
                  f"{'ratio':>6} {'ratio*':>6} {'clamped':>7} {'flagged':>7} {'fps':>6}")
            for label, use_imu, s, fovea in (("vision", False, settings, (320, 240)),
                                             ("vision + IMU", True, settings, (320, 240)),
                                             ("vision, derotating", False, StabiliseSettings(derotate=True), (320, 240)),
                                             ("vision + IMU, 160x120", True, settings, (160, 120))):
                st = stabilise_sequence(seq_dir, tmp / f"{name}-{label}", fovea=fovea, use_imu=use_imu,
                                        progress=False, settings=s)
                print(f"  {label:<22} {st.rotation_rms_error_deg:>11.4f} {st.rotation_max_error_deg:>8.4f} "
                      f"{st.raw_motion_px:>7.3f} {st.fovea_motion_px:>8.3f} {st.motion_ratio:>6.2f} "
                      f"{st.motion_ratio_unclamped:>6.2f} {st.clamped:>7d} {st.flagged:>7d} "
                      f"{st.processing_fps:>6.1f}", flush=True)
            seq = open_sequence(seq_dir)
            e_par, par = parallax_only_error(seq, settings)
            print("  (ratio* = over frame pairs where the fovea was not clamped)")
            print(f"  parallax of the translation: {par:.4f} deg RMS per frame (median corner); rotation-only fit "
                  f"on perfect matches: {e_par:.4f} deg RMS; gyro alone: {gyro_only_error(seq):.4f} deg RMS",
                  flush=True)


if __name__ == "__main__":
    main()
