"""SLAM accuracy on the twin (issue 14's numbers), over seeds the SLAM was not tuned on.

Every figure is ATE RMSE without alignment (the target fixes the frame), against the twin's
ground truth, over the report seeds (default 2-6; the settings were chosen on seeds 0, 1, 7 and 8, see
benchmarks/NOTES.md), given as median and worst per scenario:

- camera only (the paper's system): the static scenes at most 1 cm; walk, sit-down and the
  gaze-away scenarios at most 2 cm, never lost;
- with the realistic IMU (a BMI088's errors; bias and clock-offset states in the filter): walk at most 1 cm;
- a clicked start (target.toml's pixels 2-3 px off, refined on the image) against an exact
  start, camera only: within 10%. Two exact starts: the true projections given as the clicks
  (the same start-up refines them: what a perfect click gets), and the true projections taken
  as they are, unrefined (a start no real system has; a walk's ATE is its drift, which any
  sub-pixel change at the start draws again);
- map reuse: a map saved from one recording, a second recording of the same place with another
  motion started from it with no target and no IMU: at most 2 cm, located within 1 s.

Recordings are made once and kept in ``$WVR_BENCH_CACHE`` (default benchmarks/.cache).
``python benchmarks/bench_slam.py [--seeds 2,3,4,5,6] [--part accuracy,imu,clicks,reuse] [--jobs 2]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

CACHE = Path(os.environ.get("WVR_BENCH_CACHE", Path(__file__).parent / ".cache"))
REPORT_SEEDS = (2, 3, 4, 5, 6)
#: How new features start (--features): "inverse-depth" (the default) or "particles".
FEATURES = os.environ.get("WVR_BENCH_FEATURES", "inverse-depth")
STATIC = ("workbench-static", "kitchen-static", "office-static", "office-far-target")
MOVING = ("walk", "sit-down", "workbench-gaze-away", "kitchen-gaze-away", "office-sit-down", "kitchen-walk")
#: The issue's targets (cm); kitchen-walk and office-far-target are reported without one.
TARGET_CM = {**{s: 1.0 for s in STATIC if s != "office-far-target"},
             **{s: 2.0 for s in ("walk", "sit-down", "workbench-gaze-away", "kitchen-gaze-away", "office-sit-down")}}
#: Map reuse: (mapping scenario, re-locating scenario), the same place (scene seed).
REUSE = (("workbench-static", "sit-down"), ("kitchen-static", "kitchen-walk"))


def recording(scenario: str, seed: int, scene_seed: int | None = None, camera=None, seconds: float | None = None,
              name: str | None = None, depth: bool = False) -> Path:
    """The twin's recording of ``scenario`` (realistic camera and IMU, clicked target), made once
    and kept in the cache as ``name`` (default from the scenario and seeds); ``camera`` :
    CameraIntrinsics (default the twin's), ``seconds`` (default the scenario's); ``depth``: with the twin's
    depth images too."""
    if name is None:
        name = f"{scenario}-s{seed}" + (f"-place{scene_seed}" if scene_seed is not None else "") + ("-depth" if depth else "")
    path = CACHE / name
    if (path / "rgb.txt").exists() and not (path / "INCOMPLETE").exists():
        return path
    from runtime.twin.recorder import record
    from wvr.assemble import make_twin

    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = CACHE / f".{name}.{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    twin = make_twin(camera=camera)
    try:
        record(twin, scenario, tmp, seconds=seconds, seed=seed, scene_seed=scene_seed, progress=False, depth=depth)
    finally:
        twin.close()
    shutil.rmtree(path, ignore_errors=True)
    tmp.rename(path)
    return path


def slam_ate(seq_path: Path, imu: bool = False, exact_start: str = "", map_path: Path | None = None,
             save_map: Path | None = None) -> dict:
    """One SLAM run over a recording: ATE RMSE (cm, no alignment), lost, median ms per frame and,
    for a saved map's run, when the camera was first located (s). ``exact_start``: "clicks" (the
    true projections as target.toml's clicks, refined as any) or "unrefined" (taken as they are)."""
    from runtime.eval import associate, trajectory_errors
    from runtime.sequence import load_target, open_sequence, read_trajectory, save_target
    from runtime.slam.config import MapSettings
    from runtime.slam.run import run_slam

    settings = replace(MapSettings(), use_imu=imu, features=os.environ.get("WVR_BENCH_FEATURES", FEATURES))
    with tempfile.TemporaryDirectory() as d:
        seq = seq_path
        if exact_start:
            # A copy of the recording whose target.toml holds the true projections.
            if exact_start not in ("clicks", "unrefined"):
                raise ValueError(f"exact_start = {exact_start!r}: give 'clicks' or 'unrefined'")
            seq = Path(d) / "exact"
            shutil.copytree(seq_path, seq, ignore=shutil.ignore_patterns("rgb"))
            (seq / "rgb").symlink_to((seq_path / "rgb").resolve())
            save_target(load_target(seq_path / "target_truth.toml"), seq / "target.toml")
            if exact_start == "unrefined":
                settings = replace(settings, click_search_px=0.0)
        if map_path is not None:
            seq = Path(d) / "no-target"
            shutil.copytree(seq_path, seq, ignore=shutil.ignore_patterns("rgb", "target.toml", "imu.txt"))
            (seq / "rgb").symlink_to((seq_path / "rgb").resolve())
        out = Path(d) / "out"
        t0 = time.time()
        r = run_slam(seq, out, settings=settings, progress=False, map_path=map_path, save_map=save_map)
        gt = open_sequence(seq_path).groundtruth
        est = read_trajectory(out / "trajectory.tum") if r.first_localised_s is not None else None
        e = trajectory_errors(est, gt) if est is not None and len(est.t) > 1 else None
        # The first pose written: for a saved map's run, where the camera was located.
        ie, ig = associate(est, gt) if e else (np.zeros(0, int), np.zeros(0, int))
        first_cm = 100 * float(np.linalg.norm(est.p_world_cam[ie[0]] - gt.p_world_cam[ig[0]])) if len(ie) else float("inf")
        return {"ate_cm": 100 * e.ate_rmse_m if e else float("inf"), "max_cm": 100 * e.ate_max_m if e else float("inf"),
                "lost": r.lost, "lost_frames": r.lost_frames, "ms": r.median_ms_per_frame,
                "located_s": r.first_localised_s, "located_cm": first_cm, "matched": r.mean_matched,
                "wall_s": time.time() - t0}


#: The exact starts a clicked one is compared with: job kind -> slam_ate's exact_start.
EXACT_STARTS = {"exact": "clicks", "unrefined": "unrefined"}


def _job(args):
    kind, scenario, seed = args[:3]
    if kind == "reuse":
        mapping, relocating = scenario
        place = 100 + seed
        with tempfile.TemporaryDirectory() as d:
            m = Path(d) / "map.npz"
            first = slam_ate(recording(mapping, seed, place), save_map=m)
            second = slam_ate(recording(relocating, seed + 50, place), map_path=m)
        return kind, f"{mapping} -> {relocating}", seed, {"first": first, **second}
    seq = recording(scenario, seed)
    if kind == "camera":
        return kind, scenario, seed, slam_ate(seq)
    if kind == "imu":
        return kind, scenario, seed, slam_ate(seq, imu=True)
    if kind in EXACT_STARTS:
        return kind, scenario, seed, slam_ate(seq, exact_start=EXACT_STARTS[kind])
    raise ValueError(kind)


def _summary(rows: list[dict], key: str = "ate_cm") -> str:
    v = np.array([r[key] for r in rows], float)
    lost = sum(bool(r["lost"]) for r in rows)
    return f"median {np.median(v):.2f}, worst {v.max():.2f} cm" + (f"; lost in {lost} of {len(rows)}" if lost else "; never lost")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", default=",".join(map(str, REPORT_SEEDS)), help="run seeds (default: the report seeds)")
    p.add_argument("--part", default="accuracy,imu,clicks,reuse", help="which figures")
    p.add_argument("--jobs", type=int, default=2, help="parallel processes")
    p.add_argument("--features", choices=["inverse-depth", "particles"], default=FEATURES,
                   help="how new features start (default inverse-depth)")
    p.add_argument("--scenarios", default=",".join(STATIC + MOVING), help="for the accuracy part")
    a = p.parse_args()
    seeds = [int(s) for s in a.seeds.split(",")]
    os.environ["WVR_BENCH_FEATURES"] = a.features      # for the worker processes
    parts = set(a.part.split(","))
    jobs = []
    if "accuracy" in parts:
        jobs += [("camera", sc, s) for sc in a.scenarios.split(",") for s in seeds]
    if "imu" in parts:
        jobs += [("imu", "walk", s) for s in seeds]
    if "clicks" in parts:
        jobs += [(k, sc, s) for sc in ("workbench-static", "walk") for s in seeds for k in ("camera", *EXACT_STARTS)]
    if "reuse" in parts:
        jobs += [("reuse", pair, s) for pair in REUSE for s in seeds]
    jobs = list(dict.fromkeys(jobs))
    results: dict = {}
    print(f"SLAM ({a.features} features) over seeds {seeds}: {len(jobs)} runs, {a.jobs} at a time (recordings cached in {CACHE})", flush=True)
    with ProcessPoolExecutor(a.jobs) as ex:
        for kind, scenario, seed, r in ex.map(_job, jobs):
            results.setdefault((kind, scenario), []).append(r)
            extra = (f", located after {r['located_s']:.2f} s, {r['located_cm']:.2f} cm off"
                     if kind == "reuse" and r["located_s"] is not None else "")
            print(f"  {kind:6s} {scenario:40s} seed {seed}: ATE {r['ate_cm']:.2f} cm (max {r['max_cm']:.2f}), "
                  f"{'LOST ' + str(r['lost_frames']) + ' frames, ' if r['lost'] else ''}{r['ms']:.1f} ms/frame{extra}",
                  flush=True)
    print("\n| figure | target | median, worst |\n|---|---|---|")
    for (kind, scenario), rows in results.items():
        if kind == "camera" and scenario in TARGET_CM:
            ok = max(r["ate_cm"] for r in rows) <= TARGET_CM[scenario] and not any(r["lost"] for r in rows)
            print(f"| {scenario}, camera only | <= {TARGET_CM[scenario]:g} cm | {_summary(rows)}{'' if ok else ' (NOT MET)'} |")
        elif kind == "camera":
            print(f"| {scenario}, camera only | (reported) | {_summary(rows)} |")
        elif kind == "imu":
            ok = max(r["ate_cm"] for r in rows) <= 1.0 and not any(r["lost"] for r in rows)
            print(f"| {scenario}, realistic IMU with bias states and clock offset | <= 1 cm | {_summary(rows)}{'' if ok else ' (NOT MET)'} |")
        elif kind == "reuse":
            loc = [r["located_s"] for r in rows]
            ok = max(r["ate_cm"] for r in rows) <= 2.0 and all(r["located_s"] is not None and r["located_s"] < 1.0 for r in rows)
            off = np.array([r["located_cm"] for r in rows])
            print(f"| map reuse {scenario}, no target, no IMU | <= 2 cm, located < 1 s | {_summary(rows)}; located "
                  f"after {', '.join('never' if v is None else f'{v:.2f} s' for v in loc)}, {np.median(off):.2f} / "
                  f"{off.max():.2f} cm off{'' if ok else ' (NOT MET)'} |")
    for sc in ("workbench-static", "walk"):
        for kind, what, target in (("exact", "exact clicks", "within 10%"),
                                   ("unrefined", "true projections unrefined", "(reported)")):
            c, e = results.get(("camera", sc)), results.get((kind, sc))
            if not (c and e):
                continue
            ate_c, ate_e = np.array([x["ate_cm"] for x in c]), np.array([y["ate_cm"] for y in e])
            ratio = ate_c / np.maximum(ate_e, 1e-9)
            w = int(np.argmax(ratio))
            ok = "" if ratio.max() <= 1.1 or kind != "exact" else " (NOT MET)"
            print(f"| clicked start / {what}, {sc} | {target} | ratio median {np.median(ratio):.2f}, "
                  f"worst {ratio.max():.2f} ({ate_c[w]:.2f} against {ate_e[w]:.2f} cm){ok} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
