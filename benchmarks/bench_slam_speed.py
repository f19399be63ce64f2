"""SLAM speed on one core, whole frame (issue 14): MonoSLAM.process on twin recordings, image
decoding excluded (every frame is decoded into memory before the clock starts), at 320x240 and
640x480 with 30 (the targets' condition) and 60 (the default) features measured per frame at most.

Reports frames/s (median and 10th percentile over the frames), the curve of milliseconds per
frame against map size, and a profile (cProfile, top functions by own time) of one run.
Targets: at 320x240 with 20-30 features measured per frame at least 300 frames/s median; at
640x480 at least 150.

``OMP_NUM_THREADS=1 python benchmarks/bench_slam_speed.py [--scenario walk] [--seed 2]
[--seconds 12] [--csv FILE]``; recordings are kept in ``$WVR_BENCH_CACHE`` as bench_slam's.

This machine's speed can move by a factor of two between runs, so a change is timed against
the code before it in alternated runs: ``--against REF`` checks out the git revision REF beside
this one and runs the two in turn, ``--rounds`` times each (30 measured), printing each run's
frames/s median and the median over runs.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

SIZES = {"320x240": (320, 240), "640x480": (640, 480)}
TARGET_FPS = {"320x240": 300.0, "640x480": 150.0}
MAP_BINS = (0, 25, 50, 75, 100, 125, 150, 200)


def recording(scenario: str, seed: int, size: tuple[int, int], seconds: float) -> Path:
    """A twin recording at ``size`` (the default camera's lens, its intrinsics scaled), made once."""
    from bench_slam import recording as cached_recording
    from kinematics.camera import default_camera

    w, h = size
    cam = default_camera()
    s = w / cam.width
    cam = replace(cam, width=w, height=h, fx=cam.fx * s, fy=cam.fy * s, cx=cam.cx * s, cy=cam.cy * s)
    return cached_recording(scenario, seed, camera=cam, seconds=seconds,
                            name=f"speed-{scenario}-s{seed}-{w}x{h}-{seconds:g}s")


def timed_run(seq_path: Path, measure_max: int, profile: bool = False):
    """MonoSLAM over the decoded frames, camera only: per-frame seconds (F,), map sizes (F,),
    features matched (F,), and the profile's text when asked."""
    from runtime.sequence import open_sequence
    from runtime.slam.config import MapSettings
    from runtime.slam.system import MonoSLAM

    seq = open_sequence(seq_path)
    frames = [f for f in seq.frames() if f.image is not None]     # decoding, outside the clock
    slam = MonoSLAM(seq.camera, settings=replace(MapSettings(), use_imu=False).with_measure(measure_max))
    slam.start(frames[0].image, frames[0].t, seq.target)
    prof = cProfile.Profile() if profile else None
    secs, sizes, matched = [], [], []
    for f in frames[1:]:
        n = slam.state.n_features
        if prof:
            prof.enable()
        t0 = time.perf_counter()
        st = slam.process(f.image, f.t)
        dt = time.perf_counter() - t0
        if prof:
            prof.disable()
        secs.append(dt)
        sizes.append(n)
        matched.append(st.matched)
    text = None
    if prof:
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(18)
        text = buf.getvalue()
    return np.array(secs), np.array(sizes), np.array(matched), text


def fps_runs(size: str, scenario: str, seed: int, seconds: float, runs: int) -> list[float]:
    """Frames/s median of each of ``runs`` timed runs (30 measured) after a warm one."""
    seq = recording(scenario, seed, SIZES[size], seconds)
    timed_run(seq, 30)
    return [float(1.0 / np.median(timed_run(seq, 30)[0])) for _ in range(runs)]


def against(ref: str, a) -> int:
    """Alternated runs of the checkout at git revision ``ref`` and this one (module docstring)."""
    here = Path(__file__).resolve().parent
    root = here.parent
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    rev = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", "--short", f"{ref}^{{commit}}"],
                         capture_output=True, text=True)
    if rev.returncode != 0:
        print(f"bench_slam_speed: --against {ref}: not a git revision of {root}; give a commit, tag or branch",
              file=sys.stderr)
        return 2
    from bench_slam import CACHE
    env = dict(os.environ, WVR_BENCH_CACHE=str(CACHE), OMP_NUM_THREADS="1")
    runs: dict = {}
    with tempfile.TemporaryDirectory(prefix="wvr-against-") as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", "-q", str(tree), rev.stdout.strip()],
                       check=True)
        try:
            sides = {f"{ref} ({rev.stdout.strip()})": tree, f"this checkout ({head.stdout.strip()})": root}
            for r in range(a.rounds):
                for name, path in sides.items():
                    for size in SIZES:
                        out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--fps-only", size,
                                              "--scenario", a.scenario, "--seed", str(a.seed), "--seconds",
                                              str(a.seconds)],
                                             env=dict(env, PYTHONPATH=str(path)), capture_output=True, text=True,
                                             check=True)
                        if not Path(out.stderr.strip().splitlines()[-1].split(" at ")[-1]).is_relative_to(path):
                            raise RuntimeError(f"the run for {name} imported another checkout: {out.stderr.strip()}")
                        fps = [float(v) for v in out.stdout.split()]
                        runs.setdefault((name, size), []).extend(fps)
                        print(f"round {r + 1}: {name}, {size}: " + ", ".join(f"{v:.0f}" for v in fps), flush=True)
        finally:
            subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(tree)], check=False)
    print(f"\n| checkout | image | frames/s median over runs | range |\n|---|---|---|---|")
    for (name, size), v in runs.items():
        print(f"| {name} | {size} | {np.median(v):.0f} | {min(v):.0f}-{max(v):.0f} |")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="walk", help="twin scenario recorded (default walk)")
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--seconds", type=float, default=12.0)
    p.add_argument("--measure", default="30,60", help="features measured per frame, at most (list; 60 is MapSettings' default)")
    p.add_argument("--csv", help="write the map-size curve there")
    p.add_argument("--against", metavar="REF", help="alternate with the code at git revision REF (docstring)")
    p.add_argument("--rounds", type=int, default=3, help="with --against: rounds of alternation")
    p.add_argument("--fps-only", choices=list(SIZES), help=argparse.SUPPRESS)   # one side of --against
    a = p.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})     # one core
    if a.fps_only:
        import runtime
        print(f"timing the runtime package at {Path(runtime.__file__).parent}", file=sys.stderr)
        print(" ".join(f"{v:.2f}" for v in fps_runs(a.fps_only, a.scenario, a.seed, a.seconds, 3)))
        return 0
    if a.against:
        if a.rounds < 1:
            print(f"bench_slam_speed: --rounds {a.rounds}: give at least 1", file=sys.stderr)
            return 2
        return against(a.against, a)
    rows = []
    print("| image | measured at most | matched/frame (median) | frames/s median | frames/s p10 | target |")
    print("|---|---|---|---|---|---|")
    curves, profile_text = {}, None
    for label, size in SIZES.items():
        seq = recording(a.scenario, a.seed, size, a.seconds)
        for m in (int(v) for v in a.measure.split(",")):
            timed_run(seq, m)                                     # warm: numba compiled, caches filled
            secs, sizes, matched, _ = timed_run(seq, m)
            fps = 1.0 / np.median(secs)
            p10 = 1.0 / np.percentile(secs, 90)
            ok = "met" if fps >= TARGET_FPS[label] else "NOT MET"
            print(f"| {label} | {m} | {np.median(matched):.0f} | {fps:.0f} | {p10:.0f} | "
                  f">= {TARGET_FPS[label]:.0f} ({ok}) |", flush=True)
            curves[(label, m)] = (secs, sizes)
            for lo, hi in zip(MAP_BINS[:-1], MAP_BINS[1:]):
                sel = (sizes >= lo) & (sizes < hi)
                if sel.any():
                    rows.append((label, m, lo, hi, int(sel.sum()), 1000 * float(np.median(secs[sel]))))
    print(f"\nms per frame (median) against map size, {a.scenario} seed {a.seed}:")
    print("| image | measured | map size | frames | ms/frame |\n|---|---|---|---|---|")
    for label, m, lo, hi, n, ms in rows:
        print(f"| {label} | {m} | {lo}-{hi - 1} | {n} | {ms:.2f} |")
    if a.csv:
        with open(a.csv, "w") as f:
            f.write("image,measure_max,map_lo,map_hi,frames,median_ms\n")
            f.writelines(f"{r[0]},{r[1]},{r[2]},{r[3]},{r[4]},{r[5]:.3f}\n" for r in rows)
    seq = recording(a.scenario, a.seed, SIZES["640x480"], a.seconds)
    *_, profile_text = timed_run(seq, 30, profile=True)
    print("\nprofile, 640x480, 30 measured (own time):\n" + profile_text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
