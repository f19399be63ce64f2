"""The robot seam, the drivers and hardware in the loop (issue: one robot interface for twin and
hardware). Figures:

* HIL fixation: `wvr sim hil` + `wvr run --rig --task fixate` on workbench-static (4 s), scored
  from the HIL's true trajectory, against `wvr sim run` on the same scenario and seed (target:
  within 0.5 deg RMS of each other), seeds 0 and 1;
* the serial round trip (Get Errors to the virtual Maestro on a pseudo-terminal, median and 99th
  percentile) and the rig loop's period jitter in the HIL run (wall time between commands);
* Path A + the software fovea on sit-down-head-still: the closed loop's `stabilise` task
  (the head cancels the rotation from the IMU), recorded, then `stabilise_sequence`'s fovea;
  background motion (vision2d.stabilise.residual_motion) against the static camera's raw frames
  (target: at least 5x less).
"""

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from runtime.apps.closed_loop import Task  # noqa: E402
from runtime.apps.evaluate import fixation_errors  # noqa: E402
from runtime.apps.session import SessionRecorder  # noqa: E402
from runtime.drivers.maestro import Maestro  # noqa: E402
from runtime.sequence import load_target, read_trajectory  # noqa: E402
from runtime.twin.hil import HilSession, VirtualMaestro, WallClockMaestro  # noqa: E402
from runtime.twin.recorder import record  # noqa: E402
from runtime.vision2d.stabilise import stabilise_sequence  # noqa: E402
from wvr.assemble import make_twin, run_on_twin  # noqa: E402

SECONDS = 4.0


def bench_round_trip(n=500):
    vm = VirtualMaestro()
    wc = WallClockMaestro(vm)
    try:
        m = Maestro.open(wc.path)
        m.get_errors()
        dts = []
        for _ in range(n):
            t0 = time.perf_counter()
            m.get_errors()
            dts.append(time.perf_counter() - t0)
        m.close()
    finally:
        wc.close()
    dts = np.array(dts) * 1000
    print(f"serial round trip (Get Errors, virtual Maestro on a pty): median {np.median(dts):.3f} ms, "
          f"99th percentile {np.percentile(dts, 99):.3f} ms over {n}", flush=True)


def hil_fixation(seed: int, d: Path) -> tuple[float, float, np.ndarray]:
    twin = make_twin()
    twin.configure("workbench-static", seed=seed, seconds=SECONDS)
    hil = HilSession(twin, d / f"hil{seed}", imu="text", linger_s=6.0, click_seed=seed)
    ready = threading.Event()
    hil.ready = ready.set
    th = threading.Thread(target=hil.run, kwargs={"progress": False})
    th.start()
    ready.wait(120)
    r = subprocess.run([sys.executable, "-m", "wvr", "run", "--rig", str(d / f"hil{seed}" / "rig.toml"), "--task",
                        "fixate", "--out", str(d / f"run{seed}")], capture_output=True, text=True)
    th.join()
    hil.close()
    twin.close()
    if r.returncode != 0:
        raise RuntimeError(r.stderr)
    gt = read_trajectory(d / f"hil{seed}" / "groundtruth.txt")
    target = load_target(d / f"hil{seed}" / "target.toml").xyz.mean(axis=0)
    err = np.degrees(fixation_errors(gt.T_world_cam(), np.repeat(target[None], len(gt), 0)))
    after = gt.t >= 1.0
    hil_rms = float(np.sqrt(np.mean(err[after] ** 2)))
    twin = make_twin()
    s = run_on_twin(twin, "workbench-static", Task("fixate", target[None]), d / f"sim{seed}", seconds=SECONDS, seed=seed,
                    progress=False)
    twin.close()
    return hil_rms, s["fixation_rms_deg"], np.diff(hil.maestro.wall_times)


def bench_path_a_fovea(d: Path):
    twin = make_twin()
    static = record(twin, "sit-down-head-still", d / "static", seconds=SECONDS, seed=0, progress=False)
    st_static = stabilise_sequence(static, d / "static-out", progress=False)
    rec = {}

    def on_period(obs, cmd):
        if "r" not in rec:
            rec["r"] = SessionRecorder(d / "pathA", twin.camera, twin.head)
        rec["r"](obs, cmd)
    run_on_twin(twin, "sit-down-head-still", Task("stabilise"), d / "pathA-run", seconds=SECONDS, progress=False,
                on_period=on_period)
    rec["r"].finish(True)
    twin.close()
    st_a = stabilise_sequence(d / "pathA", d / "pathA-out", progress=False)
    st_af = stabilise_sequence(d / "pathA", d / "pathA-fovea", progress=False, use_imu=True)
    raw = st_static["raw_motion_px"]
    print(f"sit-down-head-still {SECONDS:g} s, background motion (median LK flow of corners, px/frame): static camera "
          f"{raw:.2f}; static + fovea {st_static['fovea_motion_px']:.2f}; Path A head {st_a['raw_motion_px']:.2f}; "
          f"Path A + fovea {st_a['fovea_motion_px']:.2f} (gyro-aided fovea {st_af['fovea_motion_px']:.2f}); "
          f"ratio static / (Path A + fovea) {raw / st_a['fovea_motion_px']:.1f}x (target >= 5)", flush=True)


def main():
    bench_round_trip()
    with tempfile.TemporaryDirectory(prefix="bench_robot_") as tmp:
        d = Path(tmp)
        wall = []
        for seed in (0, 1):
            t0 = time.time()
            hil_rms, sim_rms, periods = hil_fixation(seed, d)
            wall += list(periods[1:])
            # Period jitter: the controller's commands in the simulated clock are exactly one
            # frame apart (lock step); the wall-clock jitter is the loop's own.
            print(f"HIL fixation, workbench-static seed {seed}, {SECONDS:g} s: RMS {hil_rms:.3f} deg after 1 s; "
                  f"wvr sim run {sim_rms:.3f} deg; difference {abs(hil_rms - sim_rms):.3f} deg (target <= 0.5) "
                  f"({time.time() - t0:.0f} s)", flush=True)
            stats = json.loads((d / f"run{seed}" / "summary.json").read_text())
            print(f"  rig run: {stats['frames']} frames, ended: {stats['ended']}", flush=True)
        wall = np.array(wall)
        if len(wall):
            print(f"rig loop period (wall clock, lock step with the renderer): median {1000 * np.median(wall):.1f} ms, "
                  f"jitter (std) {1000 * np.std(wall):.1f} ms, 95th percentile {1000 * np.percentile(wall, 95):.1f} ms",
                  flush=True)
        bench_path_a_fovea(d)


if __name__ == "__main__":
    main()
