"""A depth image for a EuRoC sequence, from its two cameras: the depth start on real footage.

TUM RGB-D sequences start metric from their first depth image (``wvr slam``'s depth start), and
none is reachable from this machine. EuRoC's cam0 and cam1 are a calibrated stereo pair, so the
first frames' depth can be measured from them: both images are rectified (OpenCV's
``stereoRectify`` on the sensor.yaml calibration), matched by semi-global block matching,
left-right checked, and each depth read back at cam0's own (distorted) pixels, as a Kinect's depth
is registered to its colour image. The result is a TUM-RGB-D-shaped folder: the converted
sequence's frames, ground truth and camera.toml, plus ``depth.txt`` and 16-bit PNGs at 5000 per
metre for its first frames (the start uses the first)::

    python benchmarks/euroc_stereo_depth.py SEQ MAV0 OUT [--frames 3]

SEQ is the sequence in our layout (``wvr convert euroc``, possibly cropped to 640x480: the crop is
read from camera.toml's cx), MAV0 the EuRoC folder holding cam0 and cam1 (both at the same
stamps). The stereo baseline is 11 cm, so the depth's error grows from about 1% at 1 m to about
5% at 8 m (a quarter-pixel disparity error), much as a Kinect's does.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

#: SGBM's disparity range, px: at the 11 cm baseline and f 436 px, depths from 0.75 m.
DISPARITIES = 64
BLOCK = 7


def _sensor(mav0: Path, cam: str):
    """K (3, 3), OpenCV distortion (5,), T_body_cam (4, 4), (width, height) of mav0/cam/sensor.yaml."""
    from runtime.datasets.euroc import read_camera_yaml

    c, T_body_cam = read_camera_yaml(mav0 / cam / "sensor.yaml")
    if c.model != "brown":
        raise SystemExit(f"{mav0 / cam / 'sensor.yaml'}: a {c.model} lens; this builder reads radial-tangential only")
    D = np.array([c.distortion.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
    return c.K, D, T_body_cam, (c.width, c.height)


class StereoDepth:
    """Depth along cam0's optic axis (H, W) m at cam0's distorted pixels, 0 where unmatched."""

    def __init__(self, mav0: Path):
        K0, D0, T_b_c0, size = _sensor(mav0, "cam0")
        K1, D1, T_b_c1, _ = _sensor(mav0, "cam1")
        T_c1_c0 = np.linalg.inv(T_b_c1) @ T_b_c0
        R1, R2, P1, P2, *_ = cv2.stereoRectify(K0, D0, K1, D1, size, T_c1_c0[:3, :3].copy(),
                                               T_c1_c0[:3, 3].reshape(3, 1).copy(), flags=cv2.CALIB_ZERO_DISPARITY,
                                               alpha=0)
        self.mav0, self.size, self.R_rect_cam0, self.K0 = mav0, size, R1, K0
        self.maps = (cv2.initUndistortRectifyMap(K0, D0, R1, P1, size, cv2.CV_32FC1),
                     cv2.initUndistortRectifyMap(K1, D1, R2, P2, size, cv2.CV_32FC1))
        self.f, self.cx, self.cy = P1[0, 0], P1[0, 2], P1[1, 2]
        self.baseline_m = -P2[0, 3] / P2[0, 0]
        W, H = size
        uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        pts = np.stack([uu.ravel(), vv.ravel()], 1).reshape(-1, 1, 2)
        # Where each of cam0's own pixels lies in the rectified image.
        self.rect = cv2.undistortPoints(pts, K0, D0, R=R1, P=P1).reshape(H, W, 2).astype(np.float32)
        common = dict(numDisparities=DISPARITIES, blockSize=BLOCK, P1=8 * BLOCK**2, P2=32 * BLOCK**2, disp12MaxDiff=1,
                      uniquenessRatio=15, speckleWindowSize=100, speckleRange=1, mode=cv2.STEREO_SGBM_MODE_HH)
        self.left = cv2.StereoSGBM_create(minDisparity=0, **common)
        self.right = cv2.StereoSGBM_create(minDisparity=-DISPARITIES, **common)

    def __call__(self, stamp_ns: str) -> np.ndarray:
        a = cv2.imread(str(self.mav0 / "cam0" / "data" / f"{stamp_ns}.png"), cv2.IMREAD_GRAYSCALE)
        b = cv2.imread(str(self.mav0 / "cam1" / "data" / f"{stamp_ns}.png"), cv2.IMREAD_GRAYSCALE)
        if a is None or b is None:
            raise SystemExit(f"{self.mav0}: cam0 and cam1 have no pair of images at {stamp_ns}: give the EuRoC folder "
                             "the sequence was converted from")
        ra, rb = (cv2.remap(img, *m, cv2.INTER_LINEAR) for img, m in zip((a, b), self.maps))
        d = self.left.compute(ra, rb).astype(np.float32) / 16.0
        d_right = -self.right.compute(rb, ra).astype(np.float32) / 16.0
        W, H = self.size
        x_right = np.arange(W)[None, :] - np.rint(d).astype(int)
        back = d_right[np.arange(H)[:, None], np.clip(x_right, 0, W - 1)]
        ok = (d > 0.5) & (x_right >= 0) & (np.abs(back - d) <= 1.0)
        Z = np.where(ok, self.f * self.baseline_m / np.maximum(d, 1e-6), 0.0).astype(np.float32)
        u, v = self.rect[..., 0], self.rect[..., 1]
        Zs = cv2.remap(Z, u, v, cv2.INTER_NEAREST, borderValue=0)
        X_rect = np.stack([(u - self.cx) / self.f * Zs, (v - self.cy) / self.f * Zs, Zs], -1)
        z_cam0 = X_rect @ self.R_rect_cam0[:, 2]     # (R_rect_cam0^T X_rect)_z
        return np.where(Zs > 0, z_cam0, 0.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", type=Path, help="the converted sequence (rgb.txt, camera.toml, groundtruth.txt)")
    ap.add_argument("mav0", type=Path, help="the EuRoC folder with cam0 and cam1")
    ap.add_argument("out", type=Path, help="the new folder (must not exist)")
    ap.add_argument("--frames", type=int, default=3, help="depth images for this many first frames")
    a = ap.parse_args(argv)
    from runtime.sequence import open_sequence

    if a.out.exists():
        print(f"{a.out} exists: give a new folder", file=sys.stderr)
        return 2
    seq = open_sequence(a.seq)
    stereo = StereoDepth(a.mav0)
    x0 = int(round(stereo.K0[0, 2] - seq.camera.cx))   # the crop's left column (0: uncropped)
    a.out.mkdir(parents=True)
    (a.out / "depth").mkdir()
    for name in ("camera.toml", "groundtruth.txt"):
        shutil.copy(a.seq / name, a.out / name)
    (a.out / "rgb").symlink_to((a.seq / "rgb").resolve())
    shutil.copy(a.seq / "rgb.txt", a.out / "rgb.txt")
    lines = ["# depth from cam0/cam1 stereo (benchmarks/euroc_stereo_depth.py), registered to cam0",
             "# timestamp filename"]
    rows = [r.split() for r in (a.seq / "rgb.txt").read_text().splitlines() if r.strip() and not r.startswith("#")]
    for t, image in rows[:a.frames]:
        stamp = Path(image).stem                    # EuRoC's files are named by their nanosecond stamps
        z = stereo(stamp)[:, x0:x0 + seq.camera.width]
        cv2.imwrite(str(a.out / "depth" / f"{stamp}.png"), np.clip(np.rint(z * 5000), 0, 65535).astype(np.uint16))
        lines.append(f"{t} depth/{stamp}.png")
        print(f"{stamp}: depth at {100 * (z > 0).mean():.0f}% of pixels, median {np.median(z[z > 0]):.2f} m")
    (a.out / "depth.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
