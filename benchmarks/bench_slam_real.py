"""SLAM on real public footage, started anywhere (issue 50's table).

For each sequence folder given (our TUM layout, a TUM RGB-D folder, a EuRoC ``mav0`` folder or
its parent, a KITTI odometry sequence), ``wvr slam``'s engine runs camera only from whatever the
sequence has (no target: a natural start) and every frame's pose is scored against the ground
truth after a Sim(3) alignment (evo's Umeyama). Reported per sequence: the ATE RMSE (and without
alignment where the scale is metric), frames lost, frames before the start, the scale source and
the factor Sim(3) finds (1 for an exact metric scale), ms per frame (median, p99, max; one core,
decoding excluded; wall clock, and the tracking thread's CPU time, which a loaded machine inflates
less), beside the published figures of ORB-SLAM, PTAM and LSD-SLAM where they exist
(keyframe trajectories, from Mur-Artal et al., ORB-SLAM, T-RO 2015, table III; their "X": lost).

The data stay outside the repository (benchmarks/datasets.md says how to fetch them):

    python benchmarks/bench_slam_real.py [FOLDER ...]

with no folder, the environment's ``WVR_EUROC_MH01``, ``WVR_KITTI07`` and ``WVR_TUM`` (one or
more TUM RGB-D folders separated by ``:``) are used, and ``WVR_EUROC_MH01_IMU`` with its IMU.
``--imu`` runs the given folders with their IMU: the scale is then the IMU's (metric), and the
metric ATE column is after an SE(3) alignment (the world is the first camera's frame).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

#: Published keyframe ATE RMSE, cm (ORB-SLAM T-RO 2015, table III; None: lost or not reported).
PUBLISHED_CM = {
    "rgbd_dataset_freiburg1_xyz": {"ORB-SLAM": 0.90, "PTAM": 1.15, "LSD-SLAM": 9.00},
    "rgbd_dataset_freiburg2_xyz": {"ORB-SLAM": 0.30, "PTAM": 0.20, "LSD-SLAM": 2.15},
    "rgbd_dataset_freiburg1_floor": {"ORB-SLAM": 2.99, "PTAM": None, "LSD-SLAM": 38.07},
    "rgbd_dataset_freiburg1_desk": {"ORB-SLAM": 1.69, "PTAM": None, "LSD-SLAM": 10.65},
    "rgbd_dataset_freiburg2_desk": {"ORB-SLAM": 0.88, "PTAM": None, "LSD-SLAM": 4.57},
}


def run(folder: Path, max_frames: int | None = None, imu: bool = False) -> dict:
    """One run over ``folder``, camera only unless ``imu``: the scores of the table's row."""
    from dataclasses import replace

    from runtime.datasets import open_any
    from runtime.eval import trajectory_errors
    from runtime.sequence import read_trajectory
    from runtime.slam.config import MapSettings
    from runtime.slam.run import run_slam

    seq = open_any(folder)
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "out"
        r = run_slam(folder, out, max_frames=max_frames, settings=replace(MapSettings(), use_imu=imu), progress=False)
        stats = json.loads((out / "stats.json").read_text())
        est = read_trajectory(out / "trajectory.tum")
    e = trajectory_errors(est, seq.groundtruth) if seq.groundtruth is not None and len(est.t) > 1 else None
    timed = [f for f in stats["frames"][1:] if not f["skipped"] and f["seconds"] > 0]
    ms = np.array([1000 * f["seconds"] for f in timed])
    cpu = np.array([1000 * f.get("cpu_seconds", np.nan) for f in timed])
    return {"name": Path(seq.root).name if Path(seq.root).name != "mav0" else Path(seq.root).parent.name,
            "frames": r.frames, "before_start": r.frames_before_start, "lost": r.lost_frames, "scale": r.scale,
            "ate_sim3_cm": 100 * e.ate_sim3_rmse_m if e else float("nan"),
            # Metric scales: none after a target or a map (their frame), SE(3) after depth or the IMU.
            "ate_metric_cm": 100 * e.ate("se3" if r.scale in ("depth", "imu") else "none")[0] if e else float("nan"),
            "sim3_scale": e.sim3_scale if e else float("nan"),
            "ms_median": float(np.median(ms)) if len(ms) else float("nan"),
            "ms_p99": float(np.percentile(ms, 99)) if len(ms) else float("nan"),
            "ms_max": float(ms.max()) if len(ms) else float("nan"),
            "cpu_ms": tuple(float(v) for v in (np.median(cpu), np.percentile(cpu, 99), cpu.max())) if len(cpu) else
            (float("nan"),) * 3}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("folders", nargs="*", type=Path)
    p.add_argument("--max-frames", type=int)
    p.add_argument("--imu", action="store_true", help="run the folders with their IMU (its scale)")
    a = p.parse_args()
    folders = [(f, a.imu) for f in a.folders]
    if not folders:
        for var in ("WVR_EUROC_MH01", "WVR_KITTI07", "WVR_TUM", "WVR_EUROC_MH01_IMU"):
            folders += [(Path(v), var.endswith("_IMU")) for v in os.environ.get(var, "").split(":") if v]
    if not folders:
        # make bench runs every benchmark: without the public data this one has nothing to say.
        print("bench_slam_real: skipped: no sequence; give folders or set WVR_EUROC_MH01, WVR_KITTI07, WVR_TUM "
              "(benchmarks/datasets.md)")
        return 0
    print("| sequence | frames (before start) | lost | scale (Sim3 factor) | ATE Sim3 cm | ATE metric cm | "
          "ms median / p99 / max | CPU ms median / p99 / max | ORB-SLAM / PTAM / LSD-SLAM cm |")
    print("|---|---|---|---|---|---|---|---|---|")
    from runtime.slam.startup import SlamStartError

    for folder, imu in folders:
        try:
            r = run(folder, a.max_frames, imu)
        except SlamStartError as e:     # a sequence with no start in it is a row, not the end of the table
            print(f"| {folder.name} | no start: {str(e).split(': ', 1)[-1].split(';')[0]} | - | - | - | - | - | - | - |",
                  flush=True)
            continue
        pub = PUBLISHED_CM.get(r["name"])
        pub_s = " / ".join("X" if pub[k] is None else f"{pub[k]:.2f}" for k in ("ORB-SLAM", "PTAM", "LSD-SLAM")) \
            if pub else "-"
        metric = f"{r['ate_metric_cm']:.2f}" if r["scale"] != "arbitrary" else "-"
        print(f"| {r['name']}{' with its IMU' if imu else ''} | {r['frames']} ({r['before_start']}) | {r['lost']} "
              f"| {r['scale']} (x{r['sim3_scale']:.3f}) "
              f"| {r['ate_sim3_cm']:.2f} | {metric} | {r['ms_median']:.1f} / {r['ms_p99']:.1f} / {r['ms_max']:.1f} "
              f"| {r['cpu_ms'][0]:.1f} / {r['cpu_ms'][1]:.1f} / {r['cpu_ms'][2]:.1f} "
              f"| {pub_s} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
