"""Head tracking benchmark (paper section 3 item 2, Fig. 5). Figures:

* a 200-frame render (640x480, default_camera(), head centre 1 m away) of the textured head
  turning smoothly within +-60 deg yaw and +-30 deg pitch with +-10 deg roll
  (``headscene.smooth_head_motion``), started at the known frontal pose: RMS error of yaw, pitch,
  roll and the geodesic rotation error, their peaks, translation RMS, lost frames (target: <= 5 deg
  RMS per angle and geodesic, no lost frames);
* the same motion at 0.7 m (a larger head in the image) and at 320x240 / 0.6 m (the tests' size);
* frames per second of the tracker alone (rendering excluded).

Run: ``MUJOCO_GL=egl python benchmarks/bench_headtrack.py``.
"""

import math
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from kinematics.camera import CameraIntrinsics, default_camera  # noqa: E402
from runtime.vision2d.headscene import render_head_sequence, smooth_head_motion  # noqa: E402
from kinematics.transforms import rotation_angle  # noqa: E402
from runtime.vision2d.headtrack import HeadTracker  # noqa: E402


def bench_sequence(label, camera, distance_m, n=200, seed=0):
    ypr = smooth_head_motion(n, math.radians(60), math.radians(30), math.radians(10))
    t0 = time.perf_counter()
    images, T_true, cam = render_head_sequence(ypr, distance_m, seed=seed, camera=camera)
    t_render = time.perf_counter() - t0
    tracker = HeadTracker(cam)
    t0 = time.perf_counter()
    results = tracker.track(images, T_true[0])
    t_track = time.perf_counter() - t0
    ok = np.array([not r.lost for r in results])
    est = np.array([r.ypr for r in results])
    err = np.degrees(est - ypr)[ok]
    geo = np.degrees(rotation_angle(np.stack([r.T_cam_head[:3, :3] for r in results])[ok], T_true[ok, :3, :3]))
    t_err = np.linalg.norm(np.stack([r.translation_m for r in results])[ok] - T_true[ok, :3, 3], axis=1)
    rms = np.sqrt(np.mean(err ** 2, axis=0))
    print(f"{label}: {n} frames {cam.width}x{cam.height} at {distance_m:g} m "
          f"(yaw {np.degrees(ypr[:, 0]).min():+.0f}..{np.degrees(ypr[:, 0]).max():+.0f}, "
          f"pitch {np.degrees(ypr[:, 1]).min():+.0f}..{np.degrees(ypr[:, 1]).max():+.0f}, "
          f"roll {np.degrees(ypr[:, 2]).min():+.0f}..{np.degrees(ypr[:, 2]).max():+.0f} deg)")
    print(f"  RMS error yaw {rms[0]:.2f}  pitch {rms[1]:.2f}  roll {rms[2]:.2f}  geodesic "
          f"{np.sqrt(np.mean(geo ** 2)):.2f} deg (target <= 5); peaks {np.abs(err).max(axis=0).round(2)} "
          f"geodesic {geo.max():.2f} deg")
    print(f"  translation RMS {1000 * np.sqrt(np.mean(t_err ** 2)):.1f} mm; lost frames {int((~ok).sum())}; "
          f"keyframes {len(tracker.keyframes)}; inliers median {int(np.median([r.inliers for r in results]))}; "
          f"counts {tracker.counts}")
    print(f"  tracker {n / t_track:.1f} frames/s (rendering excluded; rendering {n / t_render:.1f} frames/s)")
    return rms, geo


if __name__ == "__main__":
    bench_sequence("640x480, 1 m", default_camera(), 1.0)
    bench_sequence("640x480, 0.7 m", default_camera(), 0.7)
    small = CameraIntrinsics(width=320, height=240, fx=257.35, fy=257.35, cx=159.5, cy=119.5)
    bench_sequence("320x240, 0.6 m", small, 0.6)
