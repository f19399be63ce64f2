"""Start anywhere on the twin (issue 50): no target, camera only, then with the IMU's scale.

Each of the twin's recordings (made once and cached, as bench_slam.py's) is copied without its
target.toml, and `wvr slam`'s engine starts from natural features:

- camera only: the two-view start, the scale arbitrary: ATE RMSE after Sim(3), frames before the
  start, frames lost;
- with the IMU: the same start, the map then handed to the IMU once it has seen the scale
  (imu_handover.py): the filter's scale 3 s after the start and at the end, against the truth's
  (the Sim(3) factor that maps the written trajectory onto the ground truth), and the ATE after
  SE(3);
- with depth (``--depth``: recordings with the twin's depth images): the depth start, metric from
  the first frame: the scale's error (the Sim(3) factor less one) and the ATE after SE(3).

``python benchmarks/bench_slam_start.py [--seeds 2,3,4,5,6] [--scenarios walk,sit-down] [--depth] [--jobs 2]``
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_slam import REPORT_SEEDS, recording  # noqa: E402


def _job(args) -> tuple:
    kind, scenario, seed = args
    from dataclasses import replace

    from runtime.eval import trajectory_errors
    from runtime.sequence import open_sequence, read_trajectory
    from runtime.slam.config import MapSettings
    from runtime.slam.run import run_slam

    src = recording(scenario, seed, depth=kind == "depth")
    with tempfile.TemporaryDirectory() as d:
        seq = Path(d) / "seq"
        drop = ["target.toml", "rgb", "depth"] + ([] if kind == "imu" else ["imu.txt"])
        shutil.copytree(src, seq, ignore=shutil.ignore_patterns(*drop))
        (seq / "rgb").symlink_to((src / "rgb").resolve())
        if kind == "depth":
            (seq / "depth").symlink_to((src / "depth").resolve())
        out = Path(d) / "out"
        try:
            r = run_slam(seq, out, settings=replace(MapSettings(), use_imu=kind == "imu"), progress=False)
        except ValueError as e:                     # no start could be made: said, no trajectory
            return kind, scenario, seed, {"started": False, "why": str(e)}
        stats = json.loads((out / "stats.json").read_text())["totals"]
        e = trajectory_errors(read_trajectory(out / "trajectory.tum"), open_sequence(src).groundtruth)
    row = {"started": True, "before": r.frames_before_start, "lost": r.lost_frames, "scale": r.scale,
           "sim3_cm": 100 * e.ate_sim3_rmse_m, "se3_cm": 100 * e.ate_aligned_rmse_m, "factor": e.sim3_scale}
    if kind == "imu" and stats.get("imu_scale"):
        # The filter's scale where the IMU was handed the map (imu_handover.py), else the estimate
        # after the run.
        s = stats["imu_scale"].get("filter") or stats["imu_scale"]
        # The written trajectory is the raw one times s (when used): the truth's scale is factor x s.
        s_used = s["scale"] if r.scale == "imu" else 1.0
        s_true = e.sim3_scale * s_used
        row.update(scale_err_pct=100 * (s["scale"] / s_true - 1),
                   scale_3s_err_pct=100 * (s["scale_first_3s"] / s_true - 1) if s["scale_first_3s"] else float("nan"),
                   handover_s=s.get("handover_after_s"))
    return kind, scenario, seed, row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", default=",".join(map(str, REPORT_SEEDS)))
    p.add_argument("--scenarios", default="walk,sit-down,kitchen-walk,office-sit-down")
    p.add_argument("--kinds", default="camera,imu", help="camera, imu, depth")
    p.add_argument("--jobs", type=int, default=2)
    a = p.parse_args()
    jobs = [(k, sc, int(s)) for k in a.kinds.split(",") for sc in a.scenarios.split(",") for s in a.seeds.split(",")]
    rows: dict = {}
    with ProcessPoolExecutor(a.jobs) as ex:
        for kind, sc, seed, r in ex.map(_job, jobs):
            rows.setdefault((kind, sc), []).append(r)
            if not r["started"]:
                print(f"  {kind:6s} {sc:16s} seed {seed}: no start: {r['why']}", flush=True)
                continue
            extra = (f", scale error {r['scale_err_pct']:+.1f}% (first 3 s {r['scale_3s_err_pct']:+.1f}%)"
                     if "scale_err_pct" in r else "")
            if r.get("handover_s") is not None:
                extra += f", the IMU took the map {r['handover_s']:.1f} s after the start"
            print(f"  {kind:6s} {sc:16s} seed {seed}: scale {r['scale']}, Sim3 {r['sim3_cm']:.2f} cm, SE3 "
                  f"{r['se3_cm']:.2f} cm, factor {r['factor']:.4f}, {r['before']} frames before the start, "
                  f"{r['lost']} lost{extra}", flush=True)
    print("\n| start | scenario | started | ATE Sim3 cm median / worst | ATE SE3 cm | scale error % median / worst |")
    print("|---|---|---|---|---|---|")
    for (kind, sc), rs in rows.items():
        ok = [r for r in rs if r["started"]]
        if not ok:
            print(f"| {kind} | {sc} | 0 of {len(rs)} | - | - | - |")
            continue
        sim3 = np.array([r["sim3_cm"] for r in ok])
        se3 = np.array([r["se3_cm"] for r in ok])
        if kind == "imu":
            # Only runs whose scale the IMU gave: a run left arbitrary (too little acceleration to
            # estimate it, and said) has no scale error to report.
            took = [r for r in ok if r["scale"] == "imu"]
            err = np.array([abs(r.get("scale_3s_err_pct", np.nan)) for r in took])
            end = np.array([abs(r.get("scale_err_pct", np.nan)) for r in took])
            scale = (f"3 s after the start: {np.nanmedian(err):.1f} / {np.nanmax(err):.1f}, at the end: "
                     f"{np.nanmedian(end):.1f} / {np.nanmax(end):.1f} ({len(took)} of {len(ok)} took the "
                     f"IMU's scale)" if len(took) and np.isfinite(err).any() else
                     f"the IMU's scale taken by {len(took)} of {len(ok)} (too little acceleration)")
        elif kind == "depth":
            err = np.array([100 * abs(r["factor"] - 1) for r in ok])
            scale = f"{np.median(err):.2f} / {err.max():.2f}"
        else:
            scale = "(arbitrary)"
        print(f"| {kind} | {sc} | {len(ok)} of {len(rs)} | {np.median(sim3):.2f} / {sim3.max():.2f} | "
              f"{np.median(se3):.2f} / {se3.max():.2f} | {scale} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
