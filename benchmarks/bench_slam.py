"""SLAM benchmarks on twin recordings: ATE (no alignment and SE(3)-aligned) on 12 s
workbench-static and walk sequences and on sit-down, and frames per second on one core
(image decoding excluded: the per-frame time MonoSLAM reports). Targets (issue): ATE RMSE at
most 1 cm on workbench-static and walk, 2 cm on sit-down; at least 300 frames per second
(the EKF alone: bench_slam_speed.py)."""

import os
import tempfile
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from runtime.sequence import open_sequence, read_trajectory  # noqa: E402
from runtime.eval import map_errors, trajectory_errors  # noqa: E402
from runtime.slam.run import run_slam  # noqa: E402
from runtime.twin.recorder import record  # noqa: E402
from wvr.cli import make_twin  # noqa: E402


def main():
    with tempfile.TemporaryDirectory() as d:
        for scenario, seconds in (("workbench-static", 12.0), ("walk", 12.0), ("sit-down", 6.0)):
            twin = make_twin()
            try:
                seq = record(twin, scenario, Path(d) / scenario, seconds=seconds, seed=0, progress=False, depth=True)
            finally:
                twin.close()
            out = Path(d) / f"{scenario}-slam"
            tot = run_slam(seq, out, progress=False)
            sequence = open_sequence(seq)
            e = trajectory_errors(read_trajectory(out / "trajectory.tum"), sequence.groundtruth)
            print(f"{scenario:17s} {seconds:4.0f} s: ATE RMSE {100 * e.ate_rmse_m:5.2f} cm (max {100 * e.ate_max_m:5.2f}), "
                  f"aligned {100 * e.ate_aligned_rmse_m:5.2f} cm; RPE 1 s {100 * e.rpe_trans_rmse_m:5.2f} cm "
                  f"{e.rpe_rot_rmse_deg:4.2f} deg; {tot['mean_matched']:.1f} matched/frame; "
                  f"{1000 / tot['mean_ms_per_frame']:.0f} frames/s mean, {1000 / tot['median_ms_per_frame']:.0f} median (whole frame, decoding "
                  f"excluded); lost {tot['lost']}", flush=True)
            m = map_errors(sequence, out / "map.csv")
            print(f"{'':17s} map against the true depth: {len(m.errors_m)} features, RMSE {100 * m.rmse_m:.2f} cm, "
                  f"median {100 * m.median_m:.2f} cm", flush=True)


if __name__ == "__main__":
    main()
