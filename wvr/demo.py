"""``wvr demo``: every stage that exists, in pipeline order, with small budgets.

Each stage writes into its own folder under the output directory and returns a Markdown
section for ``report.md`` that links its files, printed from the runners' typed results. The
stages (design, kinematics, placement, twin, SLAM, gaze, stabilisation, planar tracking, head
tracking) are listed in :data:`STAGES` in pipeline order; the head a stage uses is whatever the
previous stages chose (``context["head"]``).

A stage that cannot do its work raises :class:`StageFailed` (or fails with any error): the
report says so under its title and at the top, the later stages still run, and ``wvr demo``
exits with status 1.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from kinematics.progress import progress_bar

from kinematics import reference_head, save_head
from kinematics.camera import default_camera, save_camera


class StageFailed(RuntimeError):
    """A demo stage could not do its work (the message says why)."""


@dataclass
class DemoResult:
    report: Path                                  # report.md
    failed: list[str] = field(default_factory=list)   # titles of the stages that failed


def demo_sweep():
    """The default sweep cut down to a demo budget: 168 evaluations (6 generations of 28)."""
    from dataclasses import replace

    from design.sweep_file import load_sweep

    spec = load_sweep()
    return replace(spec, name="demo", evaluations=168, partitions=2,
                   workload=replace(spec.workload, saccade_amplitudes_deg=(10.0, 40.0), walk_seconds=1.0))


#: How the report names the sweeps' searches (design.sweep_file.ALGORITHMS).
ALGORITHM_NAMES = {"agemoea2": "AGE-MOEA2", "surrogate": "AGE-MOEA2 with a surrogate pre-screen", "nsga3": "NSGA-III",
                   "random": "Random variation"}


def stage_design(out: Path, context: dict) -> str:
    """A small sweep of the head's layout (the default search); its chosen head flows to every later stage."""
    from design.study import optimise
    from kinematics import load_head

    o = optimise(demo_sweep(), out, progress=False)
    rel = out.name
    if o.chosen is None:
        return f"No feasible design in {o.evaluations} evaluations; later stages use the reference head."
    c = o.chosen
    context["head"] = load_head(c.head_path)
    rows = "\n".join(f"| `{k}` | {v:.4g} | {c.reference_criteria[k]:.4g} |" for k, v in c.criteria.items())
    return "\n".join([
        f"{ALGORITHM_NAMES.get(o.algorithm, o.algorithm)} over the positions of camera and motors, {o.evaluations} "
        f"evaluations: {o.feasible} feasible, front of {o.front_size}, hypervolume {c.hypervolume:.3f} (normalised, "
        f"{'exact' if c.hypervolume_exact else 'moocore approximation'}). "
        f"{c.decision.capitalize()}.",
        f"Files: [report.md]({rel}/report.md), [front.csv]({rel}/front.csv), [evaluations.csv]({rel}/evaluations.csv), "
        f"[chosen_head.toml]({rel}/chosen_head.toml).", "",
        "| criterion | chosen | reference head |", "|---|---|---|", rows, "",
        f"![front]({rel}/{o.pictures['parallel']})",
    ])


def stage_kinematics(out: Path, context: dict) -> str:
    """The head's kinematics: chain summary, head.toml, its MJCF, camera.toml and a picture."""
    from kinematics.mjcf import build_mjcf
    from kinematics.picture import render_head
    from kinematics.summary import summarize, summary_markdown

    head = context.setdefault("head", reference_head())
    cam = context.setdefault("camera", default_camera())
    save_head(head, out / "head.toml")
    save_camera(cam, out / "camera.toml")
    (out / "head.xml").write_text(build_mjcf(head, cam))
    s = summarize(head, n_directions=1000)
    (out / "summary.json").write_text(json.dumps(s, indent=2))
    (out / "summary.md").write_text(summary_markdown(s))
    postures = np.radians([[0, 0, 0], [35, 50, 20], [-30, -60, -25]])
    render_head(head, out / "head.png", postures)
    rel = out.name
    return "\n".join([
        f"The `{head.name}` head (elevation, pan, cyclotorsion; HS-50 servos). "
        f"Files: [head.toml]({rel}/head.toml), [head.xml]({rel}/head.xml) (MJCF), "
        f"[camera.toml]({rel}/camera.toml), [summary.md]({rel}/summary.md), [summary.json]({rel}/summary.json).",
        "",
        f"![head at rest and two postures]({rel}/head.png)",
        "",
        summary_markdown(s).split("\n", 2)[2],
    ])


def stage_placement(out: Path, context: dict) -> str:
    """Camera placement on the default body with fewer rays; its mount.toml flows to the twin."""
    from placement.mapping import placement_map
    from placement.scores import ScoreSettings

    r = placement_map(out, settings=ScoreSettings(rays=256, motion_frames=15), progress=False)
    if r.zones.mount_zone is not None:
        context["mount"] = out / "mount.toml"
    rel = out.name
    maps = " ".join(f"![{k}]({rel}/{v})" for k, v in r.maps.items() if k in ("fov", "combined"))
    zones = r.zones.markdown().split("\n", 2)[2]
    return "\n".join([
        f"{r.polygons} places on a {r.stature_m:.2f} m body, {r.rays} rays each over the poses "
        f"{', '.join(r.poses)}; motions {', '.join(r.motions)}. "
        f"Files: [scores.csv]({rel}/scores.csv), [zones.md]({rel}/zones.md), [mount.toml]({rel}/mount.toml), "
        + ", ".join(f"[{k} map]({rel}/{v})" for k, v in r.maps.items()) + ".", "", maps, "", zones])


def _twin(out: Path, context: dict):
    """A twin with the head and mount the earlier stages chose (the objects themselves)."""
    from wvr.assemble import make_twin

    mount = context.get("mount")
    return make_twin(context.get("head") or reference_head(), mount if mount and Path(mount).exists() else None)


def stage_twin(out: Path, context: dict) -> str:
    """A short workbench-static recording of the chosen head on the chosen mount."""
    from runtime.sequence import open_sequence
    from runtime.twin.recorder import record

    mount = context.get("mount")
    twin = _twin(out, context)
    try:
        seq_dir = record(twin, "workbench-static", out / "workbench-static", seconds=3.0, seed=0, progress=False)
    finally:
        twin.close()
    context["sequence"] = seq_dir
    seq = open_sequence(seq_dir)
    rel = f"{out.name}/{seq_dir.name}"
    shutil.copy(seq.paths[0], out / "first_frame.png")
    return "\n".join([
        f"{len(seq)} frames of `workbench-static` (640x480, 30 Hz), the chosen head on the "
        f"{'chosen' if mount else 'default shoulder'} mount. Sequence folder: [{seq_dir.name}]({rel}/rgb.txt) "
        f"with [groundtruth.txt]({rel}/groundtruth.txt), [imu.txt]({rel}/imu.txt), [joints.txt]({rel}/joints.txt), "
        f"[camera.toml]({rel}/camera.toml), [target.toml]({rel}/target.toml).", "",
        f"![first frame]({out.name}/first_frame.png)"])


def stage_slam(out: Path, context: dict) -> str:
    """MonoSLAM on the twin's recording, evaluated against its ground truth."""
    from runtime.sequence import open_sequence, read_trajectory
    from runtime.eval import trajectory_errors
    from runtime.slam.run import run_slam

    seq = context.get("sequence")
    if seq is None:
        raise StageFailed("no recording to run on (the twin stage failed)")
    r = run_slam(seq, out, video=False, progress=False)
    if r.lost:
        raise StageFailed(f"the track was lost ({r.lost_frames} of {r.frames} frames)")
    e = trajectory_errors(read_trajectory(out / "trajectory.tum"), open_sequence(seq).groundtruth)
    rel = out.name
    return "\n".join([
        f"{r.frames} frames, {r.features} features in the final map, {r.mean_matched:.1f} "
        f"matched per frame, {r.median_ms_per_frame:.1f} ms per frame{', track LOST' if r.lost else ''}. "
        f"Files: [trajectory.tum]({rel}/trajectory.tum), [map.csv]({rel}/map.csv), [stats.json]({rel}/stats.json).", "",
        f"- ATE without alignment (the target fixes the frame): RMSE {100 * e.ate_rmse_m:.2f} cm, "
        f"max {100 * e.ate_max_m:.2f} cm",
        f"- ATE after SE(3) alignment: RMSE {100 * e.ate_aligned_rmse_m:.2f} cm",
        f"- RPE over 1 s: {100 * e.rpe_trans_rmse_m:.2f} cm, {e.rpe_rot_rmse_deg:.2f} deg"])


def stage_gaze(out: Path, context: dict) -> str:
    """Closed loop: the chosen head fixates the target while the wearer walks towards it, the
    controller seeing only SLAM (images), the IMU and the encoders."""
    from runtime.apps.closed_loop import Task
    from runtime.twin.scenarios import get_scenario
    from wvr.assemble import run_on_twin

    sc = get_scenario("walk-ahead")
    target = sc.bench.target_corners().mean(axis=0)
    twin = _twin(out, context)
    try:
        s = run_on_twin(twin, sc, Task("fixate", target[None]), out, seconds=4.0, progress=False)
    except ValueError as e:       # e.g. the chosen head cannot see the target from this mount
        raise StageFailed(f"the closed loop could not run with the chosen head and mount: {e}") from e
    finally:
        twin.close()
    rel = out.name
    lines = [f"`walk-ahead`, {s['seconds']:.1f} s: fixate the target's centre {np.round(target, 3).tolist()} m while "
             f"walking towards it, controlled-motion limit {s['motion_limit_deg_s']:.0f} deg/s.", ""]
    if "fixation_rms_deg" in s:
        lines.append(f"- fixation error after the first second (true): RMS {s['fixation_rms_deg']:.2f} deg, "
                     f"peak {s['fixation_peak_deg']:.2f} deg")
    lines += [f"- SLAM in the loop: ATE RMSE {100 * s['ate_rmse_m']:.2f} cm, {s['lost_frames']} frames lost",
              f"- peak commanded joint rate {s['peak_cmd_rate_deg_s']:.1f} deg/s; {s['prompts']} wearer prompts, "
              f"{len(s['refusals'])} refusals",
              "", f"Files: [report.md]({rel}/report.md), [joints.csv]({rel}/joints.csv), "
              f"[trajectory.tum]({rel}/trajectory.tum), [groundtruth.txt]({rel}/groundtruth.txt).", "",
              f"![fixation error]({rel}/fixation_error.png)"]
    return "\n".join(lines)


def stage_stabilise(out: Path, context: dict) -> str:
    """Stabilisation with a software fovea on a short sit-down recording (IMU-aided)."""
    from runtime.twin.recorder import record
    from runtime.vision2d.stabilise import stabilise_sequence

    twin = _twin(out, context)
    try:
        seq = record(twin, "sit-down", out / "sit-down", seconds=3.0, seed=0, progress=False)
    finally:
        twin.close()
    s = stabilise_sequence(seq, out / "stabilised", use_imu=True, progress=False)
    rel = f"{out.name}/stabilised"
    lines = [f"3 s of `sit-down`, fovea {s.fovea[0]}x{s.fovea[1]}, gyro-predicted and vision-measured rotation: "
             f"{s.frames} frames, {s.flagged} flagged, {s.clamped} with the fovea at the image edge.", ""]
    if s.rotation_rms_error_deg is not None:
        lines.append(f"- inter-frame rotation against the truth: RMS {s.rotation_rms_error_deg:.3f} deg, "
                     f"max {s.rotation_max_error_deg:.3f} deg")
    lines += [f"- background motion: raw {s.raw_motion_px:.2f} px/frame, fovea {s.fovea_motion_px:.2f} "
              f"(ratio {s.motion_ratio:.2f}; the head already holds its gaze, so what is left is mostly parallax)",
              "", f"Files: [report.md]({rel}/report.md), [rotations.tum]({rel}/rotations.tum), [fovea.csv]({rel}/fovea.csv)."]
    return "\n".join(lines)


def stage_planar_tracking(out: Path, context: dict) -> str:
    """The planar tracker (hyperplane approximation) on the twin's hand-held card, a quarter of
    it occluded from 1 s, started from the card's corners in the first frame (what a user would
    click); its corners scored against the card's true corners."""
    from kinematics.camera import project
    from runtime.sequence import open_sequence
    from runtime.twin.recorder import record
    from runtime.twin.scenarios import get_scenario
    from runtime.vision2d.track import track_sequence

    scenario = get_scenario("workbench-card")
    twin = _twin(out, context)
    try:
        seq_dir = record(twin, scenario, out / "workbench-card", seconds=1.8, seed=0, progress=False)
    except ValueError as e:       # e.g. the card is not in view from the chosen head and mount
        raise StageFailed(f"the card could not be recorded with the chosen head and mount: {e}") from e
    finally:
        twin.close()
    seq = open_sequence(seq_dir)
    T = seq.groundtruth.interpolate(seq.timestamps).T_world_cam()      # truth: for scoring only
    truth = np.array([project(seq.camera, (scenario.card_corners(t) - T[i, :3, 3]) @ T[i, :3, :3])
                      for i, t in enumerate(seq.timestamps)])
    r = track_sequence(seq_dir, out / "tracked", init=truth[0], method="hyperplane", progress=False)
    rows = np.genfromtxt(out / "tracked" / "polygons.csv", delimiter=",", skip_header=1)
    poly = rows[:, 1:9].reshape(-1, 4, 2)
    ok = rows[:, 9] == 0
    err = np.sqrt(np.mean(np.sum((poly[ok] - truth[ok]) ** 2, axis=2), axis=1))
    occluded = np.asarray(seq.timestamps)[ok] >= 1.0
    rel = f"{out.name}/tracked"
    lines = [f"{r.frames} frames of `workbench-card` (the card moved by hand, the camera following it), tracked from "
             f"its corners in the first frame: {r.tracked} tracked, {r.lost_frames} lost, "
             f"{r.tracking_fps or 0:.0f} frames/s after {r.learn_seconds:.2f} s of learning.", ""]
    for label, sel in (("before the occluder", ~occluded), ("a quarter occluded", occluded)):
        if sel.any():
            lines.append(f"- corner error against the true corners, {label}: RMS {np.sqrt(np.mean(err[sel] ** 2)):.2f} px, "
                         f"max {err[sel].max():.2f} px")
    lines += ["", f"Files: [polygons.csv]({rel}/polygons.csv), [stats.json]({rel}/stats.json), "
                  f"[first annotated frame]({rel}/annotated/000000.png).", "",
              f"![the last frame]({rel}/annotated/{len(seq) - 1:06d}.png)"]
    return "\n".join(lines)


def stage_head_tracking(out: Path, context: dict) -> str:
    """The head tracker on a rendered head turning in yaw, pitch and roll, and the joint targets
    that slave the chosen head to it (gaze.slaving); errors against the rendered poses."""
    import math

    import cv2

    from kinematics.camera import CameraIntrinsics
    from runtime.gaze.slaving import head_to_joint_targets
    from runtime.vision2d.headscene import render_head_sequence, smooth_head_motion
    from runtime.vision2d.headtrack import HeadTracker

    head = context.get("head") or reference_head()
    cam = CameraIntrinsics(width=320, height=240, fx=257.35, fy=257.35, cx=159.5, cy=119.5)
    ypr = smooth_head_motion(60, math.radians(40), math.radians(20), math.radians(8))
    images, T_true, cam = render_head_sequence(ypr, 0.6, seed=0, camera=cam)
    tracker = HeadTracker(cam)
    results = tracker.track(images, T_true[0])            # started at the known frontal pose
    ok = np.array([not r.lost for r in results])
    est = np.array([r.ypr for r in results])
    err = np.degrees(est[ok] - ypr[ok])
    q = np.array([head_to_joint_targets(e, limits=head) for e in est[ok]])
    with open(out / "poses.csv", "w") as f:
        f.write("frame,lost,yaw_deg,pitch_deg,roll_deg,true_yaw_deg,true_pitch_deg,true_roll_deg,"
                "q_elevation_deg,q_pan_deg,q_cyclotorsion_deg\n")
        k = 0
        for i, r in enumerate(results):
            qi = np.degrees(q[k]) if ok[i] else np.full(3, np.nan)
            k += int(ok[i])
            f.write(",".join([str(i), str(int(r.lost))] + [f"{v:.3f}" for v in
                              (*np.degrees(r.ypr), *np.degrees(ypr[i]), *qi)]) + "\n")
    cv2.imwrite(str(out / "first_frame.png"), cv2.cvtColor(images[0], cv2.COLOR_RGB2BGR))
    rms = np.sqrt(np.mean(err ** 2, axis=0)) if len(err) else np.full(3, np.nan)
    rel = out.name
    return "\n".join([
        f"{len(results)} rendered frames (320x240, head 0.6 m away) turning within +-40 deg yaw, +-20 pitch, +-8 roll, "
        f"tracked from the known frontal pose: {int((~ok).sum())} lost, {len(tracker.keyframes)} keyframes.", "",
        f"- RMS error against the rendered poses: yaw {rms[0]:.2f}, pitch {rms[1]:.2f}, roll {rms[2]:.2f} deg",
        f"- slaving the `{head.name}` head: joint targets (elevation, pan, cyclotorsion) up to "
        f"{', '.join(f'{v:.0f}' for v in np.degrees(np.abs(q).max(axis=0)))} deg, within its ranges", "",
        f"Files: [poses.csv]({rel}/poses.csv).", "", f"![first frame]({rel}/first_frame.png)"])


def _wait_twin_time(station, t: float, timeout: float = 120.0) -> None:
    t0 = time.time()
    while (station.live.latest() is None or station.live.latest().t < t) and not station.live.finished.is_set():
        if time.time() - t0 > timeout:
            raise TimeoutError(f"the station's loop did not reach {t} s of twin time")
        time.sleep(0.05)


def stage_station(out: Path, context: dict) -> str:
    """The remote operator's station on the twin: a scripted operator session through the JSON
    API (saccades to the target's corners, a label, a box, refusals, the latched stop), a
    screenshot of the page from the headless browser, the recording; the saccades scored on the
    twin's truth (true optic axis against the true corner)."""
    import math

    from runtime.apps.station import Station
    from runtime.apps.station.browser import headless_browser
    from runtime.apps.station.client import StationClient
    from runtime.twin.scenarios import get_scenario
    from wvr.assemble import clicked_target, safe_twin

    twin = _twin(out, context)
    twin.configure(get_scenario("workbench-static"), seed=0, seconds=60.0)
    st = Station(safe_twin(twin), lambda obs: clicked_target(twin, seed=0), port=0, out=out / "session", truth=twin,
                 seconds=60.0, on_finish=twin.close, notes={"scenario": "workbench-static", "seed": 0})
    calls, scores = [], []
    try:
        st.open()
        st.wait_started()
        corners_true = twin.landmarks()["target_corners"]      # scoring only
        api = StationClient(st.public_url, st.token)

        def do(what, reply):
            calls.append((what, reply.status, "accepted" if reply.accepted else reply.body.get("reason", "")))
            return reply

        _wait_twin_time(st, 1.5)
        known = [f for f in api.state()["features"] if f["known"]]
        for k, f in enumerate(known[:3]):
            r = do(f"fixate feature {f['id']} (a target corner)", api.fixate(feature=f["id"]))
            if r.accepted:
                t_click = r.body["t"]
                _wait_twin_time(st, t_click + 2.5)
                i = int(np.searchsorted(st.live.run.times, t_click + 2.5))
                T = st.live.run.T_true[min(i, len(st.live.run.T_true) - 1)]
                p = corners_true[np.argmin(np.linalg.norm(corners_true - np.array(f["xyz"]), axis=1))]
                d = p - T[:3, 3]
                scores.append((f["id"], math.degrees(math.acos(np.clip(T[:3, 2] @ d / np.linalg.norm(d), -1, 1)))))
            if k == 0:
                do(f"label feature {f['id']} 'corner A'", api.label("corner A", feature=f["id"]))
                centre = np.mean([g["xyz"] for g in known], axis=0).tolist()
                do("box at the target's centre", api.add_object("box", xyz=centre, size=[0.05, 0.05, 0.05]))
                do("fixate [NaN, 0, 0]", api.raw("POST", "/api/fixate", {"xyz": [float("nan"), 0, 0]}))
                do("fixate feature 99999", api.fixate(feature=99999))
                do("stop", api.stop("demo"))
                do(f"fixate feature {f['id']} while stopped", api.fixate(feature=f["id"]))
                do("reset", api.reset())
        with headless_browser() as ctx:
            page = ctx.new_page()
            page.goto(st.url)
            page.wait_for_function("window.station && window.station.frames >= 2", timeout=120_000)
            page.frame_locator("#view3d").locator("canvas").first.wait_for(timeout=120_000)
            time.sleep(3.0)                                      # the 3D view's scene arrives
            page.screenshot(path=str(out / "station.png"))
        st.stop("demo script done")
        st.wait(60)
    except ValueError as e:       # e.g. the chosen head cannot see the target from this mount
        raise StageFailed(f"the station could not run with the chosen head and mount: {e}") from e
    finally:
        written = st.close()
    rel = out.name
    rows = "\n".join(f"| {w} | {c} | {res} |" for w, c, res in calls)
    lines = [f"`wvr station --scenario workbench-static`: {len(st.live.run.times)} periods; the operator (a script) "
             "drove it through the JSON API, the page shown in headless Chromium.", "",
             "| call | HTTP | result |", "|---|---|---|", rows, ""]
    for fid, err in scores:
        lines.append(f"- saccade to feature {fid}: 2.5 s after the click the true optic axis is {err:.2f} deg "
                     "from the true corner")
    lines += ["", f"Files: [session/]({rel}/session/events.csv) ({', '.join(written)}).", "",
              f"![the station's page]({rel}/station.png)"]
    return "\n".join(lines)


#: (folder, title, function) in pipeline order.
STAGES: list[tuple[str, str, Callable[[Path, dict], str]]] = [
    ("design", "Design: Pareto optimisation of the head's layout", stage_design),
    ("kinematics", "Head kinematics of the chosen head", stage_kinematics),
    ("placement", "Placement: where on the body to wear it", stage_placement),
    ("twin", "Twin: a recording in the workbench scene", stage_twin),
    ("slam", "SLAM: MonoSLAM on the recording", stage_slam),
    ("gaze", "Gaze control: closed-loop fixation while walking", stage_gaze),
    ("stabilise", "Stabilisation: a software fovea on the sit-down recording", stage_stabilise),
    ("planar-tracking", "Planar tracking: the hand-held card, a quarter occluded", stage_planar_tracking),
    ("head-tracking", "Head tracking and slaving", stage_head_tracking),
    ("station", "The remote operator's station: a scripted session through the API", stage_station),
]


def run_demo(out: Path, stages=None) -> DemoResult:
    """Run all stages (or ``stages``, as :data:`STAGES`) into ``out`` (an output folder:
    INCOMPLETE until the report is written); returns report.md's path and the failed stages."""
    from kinematics.outdir import output_folder

    context: dict = {}
    failed: list[str] = []
    sections = ["# wvr demo", "",
                "Every stage of the pipeline that exists, in order, with small budgets "
                "(Mayol, Davison, Tordoff, Murray: *Applying Active Vision and SLAM to Wearables*).", ""]
    with output_folder(out, kind="demo") as out:
        for folder, title, fn in progress_bar(STAGES if stages is None else stages, desc="wvr demo", unit="stage"):
            d = out / folder
            if d.exists():          # the demo owns its folders: every run starts afresh
                shutil.rmtree(d)
            d.mkdir()
            t0 = time.perf_counter()
            try:
                body = fn(d, context)
            except Exception as e:      # the report records it; the later stages still run
                failed.append(title)
                body = f"**FAILED**: {e}" if isinstance(e, StageFailed) else f"**FAILED** ({type(e).__name__}): {e}"
            sections += [f"## {title}", "", body, "", f"*Stage time: {time.perf_counter() - t0:.1f} s*", ""]
        if failed:
            sections[4:4] = [f"**{len(failed)} stage(s) FAILED**: {', '.join(failed)}.", ""]
        report = out / "report.md"
        report.write_text("\n".join(sections))
    return DemoResult(report, failed)
