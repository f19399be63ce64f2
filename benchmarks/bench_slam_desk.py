"""SLAM on a desk the twin did not render (issue 14's first case): ``desk_scene.py`` ray-casts a
desk of planar patches (wood, printed pages, boxes, a postered wall, the 21 x 15 cm target) in
numpy, with its own textures, a hand-held motion and its own image model (sensor noise, motion
blur over the exposure, an auto-exposure's drift and step), none of them the twin's. The target's
pixels are clicks 2-3 px off. Camera only, as the issue's reference system.

Scenarios: ``desk-handheld`` (10 s, the target always in view) and ``desk-gaze-away`` (the gaze
leaves the target from 3.5 s to 6.5 s, only the desk's natural features hold the pose, then
comes back). Reports per seed the ATE RMSE without alignment (the target fixes the frame), the
frames lost, and the median and worst over the seeds. Seeds 1, 11 and 23 were looked into while
the retry after a jerk and the target's re-acquisition were made (system.py); the default, 30-34,
came after and took part in nothing (benchmarks/NOTES.md).

``--start depth`` and ``--start two-view`` run each recording without its target.toml: the
natural start, from a depth image of the first frames (ray-cast at the frame's pose, with a
structured-light sensor's noise and 1/5000 m steps, registered to the camera: a TUM RGB-D
sequence's case) and scored after an SE(3) alignment (the start is metric in the first camera's
frame) with the scale's error (the Sim(3) factor less one); or from two views, scored after
Sim(3).

``--drop F`` runs each on a copy of the recording with about a fraction F of its frames missing,
in runs of 1 to 3 (as a recorder that drops frames under load, or frames skipped as bad, leave
them): the images and stamps are the same, the gaps longer.

``python benchmarks/bench_slam_desk.py [--seeds 30,31,32,33,34] [--jobs 2] [--drop 0.15]``;
sequences are kept in ``$WVR_BENCH_CACHE`` (default benchmarks/.cache) as
``desk-<scenario>-s<seed>`` (and ``...-drop<percent>``, rgb.txt rewritten, the rest linked).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

CACHE = Path(os.environ.get("WVR_BENCH_CACHE", Path(__file__).parent / ".cache"))
SECONDS = 10.0
#: scenario -> (distance to the target, m; the gaze-away's (start, end, ramp) s or None)
SCENARIOS = {"desk-handheld": (0.6, None), "desk-gaze-away": (0.6, (3.5, 6.5, 0.6))}
TARGET_CM = 2.0


def camera():
    """320x240, about 65 degrees across, a little barrel distortion (not the twin's lens)."""
    from kinematics.camera import CameraIntrinsics
    return CameraIntrinsics(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5, model="brown",
                            k1=-0.12, k2=0.02)


def sequence(scenario: str, seed: int) -> Path:
    """The rendered sequence, made once (written aside, then moved in place)."""
    from desk_scene import HandHeld, make_desk, write_sequence

    path = CACHE / f"desk-{scenario}-s{seed}"
    if (path / "target.toml").exists():
        return path
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = CACHE / f".desk-{scenario}-s{seed}.{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    distance, away = SCENARIOS[scenario]
    scene = make_desk(seed)
    motion = HandHeld(seed, scene.target_xyz.mean(axis=0), distance=distance, away=away)
    write_sequence(tmp, camera(), scene, motion, SECONDS, seed)
    shutil.rmtree(path, ignore_errors=True)
    tmp.rename(path)
    return path


def _linked_copy(seq: Path, path: Path, leave_out: str) -> Path | None:
    """None if ``path`` is made already; else a new folder beside it (renamed to it when done)
    linking every file of ``seq`` but ``leave_out``."""
    if (path / "rgb.txt").exists():
        return None
    tmp = seq.parent / f".{path.name}.{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for f in seq.iterdir():
        if f.name != leave_out:
            (tmp / f.name).symlink_to(f.resolve())
    return tmp


def dropped(seq: Path, fraction: float, seed: int) -> Path:
    """A copy of ``seq`` whose rgb.txt misses about ``fraction`` of its frames after the first
    (the target's clicks are on the first), in runs of 1-3; the other files are linked."""
    path = seq.parent / f"{seq.name}-drop{round(100 * fraction)}"
    tmp = _linked_copy(seq, path, "rgb.txt")
    if tmp is None:
        return path
    lines = (seq / "rgb.txt").read_text().splitlines(keepends=True)
    rng = np.random.default_rng(1000 + seed)
    out, first, skip = [], True, 0
    for line in lines:
        if line.startswith("#") or not line.strip():
            out.append(line)
        elif first:
            out.append(line)
            first = False
        elif skip > 0:
            skip -= 1
        elif rng.random() < fraction / 2.0:      # a run of 1-3 (2 on average) starts here
            skip = int(rng.integers(0, 3))
        else:
            out.append(line)
    (tmp / "rgb.txt").write_text("".join(out))
    shutil.rmtree(path, ignore_errors=True)
    tmp.rename(path)
    return path


#: Depth images the depth start's recordings hold (the first frames').
DEPTH_FRAMES = 3


def untargeted(seq: Path, scenario: str, seed: int, start: str) -> Path:
    """A copy of ``seq`` without its target.toml (the other files linked); for ``start`` "depth",
    with depth images of its first DEPTH_FRAMES frames (desk_scene.Renderer.depth at the frames'
    true poses, the sensor's noise seeded by ``seed``) and their depth.txt."""
    from desk_scene import HandHeld, Renderer, make_desk

    from runtime.sequence import open_sequence
    from runtime.sequence.writer import SequenceWriter

    path = seq.parent / f"{seq.name}-{start}"
    tmp = _linked_copy(seq, path, "target.toml")
    if tmp is None:
        return path
    if start == "depth":
        distance, away = SCENARIOS[scenario]
        scene = make_desk(seed)
        motion = HandHeld(seed, scene.target_xyz.mean(axis=0), distance=distance, away=away)
        s = open_sequence(seq)
        ren, rng = Renderer(s.camera, scene), np.random.default_rng(40_000 + seed)
        with SequenceWriter(tmp / ".depth", s.camera) as w:
            for t in s.timestamps[:DEPTH_FRAMES]:
                w.add_depth(t, ren.depth(*motion.pose(t), rng))
        (tmp / ".depth" / "depth").rename(tmp / "depth")
        (tmp / ".depth" / "depth.txt").rename(tmp / "depth.txt")
        shutil.rmtree(tmp / ".depth")
    shutil.rmtree(path, ignore_errors=True)
    tmp.rename(path)
    return path


def _job(args):
    scenario, seed, drop, start = args
    from runtime.eval import trajectory_errors
    from runtime.sequence import open_sequence, read_trajectory
    from runtime.slam.run import run_slam

    seq = sequence(scenario, seed)
    if drop > 0:
        seq = dropped(seq, drop, seed)
    if start != "target":
        seq = untargeted(seq, scenario, seed, start)
    with tempfile.TemporaryDirectory() as d:
        try:
            tot = run_slam(seq, d, progress=False)
        except Exception as e:                     # a refused start is a result here
            return scenario, seed, None, str(e).splitlines()[0]
        e = trajectory_errors(read_trajectory(Path(d) / "trajectory.tum"), open_sequence(seq).groundtruth)
    ate = {"target": e.ate_rmse_m, "depth": e.ate("se3")[0], "two-view": e.ate_sim3_rmse_m}[start]
    return scenario, seed, (100 * ate, tot.lost_frames, tot.mean_matched, tot.reacquired, e.sim3_scale,
                            tot.frames_before_start, tot.scale), None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", default="30,31,32,33,34", help="desk seeds (scene, motion and images)")
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--drop", type=float, default=0.0, help="fraction of the frames missing, in runs of 1-3")
    p.add_argument("--start", choices=("target", "depth", "two-view"), default="target",
                   help="the clicked target (ATE unaligned), a depth image (SE(3)) or two views (Sim(3))")
    a = p.parse_args()
    if not 0.0 <= a.drop < 0.8:
        p.error(f"--drop {a.drop}: give a fraction of the frames in [0, 0.8)")
    seeds = [int(s) for s in a.seeds.split(",")]
    jobs = [(sc, s, a.drop, a.start) for sc in a.scenarios.split(",") for s in seeds]
    how = {"target": "clicked start", "depth": "depth start, ATE after SE(3)", "two-view": "two-view start, ATE after "
           "Sim(3)"}[a.start]
    print(f"SLAM on the ray-cast desk, camera only, {how}: {len(jobs)} runs (sequences in {CACHE})", flush=True)
    scale_err: dict[str, list] = {}
    res: dict[str, list] = {}
    with ProcessPoolExecutor(a.jobs) as ex:
        for scenario, seed, r, err in ex.map(_job, jobs):
            if r is None:
                print(f"{scenario} seed {seed}: refused: {err}", flush=True)
                res.setdefault(scenario, []).append(np.inf)
                continue
            ate, lost, matched, reacquired, factor, before, scale = r
            print(f"{scenario} seed {seed}: ATE {ate:.2f} cm, {lost} frames lost, {matched:.1f} matched/frame, "
                  + (f"target re-acquired {reacquired} times" if a.start == "target" else
                     f"scale {scale} (Sim3 factor {factor:.4f}), {before} frames before the start"), flush=True)
            res.setdefault(scenario, []).append(ate if lost == 0 else np.inf)
            scale_err.setdefault(scenario, []).append(100 * abs(factor - 1.0))
    metric = a.start == "depth"
    print(f"\n| scenario | seeds | ATE cm median | worst | {'scale error % median / worst | ' if metric else ''}target |"
          f"\n|---|---|---|---|{'---|' if metric else ''}---|")
    for scenario, v in res.items():
        v = np.array(v)
        ok = "met" if v.max() <= TARGET_CM else "NOT MET"
        name = f"{scenario}, {100 * a.drop:.0f}% of frames missing" if a.drop > 0 else scenario
        sc = np.array(scale_err.get(scenario, [np.nan]))
        print(f"| {name} | {len(v)} | {np.median(v):.2f} | {v.max():.2f} | "
              + (f"{np.median(sc):.1f} / {sc.max():.1f} | " if metric else "")
              + f"<= {TARGET_CM:g}, never lost ({ok}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
