"""The ``wvr`` command: one subcommand group per package, each a thin wrapper over its API.

Bad input never produces a traceback: the packages raise exceptions whose messages say what is
wrong and how to fix it, and :func:`main` prints that one line and exits with status 2.
"""

from __future__ import annotations

import os

# Headless by default: MuJoCo and VTK render offscreen through EGL unless told otherwise.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import argparse  # noqa: E402
import json
import sys
from pathlib import Path

import numpy as np

from kinematics import HeadFileError, ServoCommandError, gaze_at_direction, gaze_at_point, load_head
from kinematics.camera import CameraFileError, default_camera, load_camera

# Every package's bad-input exception derives from ValueError and carries a one-line message.
USER_ERRORS = (HeadFileError, CameraFileError, ServoCommandError, FileNotFoundError, ValueError)


def _vector(text: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not X,Y,Z (three comma-separated numbers, metres)") from None
    if v.shape != (3,):
        raise argparse.ArgumentTypeError(f"{text!r} must have three components X,Y,Z")
    return v


def cmd_kinematics_show(args) -> int:
    from kinematics.summary import summarize, summary_markdown

    head = load_head(args.head)
    s = summarize(head, n_directions=args.directions)
    print(json.dumps(s, indent=2) if args.json else summary_markdown(s))
    return 0


def cmd_kinematics_mjcf(args) -> int:
    from kinematics.mjcf import build_mjcf

    head = load_head(args.head)
    cam = load_camera(args.camera) if args.camera else default_camera()
    sys.stdout.write(build_mjcf(head, cam))
    return 0


def cmd_kinematics_ik(args) -> int:
    head = load_head(args.head)
    q0 = np.radians(args.current) if args.current is not None else np.zeros(3)
    solve = gaze_at_point if args.point else gaze_at_direction
    res = solve(head, args.target, args.up, q_current=q0)
    if not res.reachable:
        print(f"unreachable: {res.reason}")
        return 1
    for s in res.solutions:
        print("q_deg = " + ", ".join(f"{v:.4f}" for v in np.degrees(s.q)) + f"   (sigma_min {s.sigma_min:.3f})")
    if not res.vertical_defined:
        print("note: target within the zenith cone; cyclotorsion held, image vertical undefined")
    if res.near_singular:
        print("warning: near-singular posture; following a moving target here needs large rates")
    return 0


def cmd_kinematics_picture(args) -> int:
    from kinematics.picture import render_head

    head = load_head(args.head)
    out = render_head(head, args.out, postures=np.radians(np.array(args.posture)) if args.posture else None)
    print(f"wrote {out}")
    return 0


def cmd_design_optimise(args) -> int:
    from design.report import write_outputs
    from design.sweep import open_client, run_sweep
    from design.sweep_file import load_sweep

    spec = load_sweep(args.sweep)
    out = Path(args.out)
    client = open_client(args.workers, args.scheduler)
    try:
        result = run_sweep(spec, out, evaluations=args.evaluations, seed=args.seed, algorithm=args.algorithm,
                           resume=args.resume, client=client)
    finally:
        if client is not None:
            client.close()
    s = write_outputs(result, spec, out)
    print(f"{s['evaluations']} evaluations ({result.evaluated} computed now, {result.reused} reused), "
          f"{s['feasible']} feasible, front of {s['front_size']}")
    if s.get("chosen") is not None or "chosen_index" in s:
        print(f"chosen head: {out / 'chosen_head.toml'}; report: {out / 'report.md'}")
    else:
        print(f"no feasible design; see {out / 'report.md'}")
    return 0


def cmd_design_evaluate(args) -> int:
    from design.problem import EvaluationContext, score_head
    from design.sweep_file import load_sweep

    ctx = EvaluationContext.from_spec(load_sweep(args.sweep))
    crit, cons = score_head(load_head(args.head), ctx)
    for k, v in {**crit, **cons}.items():
        print(f"{k:24s} {v:.6g}")
    return 0


def cmd_design_template(args) -> int:
    from design.sweep_file import default_sweep_text

    sys.stdout.write(default_sweep_text())
    return 0


def cmd_placement_map(args) -> int:
    from placement.body import make_body
    from placement.io import load_body, load_bvh
    from placement.mapping import placement_map
    from placement.motions import default_motions
    from placement.scores import ScoreSettings

    if (args.body is None) != (args.joints is None):
        raise ValueError("--body and --joints go together: a labelled mesh and its joints JSON")
    body = load_body(args.body, args.joints) if args.body else make_body(args.stature)
    motions = [load_bvh(p, body) for p in args.motion] if args.motion else default_motions(body)
    for m in motions:
        if m.unmapped:
            print(f"{m.name}: joints not driving any segment: {', '.join(m.unmapped)}")
    settings = ScoreSettings(rays=args.rays, standoff_m=args.standoff)
    s = placement_map(args.out, body, motions, settings)
    print(f"scored {s['polygons']} places; maps, scores.csv, zones.md and mount.toml in {args.out}")
    for r in s["zones"]:
        if r["polygons"]:
            print(f"  {r['zone']:9s} fov {r['fov']:.3f}  handling {r['handling_view']:.3f}  motion {r['motion_mm']:.0f} mm  "
                  f"combined {r['combined']:.3f}  ({r['frame']}, acceptability {r['acceptability']})")
    return 0


def wearer_for(scenario, seconds: float):
    """The twin's wearer for a scenario: the placement body posed by the named placement motion,
    placed in the world where the scenario says (the twin never imports placement itself)."""
    from placement import motions
    from placement.body import SEGMENTS, make_body
    from runtime.twin.wearer import Wearer

    body = make_body()
    if scenario.motion == "stand":
        m = motions.stand(body, seconds)
    elif scenario.motion == "walk":
        m = motions.walk(body, seconds, speed_m_s=scenario.walk_speed_m_s, cycle_s=1.2)
    elif scenario.motion == "sit-down":
        m = motions.sit_down(body, seconds)
    else:
        raise ValueError(f"scenario motion {scenario.motion!r} is not one of stand, walk, sit-down")
    G = scenario.T_world_body() @ body.segment_transforms(m)
    return Wearer(SEGMENTS, body.vertices, body.faces, body.face_segment, body.joints, m.t, G)


def make_twin(head_path=None, mount_path=None, camera_path=None, ideal_imu: bool = False, ideal_camera: bool = False):
    """A Twin with the chosen (or reference) head, the chosen (or default shoulder) mount; a
    real IMU's errors (BMI088) and a real camera's blur, exposure and noise unless ``ideal_*``."""
    from kinematics import reference_head
    from runtime.twin.mount import default_shoulder_mount, load_mount
    from runtime.twin.twin import Twin

    head = load_head(head_path) if head_path else reference_head()
    mount = load_mount(mount_path) if mount_path else default_shoulder_mount
    cam = load_camera(camera_path) if camera_path else default_camera()
    options = {}
    if ideal_imu:
        options["imu"] = None
    if ideal_camera:
        options["camera_sensor"] = None
    return Twin(head, cam, mount, wearer_for, **options)


def cmd_sim_record(args) -> int:
    from dataclasses import replace

    from runtime.twin.recorder import record
    from runtime.twin.scenarios import get_scenario

    scenario = get_scenario(args.scenario)
    if args.dim_to is not None:
        if not 0.0 <= args.dim_to <= 1.0:
            raise ValueError(f"--dim-to {args.dim_to}: give the final light level as a fraction 0..1")
        scenario = replace(scenario, dim_to=args.dim_to)
    for flag, v in (("--seed", args.seed), ("--scene-seed", args.scene_seed)):
        if v is not None and v < 0:
            raise ValueError(f"{flag} {v}: give a seed of 0 or more")
    if not (np.isfinite(args.click_error) and 0.0 <= args.click_error <= 50.0):
        raise ValueError(f"--click-error {args.click_error}: give the operator's click error in pixels, 0 to 50")
    twin = make_twin(args.head, args.mount, args.camera, ideal_imu=args.ideal_imu, ideal_camera=args.ideal_camera)
    try:
        out = record(twin, scenario, args.out, seconds=args.seconds, seed=args.seed, depth=args.depth,
                     scene_seed=args.scene_seed, click_error_px=args.click_error)
    finally:
        twin.close()
    print(f"recorded {args.scenario} (seed {args.seed}, scene seed {twin.scene_seed}) into {out}")
    return 0


def cmd_sim_run(args) -> int:
    import math

    from runtime.gaze import ControllerSettings
    from runtime.twin.loop import Task, load_targets, run_closed_loop
    from runtime.twin.scenarios import get_scenario

    scenario = get_scenario(args.scenario)
    targets = [np.asarray(t, float) for t in (args.target or [])]
    dwell = args.dwell
    if args.targets:
        pts, file_dwell = load_targets(args.targets)
        targets += list(pts)
        dwell = file_dwell or dwell
    if not targets and args.task == "fixate":
        targets = [scenario.bench.target_corners().mean(axis=0)]
    if any(np.shape(t) != (3,) for t in targets):
        raise ValueError("--target takes three numbers X,Y,Z (world frame, m)")
    region = None
    if getattr(args, "init", None) is not None:
        if np.shape(args.init) != (4,):
            raise ValueError("--init takes four numbers X,Y,W,H (pixels in the first frame)")
        region = tuple(float(v) for v in args.init)
    task = Task(args.task, np.array(targets).reshape(-1, 3), dwell_s=dwell, region=region,
                method=getattr(args, "method", "hyperplane"))
    settings = ControllerSettings(motion_limit_rad_s=math.radians(args.limit))
    twin = make_twin(args.head, args.mount, args.camera)
    try:
        s = run_closed_loop(twin, scenario, task, args.out, seconds=args.seconds, seed=args.seed, settings=settings)
    finally:
        twin.close()
    print(Path(args.out, "report.md").read_text().split("![")[0].strip())
    print(f"wrote {args.out}: groundtruth.txt, trajectory.tum, task.toml, joints.csv, prompts.csv, report.md")
    return 0 if not s["refusals"] else 1


def cmd_stabilise(args) -> int:
    from runtime.vision2d.stabilise import stabilise_sequence

    fovea = _size(args.fovea, "--fovea")
    totals = stabilise_sequence(args.seq, args.out, fovea=fovea, use_imu=args.imu)
    print(json.dumps(totals, indent=1))
    print(f"wrote {Path(args.out) / 'rotations.tum'}, fovea/, report.md")
    return 0


def _size(text: str, flag: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"{flag} {text!r}: give the size as WxH in pixels, e.g. 320x240") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"{flag} {text!r}: width and height must be positive")
    return w, h


def cmd_track(args) -> int:
    if args.servo:
        # The closed loop: the twin's head keeps the tracked target centred (gaze track mode).
        if not args.scenario:
            raise ValueError("--servo runs the closed loop in the twin: give --scenario NAME (and no SEQ)")
        args.task, args.target, args.targets, args.dwell, args.limit = "track", None, None, 2.0, 30.0
        return cmd_sim_run(args)
    if not args.seq:
        raise ValueError("give the sequence folder SEQ (or --servo --scenario NAME for the closed loop)")
    if args.init is None or np.shape(args.init) != (4,):
        raise ValueError("--init X,Y,W,H is required: the target's box in the first frame, pixels")
    from runtime.vision2d.track import track_sequence

    totals = track_sequence(args.seq, args.out, init=tuple(float(v) for v in args.init), method=args.method)
    print(json.dumps(totals, indent=1))
    print(f"wrote {Path(args.out) / 'polygons.csv'}, annotated/, stats.json")
    return 0


def cmd_slam(args) -> int:
    from runtime.slam.run import run_slam

    from dataclasses import replace

    from runtime.slam.system import MapSettings

    settings = replace(MapSettings(), use_imu=not args.no_imu, bias_time_s=args.imu_bias_time)
    totals = run_slam(args.seq, args.out, max_frames=args.max_frames, video=args.video, settings=settings)
    print(f"{totals['frames']} frames ({totals['skipped']} skipped), {totals['features']} features in the map, "
          f"{totals['mean_matched']:.1f} matched per frame, {totals['mean_ms_per_frame']:.1f} ms per frame"
          + ("; track was LOST for " + str(totals["lost_frames"]) + " frames" if totals["lost"] else ""))
    print(f"wrote {Path(args.out) / 'trajectory.tum'}, map.csv, stats.json")
    return 0


def cmd_eval(args) -> int:
    from runtime.sequence import open_sequence, read_trajectory
    from runtime.slam.eval import trajectory_errors

    seq = open_sequence(args.seq)
    if seq.groundtruth is None:
        raise ValueError(f"{args.seq}: no groundtruth.txt to evaluate against")
    e = trajectory_errors(read_trajectory(Path(args.result) / "trajectory.tum"), seq.groundtruth)
    print(f"poses matched: {e.matched}")
    print(f"ATE (no alignment): RMSE {100 * e.ate_rmse_m:.2f} cm, max {100 * e.ate_max_m:.2f} cm")
    print(f"ATE (SE3-aligned):  RMSE {100 * e.ate_aligned_rmse_m:.2f} cm, max {100 * e.ate_aligned_max_m:.2f} cm")
    print(f"RPE over {e.rpe_delta_s:g} s: {100 * e.rpe_trans_rmse_m:.2f} cm, {e.rpe_rot_rmse_deg:.2f} deg RMSE")
    if seq.depth_paths is not None and (Path(args.result) / "map.csv").exists():
        from runtime.slam.eval import map_errors

        m = map_errors(seq, Path(args.result) / "map.csv")
        print(f"map against the true depth: {len(m.errors_m)} features, RMSE {100 * m.rmse_m:.2f} cm, "
              f"median {100 * m.median_m:.2f} cm")
    return 0


def cmd_demo(args) -> int:
    from wvr.demo import run_demo

    report = run_demo(Path(args.out))
    print(f"wrote {report}")
    return 0


def _twin_options(p: argparse.ArgumentParser, scenarios, required: bool = True, when: str = "") -> None:
    """The options every twin run takes (record, closed loop, tracking servo): scenario,
    duration, seed, and the head, mount and camera files. ``when`` prefixes their help."""
    p.add_argument("--scenario", required=required, choices=sorted(scenarios), help=f"{when}the twin scenario")
    p.add_argument("--seconds", type=float, help=f"{when}duration (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0,
                   help=f"{when}run seed: motion variation and sensor noise, and the place (textures, layout)")
    p.add_argument("--head", help=f"{when}head.toml (default: the reference head)")
    p.add_argument("--mount", help=f"{when}mount.toml from wvr placement map (default: on the right shoulder)")
    p.add_argument("--camera", help=f"{when}camera.toml (default: 640x480, f = 514.7 px)")


def build_parser() -> argparse.ArgumentParser:
    from runtime.twin.scenarios import SCENARIOS, TASKS
    from runtime.vision2d.track import METHODS

    p = argparse.ArgumentParser(
        prog="wvr",
        description="wvr: design, place and run an active wearable camera (Mayol, Davison, Tordoff, Murray).",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    kin = sub.add_parser("kinematics", help="the head: chain summary, MJCF model, gaze IK, picture")
    ksub = kin.add_subparsers(dest="kinematics_command", metavar="SUBCOMMAND", required=True)
    show = ksub.add_parser("show", help="print the chain, masses, radii, torques and gaze coverage of a head")
    show.add_argument("head", help="head.toml, or 'reference'")
    show.add_argument("--json", action="store_true", help="print JSON instead of Markdown")
    show.add_argument("--directions", type=int, default=2000, help="gaze directions sampled for coverage")
    show.set_defaults(func=cmd_kinematics_show)
    mj = ksub.add_parser("mjcf", help="write the head's MJCF model to standard output")
    mj.add_argument("head", help="head.toml, or 'reference'")
    mj.add_argument("--camera", help="camera.toml with the intrinsics (default: 640x480, f=514.7 px)")
    mj.set_defaults(func=cmd_kinematics_mjcf)
    ik = ksub.add_parser("ik", help="joint angles that fixate a direction or point (mount frame), image upright")
    ik.add_argument("head", help="head.toml, or 'reference'")
    ik.add_argument("--target", type=_vector, required=True, help="X,Y,Z direction (or point with --point), mount frame")
    ik.add_argument("--point", action="store_true", help="the target is a 3D point in metres, not a direction")
    ik.add_argument("--up", type=_vector, default=np.array([0.0, 0.0, 1.0]), help="world up in the mount frame")
    ik.add_argument("--current", type=_vector, help="current joint angles, degrees")
    ik.set_defaults(func=cmd_kinematics_ik)
    pic = ksub.add_parser("picture", help="render the head to a PNG (offscreen)")
    pic.add_argument("head", help="head.toml, or 'reference'")
    pic.add_argument("--out", required=True, help="PNG path")
    pic.add_argument("--posture", type=_vector, action="append", help="joint angles in degrees (repeatable)")
    pic.set_defaults(func=cmd_kinematics_picture)

    des = sub.add_parser("design", help="Pareto optimisation of the head's layout (7 criteria)")
    dsub = des.add_subparsers(dest="design_command", metavar="SUBCOMMAND", required=True)
    opt = dsub.add_parser("optimise", help="run (or resume) a design sweep; writes the front and chosen_head.toml")
    opt.add_argument("--sweep", help="sweep.toml (default: the shipped default sweep; see sweep-template)")
    opt.add_argument("--out", required=True, help="output directory")
    opt.add_argument("--evaluations", type=int, help="evaluation budget (default: the sweep file's)")
    opt.add_argument("--seed", type=int, help="random seed (default: the sweep file's)")
    opt.add_argument("--algorithm", choices=["nsga3", "random"], help="default: the sweep file's")
    group = opt.add_mutually_exclusive_group()
    group.add_argument("--workers", type=int, help="evaluate on a local Dask cluster of N worker processes")
    group.add_argument("--scheduler", help="evaluate on an existing Dask cluster, e.g. tcp://HOST:8786")
    opt.add_argument("--resume", action="store_true", help="continue a killed sweep in --out")
    opt.set_defaults(func=cmd_design_optimise)
    ev = dsub.add_parser("evaluate", help="print the 7 criteria and the constraints of a head")
    ev.add_argument("head", help="head.toml, or 'reference'")
    ev.add_argument("--sweep", help="sweep.toml for the workload and settings (default: the default sweep)")
    ev.set_defaults(func=cmd_design_evaluate)
    tpl = dsub.add_parser("sweep-template", help="print the default sweep.toml to start your own")
    tpl.set_defaults(func=cmd_design_template)

    pla = sub.add_parser("placement", help="where on the body to wear the camera: scores, body maps, zones")
    psub = pla.add_subparsers(dest="placement_command", metavar="SUBCOMMAND", required=True)
    pm = psub.add_parser("map", help="score every polygon of a body; write scores.csv, maps, zones.md, mount.toml")
    pm.add_argument("--out", required=True, help="output directory")
    pm.add_argument("--body", help="labelled mesh (OBJ with a group per segment, or PLY with a face label)")
    pm.add_argument("--joints", help="joints JSON for --body: segment name -> joint centre (m)")
    pm.add_argument("--stature", type=float, default=1.75, help="stature of the generated body, m (default 1.75)")
    pm.add_argument("--motion", action="append", help="BVH motion file (repeatable); default: walk, sit, turn, reach")
    pm.add_argument("--rays", type=int, default=2048, help="rays per place for the field of view (default 2048)")
    pm.add_argument("--standoff", type=float, default=0.02, help="camera stand-off from the surface, m (default 0.02)")
    pm.set_defaults(func=cmd_placement_map)

    sim = sub.add_parser("sim", help="the MuJoCo twin: record sequences of the wearer and the head")
    ssub = sim.add_subparsers(dest="sim_command", metavar="SUBCOMMAND", required=True)
    rec = ssub.add_parser("record", help="record a scenario as a sequence (TUM layout, camera.toml, target.toml)")
    rec.add_argument("--out", required=True, help="output sequence folder")
    rec.add_argument("--dim-to", type=float, help="dim the lights linearly to this fraction by the end (e.g. 0.3)")
    rec.add_argument("--depth", action="store_true",
                     help="also write the true depth of every frame (depth.txt, depth/<t>.png, TUM RGB-D)")
    rec.add_argument("--scene-seed", type=int, metavar="S",
                     help="fix the place (textures, object layout) apart from --seed (default: --seed); recordings "
                          "of scenarios in one place with one scene seed show the same place")
    rec.add_argument("--ideal-imu", action="store_true",
                     help="an ideal IMU (white noise only) instead of a BMI088's biases, scale errors and clock offset")
    rec.add_argument("--ideal-camera", action="store_true",
                     help="clean renders: no motion blur, auto-exposure or sensor noise")
    rec.add_argument("--click-error", type=float, default=2.5, metavar="PX",
                     help="how far off the operator clicks the target's corners in target.toml, pixels "
                          "(default 2.5; 0: the exact projection)")
    _twin_options(rec, SCENARIOS)
    rec.set_defaults(func=cmd_sim_record)

    run = ssub.add_parser("run", help="closed loop: twin, SLAM and gaze controller (fixate, saccade, Path A, Path B)")
    run.add_argument("--task", required=True, choices=list(TASKS))
    run.add_argument("--target", action="append", type=_vector, metavar="X,Y,Z",
                     help="world point to fixate or saccade to, m (repeatable; default for fixate: the scenario's "
                          "known rectangle's centre)")
    run.add_argument("--targets", help="TOML file: targets = [[x, y, z], ...] (world, m), optional dwell_s")
    run.add_argument("--dwell", type=float, default=2.0, help="seconds on each saccade target (default 2)")
    run.add_argument("--limit", type=float, default=30.0,
                     help="controlled-motion limit on every joint rate, deg/s (default 30; at most the servos')")
    run.add_argument("--init", type=_vector, metavar="X,Y,W,H",
                     help="track: the region in the first frame, pixels (default: the known rectangle)")
    run.add_argument("--method", choices=METHODS, default="hyperplane", help="track: the 2D tracker")
    run.add_argument("--out", required=True, help="output directory")
    _twin_options(run, SCENARIOS)
    run.set_defaults(func=cmd_sim_run)

    stab = sub.add_parser("stabilise", help="visual (and inertial) stabilisation with a software fovea")
    stab.add_argument("seq", help="sequence folder (TUM layout with camera.toml)")
    stab.add_argument("--out", required=True, help="output directory")
    stab.add_argument("--fovea", default="320x240", help="fovea size WxH, pixels (default 320x240)")
    stab.add_argument("--imu", action="store_true", help="use imu.txt's gyro to predict each frame's rotation")
    stab.set_defaults(func=cmd_stabilise)

    trk = sub.add_parser("track", help="2D object tracking (hyperplane planar tracker or mean shift); --servo in the twin")
    trk.add_argument("seq", nargs="?", help="sequence folder (not with --servo)")
    trk.add_argument("--init", type=_vector, metavar="X,Y,W,H", help="the target's box in the first frame, pixels")
    trk.add_argument("--method", choices=METHODS, default="hyperplane", help="the 2D tracker")
    trk.add_argument("--out", required=True, help="output directory")
    trk.add_argument("--servo", action="store_true",
                     help="closed loop in the twin: the gaze controller keeps the target centred")
    _twin_options(trk, SCENARIOS, required=False, when="with --servo: ")
    trk.set_defaults(func=cmd_track)

    sl = sub.add_parser("slam", help="single-camera EKF SLAM (MonoSLAM) over a sequence folder")
    sl.add_argument("seq", help="sequence folder (TUM layout with camera.toml and target.toml)")
    sl.add_argument("--out", required=True, help="output directory")
    sl.add_argument("--max-frames", type=int, help="stop after N frames")
    sl.add_argument("--video", action="store_true", help="write annotated frames (features, ellipses, particles) and video.mp4")
    sl.add_argument("--no-imu", action="store_true",
                    help="ignore imu.txt (camera only: the constant-velocity motion model)")
    sl.add_argument("--imu-bias-time", type=float, default=0.0, metavar="S",
                    help="estimate the IMU's biases with this time constant, s (default 0: the IMU is calibrated)")
    sl.set_defaults(func=cmd_slam)
    ev2 = sub.add_parser("eval", help="ATE and RPE of a SLAM result against the sequence's ground truth")
    ev2.add_argument("seq", help="sequence folder with groundtruth.txt")
    ev2.add_argument("result", help="the folder wvr slam wrote (trajectory.tum)")
    ev2.set_defaults(func=cmd_eval)

    demo = sub.add_parser("demo", help="run every stage of the pipeline with small budgets; writes DIR/report.md")
    demo.add_argument("--out", required=True, help="output directory")
    demo.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except USER_ERRORS as e:
        print(f"wvr: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
