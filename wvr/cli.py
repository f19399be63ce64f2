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
import contextlib
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

from kinematics import JOINT_NAMES, HeadFileError, ServoCommandError, gaze_at_direction, gaze_at_point, load_head
from kinematics.camera import CameraFileError, default_camera, load_camera
from kinematics.outdir import check_folder, check_output, check_output_file, output_folder

from wvr.assemble import make_twin, wearer_for  # noqa: E402,F401  (the composition root; re-exported)

# Every package's bad-input exception derives from ValueError and carries a one-line message.
from runtime.drivers import DriverError  # noqa: E402
from runtime.robot import MOTION_LIMIT_DEG_S  # noqa: E402
from runtime.safety import EStopLatched  # noqa: E402

USER_ERRORS = (HeadFileError, CameraFileError, ServoCommandError, FileNotFoundError, ValueError, DriverError,
               EStopLatched)
#: A message longer than this is cut: a value echoed from a file can be megabytes long.
MAX_MESSAGE = 400


class _Parser(argparse.ArgumentParser):
    """argparse with the suite's error style: one line and exit status 2, never the usage dump."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}; see '{self.prog} --help'\n")


#: The largest magnitude of a command-line vector's component (m, px or deg): beyond it a
#: product overflows, and nothing in a wearable's world is that far.
MAX_COMPONENT = 1e12


def _numbers(names: tuple[str, ...], unit: str):
    """An argparse type for a comma-separated vector of len(names) finite numbers (names and
    unit say what they are in the message)."""
    form = ",".join(names)

    def parse(text: str) -> np.ndarray:
        try:
            v = np.array([float(x) for x in text.split(",")])
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {form} ({len(names)} comma-separated numbers, "
                                             f"{unit})") from None
        if v.shape != (len(names),):
            raise argparse.ArgumentTypeError(f"{text!r} must have {len(names)} components {form} ({unit})")
        if not np.all(np.isfinite(v)):
            raise argparse.ArgumentTypeError(f"{text!r}: every component of {form} must be a finite number ({unit})")
        if np.max(np.abs(v)) > MAX_COMPONENT:
            raise argparse.ArgumentTypeError(f"{text!r}: every component of {form} must lie within "
                                             f"+-{MAX_COMPONENT:g} ({unit})")
        return v

    parse.__name__ = form   # argparse names the type in some messages
    return parse


_point = _numbers(("X", "Y", "Z"), "metres")
_direction = _numbers(("X", "Y", "Z"), "a direction")
_angles = _numbers(("E", "P", "C"), "degrees: elevation, pan, cyclotorsion")
_box = _numbers(("X", "Y", "W", "H"), "pixels: corner, width, height")
#: Options whose value is a vector: "--target -1.35,-0.6,0.85" must not be read as an option.
_VECTOR_OPTIONS = {"--target", "--up", "--current", "--posture", "--init"}
_NEGATIVE_VECTOR = re.compile(r"-[0-9.][^\s]*,.*")
#: Options whose value is a size WxH: "--fovea -320x240" must reach its own check, not argparse's.
_SIZE_OPTIONS = {"--fovea"}
_NEGATIVE_SIZE = re.compile(r"-[0-9.]+[xX].*")


def _with_negative_vectors(argv: list[str]) -> list[str]:
    """Join a vector option and a value that starts with a minus sign ("--current -10,0,0")
    into one token ("--current=-10,0,0"), which argparse would otherwise take for an option;
    a positional vector (``wvr head goto -10,0,0``) gets a leading space, which argparse does
    not read as an option and float() ignores."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if ((a in _VECTOR_OPTIONS and i + 1 < len(argv) and _NEGATIVE_VECTOR.fullmatch(argv[i + 1]))
                or (a in _SIZE_OPTIONS and i + 1 < len(argv) and _NEGATIVE_SIZE.fullmatch(argv[i + 1]))):
            out.append(f"{a}={argv[i + 1]}")
            i += 2
        elif a == "goto" and i + 1 < len(argv) and _NEGATIVE_VECTOR.fullmatch(argv[i + 1]):
            out += [a, " " + argv[i + 1]]
            i += 2
        else:
            out.append(a)
            i += 1
    return out


def _number(kind: type, test, what: str):
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'a whole number' if kind is int else 'a number'}") \
                from None
        if not (math.isfinite(v) and test(v)):
            raise argparse.ArgumentTypeError(f"{text!r} must be {what}")
        return v

    parse.__name__ = what
    return parse


_positive_int = _number(int, lambda v: v > 0, "a whole number above 0")
#: Gaze directions for show's coverage: a few thousand resolve it; millions only take minutes.
_directions = _number(int, lambda v: 0 < v <= 200_000, "a whole number of directions, 1 to 200000")
#: Seeds and other counts from 0: argparse names the flag in its message ("argument --seed: ...").
_nonneg_int = _number(int, lambda v: v >= 0, "a whole number >= 0")
#: How far off the (simulated) operator clicks, pixels: what sim record has always allowed.
_click_error = _number(float, lambda v: 0 <= v <= 50, "the click error in pixels, 0 to 50")
_positive = _number(float, lambda v: v > 0, "a number above 0")
_nonnegative = _number(float, lambda v: v >= 0, "a number >= 0")
_seconds = _number(float, lambda v: v > 0, "a duration above 0 s")
_milliseconds = _number(float, lambda v: abs(v) < 1000, "a number of ms between -1000 and 1000")


def _short(message: str) -> str:
    return message if len(message) <= MAX_MESSAGE else message[:MAX_MESSAGE - 20] + " ... (message cut)"


def cmd_kinematics_show(args) -> int:
    from kinematics.summary import summarize, summary_markdown

    head = load_head(args.head)
    s = summarize(head, n_directions=args.directions)
    if args.json:
        try:
            text = json.dumps(s, indent=2, allow_nan=False)
        except ValueError:
            raise ValueError(f"{args.head}: the summary holds a non-finite number (a size or position too large "
                             f"to compute with); give the head's sizes and positions in metres") from None
        print(text)
    else:
        print(summary_markdown(s))
    return 0


def cmd_kinematics_mjcf(args) -> int:
    from kinematics.mjcf import build_mjcf

    head = load_head(args.head)
    cam = load_camera(args.camera) if args.camera else default_camera()
    sys.stdout.write(build_mjcf(head, cam))
    return 0


def cmd_kinematics_ik(args) -> int:
    head = load_head(args.head)
    q0 = np.zeros(3)
    if args.current is not None:
        q0 = np.radians(args.current)
        out = np.flatnonzero((q0 < head.lower - 1e-9) | (q0 > head.upper + 1e-9))
        if out.size:
            from kinematics import JOINT_NAMES

            j = int(out[0])
            raise ValueError(f"--current: {JOINT_NAMES[j]} = {args.current[j]:g} deg is outside its range "
                             f"[{math.degrees(head.lower[j]):g}, {math.degrees(head.upper[j]):g}] deg; give the "
                             f"joint angles the head is at now (E,P,C degrees)")
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


def _picture_path(text: str) -> Path:
    """The PNG a picture goes to: ``--out`` itself when it ends in .png, ``head.png`` inside it
    when it is an existing folder; anything else is refused (the renderer would add .png)."""
    path = Path(text)
    if path.is_dir():
        path = path / "head.png"
    elif path.suffix.lower() != ".png":
        raise ValueError(f"--out {text}: a picture is a PNG file; give a path ending in .png (e.g. head.png), "
                         f"or an existing folder to write head.png into")
    return check_output_file(path, "--out", ".png")


def _check_in_range(head, q_rad: np.ndarray, flag: str) -> None:
    """Refuse joint angles (3,) radians outside the head's ranges, naming the joint and the flag."""
    bad = np.flatnonzero((q_rad < head.lower - 1e-9) | (q_rad > head.upper + 1e-9))
    if bad.size:
        j = int(bad[0])
        raise ValueError(f"{flag}: {JOINT_NAMES[j]} = {math.degrees(q_rad[j]):g} deg is outside its range "
                         f"[{math.degrees(head.lower[j]):g}, {math.degrees(head.upper[j]):g}] deg; give E,P,C degrees "
                         f"within the head's ranges")


def cmd_kinematics_picture(args) -> int:
    from kinematics.picture import render_head

    path = _picture_path(args.out)             # before the head is rendered: a refusal loses no work
    head = load_head(args.head)
    for q in args.posture or []:
        _check_in_range(head, np.radians(q), "--posture")
    out = render_head(head, path, postures=np.radians(np.array(args.posture)) if args.posture else None)
    print(f"wrote {out}")
    return 0


def _design_seed(text: str) -> int:
    """--seed: a whole number from 0 to 2**32 - 1 (numpy's seeds)."""
    try:
        v = int(text)
    except ValueError:
        v = None
    if v is None or not 0 <= v < 2**32:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number >= 0 (at most {2**32 - 1}, numpy's seeds)")
    return v


def cmd_design_optimise(args) -> int:
    from design.study import optimise
    from design.sweep_file import load_sweep

    spec = load_sweep(args.sweep)
    o = optimise(spec, args.out, evaluations=args.evaluations, seed=args.seed, algorithm=args.algorithm,
                 resume=args.resume, workers=args.workers, scheduler=args.scheduler, dashboard=args.dashboard)
    print(f"{o.evaluations} evaluations ({o.evaluated} computed now, {o.reused} reused), "
          f"{o.feasible} feasible, front of {o.front_size}")
    if o.chosen is not None:
        print(f"chosen head: {o.chosen.head_path}; report: {o.report_path}")
    else:
        print(f"no feasible design; see {o.report_path}")
    return 0


def cmd_design_evaluate(args) -> int:
    from design.problem import EvaluationContext, score_head
    from design.sweep_file import load_sweep

    ctx = EvaluationContext.from_spec(load_sweep(args.sweep))
    crit, cons = score_head(load_head(args.head), ctx)
    for k, v in {**crit, **cons}.items():
        print(f"{k:24s} {v:.6g}")
    return 0


def cmd_design_compare(args) -> int:
    from design.convergence import fraction_to_match, read_evaluations

    c = fraction_to_match(*read_evaluations(args.run), *read_evaluations(args.baseline), at=args.at)
    kind = "exact" if c.exact else "approximate"
    if c.needed is None:
        print(f"never reached: {c.reached:.5f} at {c.at} evaluations against the baseline's {c.target:.5f} ({kind})")
    else:
        print(f"fraction {c.fraction:.3f}: {c.needed} of {c.at} evaluations reach the baseline's hypervolume "
              f"{c.target:.5f} ({kind}; {c.reached:.5f} at {c.at})")
    return 0


def cmd_design_template(args) -> int:
    from design.sweep_file import default_sweep_text

    sys.stdout.write(default_sweep_text())
    return 0


def cmd_placement_map(args) -> int:
    from placement.body import make_body
    from placement.io import load_body
    from placement.mapping import placement_map
    from placement.motions import default_motions
    from placement.retarget import load_bvh
    from placement.scores import ScoreSettings

    if (args.body is None) != (args.joints is None):
        raise ValueError("--body and --joints go together: a labelled mesh and its joints JSON")
    check_folder(args.out, "placement map")
    body = load_body(args.body, args.joints) if args.body else make_body(args.stature)
    motions = ([load_bvh(p, body, scale=args.motion_scale, up=args.motion_up, allow_missing=args.allow_missing_joints)
                for p in args.motion] if args.motion else default_motions(body))
    for m in motions:
        if m.unmapped:
            print(f"{m.name}: joints not driving any segment: {', '.join(m.unmapped)}")
    settings = ScoreSettings(rays=args.rays, standoff_m=args.standoff)
    r = placement_map(args.out, body, motions, settings)
    print(f"scored {r.polygons} places; maps, scores.csv, zones.md and mount.toml in {r.folder}")
    for z in r.zones.rows.values():
        if z is not None:
            print(f"  {z.zone:9s} fov {z.fov:.3f}  handling {z.handling_view:.3f}  motion {z.motion_mm:.0f} mm  "
                  f"combined {z.combined:.3f}  ({z.frame}, acceptability {z.acceptability})")
    if r.zones.mount_zone is None:
        print("no zone qualifies for mount.toml (every zone ties the camera to the wearer's attention)")
    return 0


def cmd_sim_record(args) -> int:
    from dataclasses import replace

    from runtime.sequence import check_new_recording
    from runtime.twin.recorder import record
    from runtime.twin.scenarios import get_scenario

    scenario = get_scenario(args.scenario)
    if args.dim_to is not None:
        if not 0.0 <= args.dim_to <= 1.0:
            raise ValueError(f"--dim-to {args.dim_to}: give the final light level as a fraction 0..1")
        scenario = replace(scenario, dim_to=args.dim_to)
    check_new_recording(args.out)       # before the twin is built: a refusal loses no work
    twin = make_twin(args.head, args.mount, args.camera, ideal_imu=args.ideal_imu, ideal_camera=args.ideal_camera)
    try:
        with _seed_hint("--scene-seed or --seed"):
            out = record(twin, scenario, args.out, seconds=args.seconds, seed=args.seed, depth=args.depth,
                         scene_seed=args.scene_seed, click_error_px=args.click_error)
    finally:
        twin.close()
    print(f"recorded {args.scenario} (seed {args.seed}, scene seed {twin.scene_seed}) into {out}")
    return 0


@contextlib.contextmanager
def _seed_hint(options: str):
    """A hidden start target's advice in the options of the command that runs (the library says
    "another seed": sim run takes --seed, sim record also --scene-seed)."""
    from runtime.twin.operator import TargetHidden

    try:
        yield
    except TargetHidden as e:
        raise TargetHidden(str(e).replace("use another seed", f"use another {options}")) from None


def _check_limit(limit_deg_s: float, head_path) -> None:
    """--limit in the unit the flag takes (deg/s): above 0, at most the head's servos' speed."""
    from kinematics import reference_head

    head = load_head(head_path) if head_path else reference_head()
    top = math.degrees(float(np.min(head.max_speed)))
    if not (math.isfinite(limit_deg_s) and 0 < limit_deg_s <= top + 1e-9):
        raise ValueError(f"--limit {limit_deg_s:g} deg/s: the controlled-motion limit must be above 0 and at most "
                         f"the servos' {top:.0f} deg/s (the paper's is 30)")


def _recentre(args) -> float:
    """--recentre, which only the stabilise task takes (one line otherwise)."""
    g = float(getattr(args, "recentre", 0.0) or 0.0)
    if g > 0 and args.task != "stabilise":
        raise ValueError(f"--recentre is Path A's outer loop: give it with --task stabilise, not {args.task}")
    return g


def cmd_sim_run(args) -> int:
    from runtime.apps.closed_loop import Task, load_targets
    from runtime.gaze import ControllerSettings
    from runtime.twin.scenarios import get_scenario
    from wvr.assemble import run_on_twin

    check_folder(args.out, "sim run")          # before any file is read: a refusal loses no work
    scenario = get_scenario(args.scenario)
    _check_limit(args.limit, args.head)
    targets = [np.asarray(t, float) for t in (args.target or [])]
    dwell = args.dwell
    if args.targets:
        pts, file_dwell = load_targets(args.targets)
        targets += list(pts)
        dwell = file_dwell or dwell
    start = getattr(args, "start", "target")
    if not targets and args.task == "fixate" and start == "target":
        targets = [scenario.bench.target_corners().mean(axis=0)]
    region = None if getattr(args, "init", None) is None else tuple(float(v) for v in args.init)
    task = Task(args.task, np.array(targets).reshape(-1, 3), dwell_s=dwell, region=region,
                method=getattr(args, "method", "hyperplane"), recentre_per_s=_recentre(args), start=start,
                glances=getattr(args, "glances", False), slam_imu=not getattr(args, "no_imu", False))
    settings = ControllerSettings(motion_limit_rad_s=math.radians(args.limit))
    with output_folder(args.out, kind="sim run") as out:    # INCOMPLETE until the end
        twin = make_twin(args.head, args.mount, args.camera)
        try:
            with _seed_hint("--seed"):
                s = run_on_twin(twin, scenario, task, out, seconds=args.seconds, seed=args.seed, settings=settings,
                                click_error_px=getattr(args, "click_error", 2.5),
                                session_log=not getattr(args, "no_session_log", False))
        finally:
            twin.close()
    print(Path(args.out, "report.md").read_text().split("![")[0].strip())
    # Only what this run wrote (SLAM that could not start writes no trajectory.tum).
    names = ("groundtruth.txt", "trajectory.tum", "task.toml", "joints.csv", "prompts.csv", "head.toml", "report.md")
    print(f"wrote {args.out}: " + ", ".join(n for n in names if Path(args.out, n).exists()))
    return 0 if not s["refusals"] else 1


def cmd_stabilise(args) -> int:
    from runtime.vision2d.stabilise import stabilise_sequence

    fovea = _size(args.fovea, "--fovea")
    check_folder(args.out, "stabilise")
    if args.imu:
        from runtime.sequence import open_sequence

        seq = open_sequence(args.seq)
        if seq.imu is not None and len(seq.imu.t) == 0:
            raise ValueError(f"{Path(args.seq) / 'imu.txt'}: holds no samples, so --imu has nothing to use; run "
                             f"without --imu, or record the IMU")
    r = stabilise_sequence(args.seq, args.out, fovea=fovea, use_imu=args.imu)
    print(json.dumps(r.stats(), indent=1))
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
        if args.seq:
            raise ValueError(f"--servo runs in the twin, not on a sequence: leave out {args.seq!r}")
        args.task, args.target, args.targets, args.dwell, args.limit = "track", None, None, 2.0, MOTION_LIMIT_DEG_S
        return cmd_sim_run(args)
    if not args.seq:
        raise ValueError("give the sequence folder SEQ (or --servo --scenario NAME for the closed loop)")
    if args.init is None:
        raise ValueError("--init X,Y,W,H is required: the target's box in the first frame, pixels")
    from runtime.vision2d.track import track_sequence

    check_folder(args.out, "track")
    r = track_sequence(args.seq, args.out, init=tuple(float(v) for v in args.init), method=args.method)
    print(json.dumps(r.stats(), indent=1))
    print(f"wrote {Path(args.out) / 'polygons.csv'}, annotated/, stats.json")
    return 0


def cmd_slam(args) -> int:
    from dataclasses import replace

    from runtime.slam.config import DEFAULT_CONFIG, MapSettings
    from runtime.slam.run import run_slam

    settings = replace(MapSettings(), use_imu=not args.no_imu, imu_biases=not args.no_imu_biases,
                       imu_handover=not args.no_imu_handover, features=args.features)
    cfg = replace(DEFAULT_CONFIG, time_offset0=args.imu_clock_offset / 1000.0)
    if args.fixed_impulses:
        cfg = replace(cfg, adapt_sigma_a=False, adapt_sigma_alpha=False, adapt_onset=False)
    if args.measure is not None:
        settings = settings.with_measure(args.measure)
    if args.save_map is not None:
        from runtime.slam.map_io import check_map_path

        check_map_path(args.save_map)
        check_output(Path(args.save_map).parent, "--save-map")
    with output_folder(args.out, kind="slam") as out:    # checked before the run, INCOMPLETE until it ends
        r = run_slam(args.seq, out, max_frames=args.max_frames, video=args.video, cfg=cfg, settings=settings,
                     save_map=args.save_map, map_path=args.map, session_log=not args.no_session_log)
    print(f"{r.frames} frames ({r.skipped} skipped), {r.features} features in the map, {r.mean_matched:.1f} of "
          f"{r.mean_searched:.1f} searched matched per frame, {r.median_ms_per_frame:.1f} ms per frame (median)"
          + (f"; located in the map after {r.first_localised_s:.2f} s" if args.map and r.first_localised_s is not None else "")
          + (f"; track LOST for {r.lost_frames} frames" if r.lost else "")
          + (f"; {r.frame_gaps} gaps between images (frames missing; the longest {1000 * r.longest_interval_s:.0f} ms)"
             if r.frame_gaps else "")
          + (f"; IMU: {r.imu['gaps']} gaps, {r.imu['spikes']} spikes, {r.imu['non_finite']} bad samples"
             if r.imu.get("rows") and (r.imu["gaps"] or r.imu["spikes"] or r.imu["non_finite"]) else ""))
    if r.imu_clock_offset_s is not None and r.imu_frames > 0:
        print(f"IMU clock offset {1000 * r.imu_clock_offset_s:.1f} +- {1000 * r.imu_clock_offset_sd_s:.1f} ms "
              "(estimated; a sample stamped t was taken at t - offset on the camera's clock)")
    if args.map and r.first_localised_s is None:
        print("the camera was never located in the saved map: trajectory.tum is empty")
    print(f"wrote {Path(args.out) / 'trajectory.tum'}, map.csv, stats.json"
          + (f"; the map in {args.save_map}" if args.save_map else ""))
    return 0


#: eval warns when fewer than this share of the estimated poses have a ground-truth pose.
MIN_COVERAGE = 0.9


def _default_alignment(result: Path) -> str:
    """The alignment a run's stats.json scale calls for: none where a target or a saved map fixed
    the world's frame and scale, se3 where the scale is metric but the frame the first camera's
    (depth, imu), sim3 where the scale is arbitrary."""
    try:
        scale = json.loads((result / "stats.json").read_text()).get("totals", {}).get("scale", "target")
    except (OSError, ValueError, AttributeError):
        scale = "target"
    return {"arbitrary": "sim3", "depth": "se3", "imu": "se3"}.get(scale, "none")


def cmd_eval(args) -> int:
    from kinematics.outdir import check_complete
    from runtime.datasets import dataset_kind, open_any, open_tum
    from runtime.sequence import read_trajectory
    from runtime.eval import trajectory_errors

    result = Path(args.result)
    if not result.is_dir():
        raise ValueError(f"{result}: not a folder; give the folder wvr slam wrote (with trajectory.tum)")
    check_complete(result, "SLAM result")
    # As wvr slam reads them, but ours (and TUM RGB-D) with an unreadable depth image skipped and
    # counted by the map's scoring instead of refusing the sequence.
    seq = open_tum(args.seq, check_depth=False) if dataset_kind(args.seq) == "tum" else open_any(args.seq)
    if seq.groundtruth is None:
        raise ValueError(f"{args.seq}: no ground truth to evaluate against (groundtruth.txt; EuRoC's "
                         f"state_groundtruth_estimate0; KITTI's poses/NN.txt)")
    est = read_trajectory(result / "trajectory.tum")
    if len(seq.groundtruth) < 2:
        raise ValueError(f"{Path(args.seq) / 'groundtruth.txt'}: holds {len(seq.groundtruth)} poses; the ground "
                         f"truth needs at least two to evaluate against (re-record the sequence)")
    if len(est) < 2:
        raise ValueError(f"{result / 'trajectory.tum'}: holds {len(est)} poses, so there is nothing to evaluate "
                         f"(the camera was never located, or the run stopped at once); run wvr slam again")
    e = trajectory_errors(est, seq.groundtruth)
    print(f"poses matched: {e.matched} of {len(est)}")
    if e.matched < MIN_COVERAGE * len(est):
        print(f"warning: the ground truth covers only {e.matched} of the {len(est)} estimated poses "
              f"({100 * e.matched / len(est):.0f}%); every figure below describes that part only", file=sys.stderr)
    align = args.align or _default_alignment(result)
    for name, label in (("none", "no alignment"), ("se3", "SE3-aligned"), ("sim3", "Sim3-aligned")):
        rmse, worst = e.ate(name)
        print(f"{'*' if name == align else ' '} ATE ({label}):{' ' * (14 - len(label))}RMSE {100 * rmse:.2f} cm, "
              f"max {100 * worst:.2f} cm" + (f", scale x{e.sim3_scale:.4f}" if name == "sim3" else ""))
    if math.isfinite(e.rpe_trans_rmse_m):
        print(f"RPE over {e.rpe_delta_s:g} s: {100 * e.rpe_trans_rmse_m:.2f} cm, {e.rpe_rot_rmse_deg:.2f} deg RMSE")
    else:
        from runtime.eval import associate

        span = float(np.ptp(est.t[associate(est, seq.groundtruth)[0]]))
        print(f"RPE over {e.rpe_delta_s:g} s: cannot be computed: the matched poses span {span:.2f} s, not more "
              f"than {e.rpe_delta_s:g} s")
    if seq.depth_paths is not None and (result / "map.csv").exists():
        from runtime.eval import map_errors

        m = map_errors(seq, result / "map.csv")
        if m.skipped:
            print(f"warning: {len(m.skipped)} depth images skipped, their features left out of the map figures "
                  f"(the first: {m.skipped[0]})", file=sys.stderr)
        if len(m.errors_m):
            print(f"map against the true depth: {len(m.errors_m)} features, RMSE {100 * m.rmse_m:.2f} cm, "
                  f"median {100 * m.median_m:.2f} cm")
        else:
            print("map against the true depth: cannot be computed: no mapped feature falls on a pixel with depth")
    return 0


def cmd_convert(args) -> int:
    from runtime.datasets import convert_euroc, convert_kitti

    if args.format == "euroc":
        seq = convert_euroc(args.src, args.out, groundtruth=args.groundtruth, copy=args.copy)
    else:
        seq = convert_kitti(args.src, args.out, poses=args.poses, copy=args.copy)
    for note in seq.notes:
        print(f"note: {note}")
    span = seq.timestamps[-1] - seq.timestamps[0]
    print(f"{len(seq)} frames over {span:.2f} s, {seq.camera.width}x{seq.camera.height} {seq.camera.model}"
          + (f"; {len(seq.imu)} IMU samples (camera frame)" if seq.imu is not None else "; no IMU")
          + (f"; {len(seq.groundtruth)} ground-truth poses" if seq.groundtruth is not None else "; no ground truth"))
    print(f"wrote {Path(args.out) / 'rgb.txt'} ({'copies of' if args.copy else 'links to'} the images), camera.toml"
          + (", imu.txt" if seq.imu is not None else "") + (", groundtruth.txt" if seq.groundtruth is not None else ""))
    return 0


# ------------------------------------------------------------------ the hardware rig

def _degrees3(text: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise ValueError(f"{text!r} is not E,P,C (three comma-separated angles, degrees)") from None
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"{text!r} must be three finite angles E,P,C in degrees")
    return v


def _distinct(value: float, *limits: float) -> list[str]:
    """value (as typed) and limits printed with the fewest decimals (at least one) that tell
    the value from every limit: 80.0001 beyond 80.0, not 80.0 beyond 80.0."""
    for digits in range(1, 17):
        text = [f"{x:.{digits}f}" for x in (value, *limits)]
        if text[0] not in text[1:]:
            break
    trim = [t.rstrip("0") + "0" if t.rstrip("0").endswith(".") else t.rstrip("0") for t in text]
    return [repr(float(value))] + trim[1:]          # the value as typed (repr round-trips the text's float)


def cmd_head(args) -> int:
    """Bring-up moves at a slow, stated rate; nothing beyond the head's range is ever sent."""
    import math

    from runtime.drivers.rig import load_rig, open_servo_board
    from runtime.safety import EStop

    cfg = load_rig(args.rig, with_camera=False)        # bring-up needs the servos only
    estop = EStop(cfg.estop_file)
    if args.action == "stop":
        try:
            estop.trip("stopped from the command line (wvr head stop)")
        except OSError as e:
            raise DriverError(f"the emergency stop is NOT latched: {cfg.estop_file} cannot be written "
                              f"({e.strerror or e}); stop the head by its power switch, then fix safety.estop_file "
                              f"in {args.rig}") from None
        print(f"emergency stop latched ({cfg.estop_file}); every run holds until wvr head --rig {args.rig} reset")
        return 0
    if args.action == "reset":
        try:
            estop.reset()
        except OSError as e:
            raise DriverError(f"the emergency stop is still latched: {cfg.estop_file} cannot be removed "
                              f"({e.strerror or e}); remove it by hand") from None
        print("emergency stop cleared")
        return 0
    head = cfg.head
    if args.action == "goto":
        if args.angles is None:
            raise ValueError("goto needs the angles: wvr head --rig rig.toml goto E,P,C (degrees)")
        goal_deg = _degrees3(args.angles)
        goal = np.radians(goal_deg)
        bad = (goal < head.lower - 1e-12) | (goal > head.upper + 1e-12)
        if bad.any():
            j = int(np.argmax(bad))
            lo, hi = math.degrees(head.lower[j]), math.degrees(head.upper[j])
            v, lo_s, hi_s = _distinct(goal_deg[j], lo, hi)
            raise ValueError(f"{JOINT_NAMES[j]} {v} deg is beyond the head's range {lo_s}..{hi_s} deg; nothing "
                             f"was sent")
        poses = [goal]
    elif args.action == "home":
        poses = [cfg.home]
    else:                                       # sweep: each joint through its range, and back
        poses = []
        for j in range(3):
            for a in (head.lower[j], head.upper[j], cfg.home[j]):
                q = cfg.home.copy()
                q[j] = a
                poses.append(q)
    if estop.tripped:
        raise DriverError(f"the emergency stop is latched ({estop.reason}); clear it with wvr head --rig {args.rig} reset")
    rate = math.radians(args.rate)
    if not 0 < rate <= float(np.min(cfg.speed_limit_rad_s)):
        raise ValueError(f"--rate {args.rate:g} deg/s must be positive and at most the board's "
                         f"{math.degrees(float(np.min(cfg.speed_limit_rad_s))):.0f} deg/s")
    board = open_servo_board(cfg)
    try:
        board.start()
        print(f"moving at {args.rate:g} deg/s (the board's speed limit for the move)")
        for q in poses:
            reached = board.move_slowly(q, rate, timeout_s=args.timeout)
            print("at " + ", ".join(f"{n} {math.degrees(v):.1f}" for n, v in zip(JOINT_NAMES, reached)) + " deg")
        board.check_errors()
    finally:
        board.close()
    return 0


def cmd_run(args) -> int:
    import math

    from runtime.apps.closed_loop import Task, load_targets
    from runtime.drivers.rig import load_rig
    from runtime.gaze import ControllerSettings
    from runtime.sequence import load_target

    out = check_folder(args.out, "run")          # before the rig is read or opened: a refusal loses no work
    cfg = load_rig(args.rig)
    start_path = Path(args.start_target) if args.start_target else cfg.start_target
    start = load_target(start_path) if start_path is not None else None
    targets = [np.asarray(t, float) for t in (args.target or [])]
    dwell = args.dwell
    if args.targets:
        pts, file_dwell = load_targets(args.targets)
        targets += list(pts)
        dwell = file_dwell or dwell
    start_kind = getattr(args, "start", "target")
    if not targets and args.task == "fixate" and start is not None and start_kind == "target":
        targets = [start.xyz.mean(axis=0)]           # the known target's centre
    region = None
    if args.init is not None:
        if np.shape(args.init) != (4,):
            raise ValueError("--init takes four numbers X,Y,W,H (pixels in the first frame)")
        region = tuple(float(v) for v in args.init)
    task = Task(args.task, np.array(targets).reshape(-1, 3), dwell_s=dwell, region=region, method=args.method,
                recentre_per_s=_recentre(args), start=start_kind, glances=args.glances, slam_imu=not args.no_imu)
    limit = min(args.limit, math.degrees(cfg.safety.motion_limit_rad_s))
    settings = ControllerSettings(motion_limit_rad_s=math.radians(limit))
    if task.uses_slam and start is None and start_kind == "target":
        raise ValueError(f"task {task.kind} starts SLAM from the known target: give --start-target target.toml "
                         f"(or [start] target in {args.rig})")
    with output_folder(out, kind="run"):        # locked, INCOMPLETE until the session is written
        try:
            return _run_on_rig(args, cfg, out, task, start, settings)
        except DriverError as e:
            if not (out / "session.json").exists():
                raise                           # the rig never started (a missing port): no folder left
            # A fault ends the session, which is written whole up to it (session.json says so):
            # the folder is complete; the error is still the command's result.
            fault = e
    raise fault


def _run_on_rig(args, cfg, out: Path, task, start, settings) -> int:
    from runtime.apps.closed_loop import run_closed_loop
    from runtime.apps.session import SessionRecorder
    from wvr.assemble import make_rig

    rig = make_rig(cfg)
    rec = SessionRecorder(out, cfg.camera, cfg.head, start, notes={"rig": str(Path(args.rig).resolve()), "task": task.kind})
    complete, reason, s = False, "", None
    stopped: list[str] = []

    def stop_now():                                   # once, as soon as the loop ends
        if not stopped:
            stopped.append(rig.safe_stop(home=True))

    try:
        s = run_closed_loop(rig, task, out, start_target=start, seconds=args.seconds, settings=settings,
                            label="rig", task_info={"rig": str(args.rig)}, on_period=rec, on_end=stop_now,
                            session_log=not args.no_session_log)
        complete = s["ended"] in ("complete",) or s["ended"].endswith("stream ended")
        reason = s["ended"]
    except DriverError as e:
        reason = f"fault: {e}"
        raise
    finally:
        stop_now()
        stop = stopped[0]
        rig.close()
        rep = rig.chain.report()
        rec.notes.update(safe_stop=stop, safety=rep.__dict__)
        rec.finish(complete, reason or "stopped")
    print(Path(out, "report.md").read_text().split("![")[0].strip())
    slam = ", trajectory.tum" if (out / "trajectory.tum").exists() else ""   # none without a start target
    print(f"wrote {out}: rgb/, rgb.txt, imu.txt, joints.txt, camera.toml, head.toml, target.toml{slam}, "
          f"joints.csv, session.json ({'complete' if complete else 'INCOMPLETE: ' + reason}); safe stop: {stop}")
    return 0 if not s["refusals"] else 1


def cmd_sim_hil(args) -> int:
    from runtime.twin.hil import HilSession

    # A finished session is reused only with --force (the folder's kind says what wrote it).
    out = check_folder(args.out, "sim hil", reuse=args.force)
    with output_folder(out, kind="sim hil", reuse=args.force):
        twin = make_twin(args.head, args.mount, args.camera)
        twin.configure(args.scenario, seed=args.seed, seconds=args.seconds)
        session = HilSession(twin, out, imu=args.imu, wait_s=args.wait, linger_s=args.linger,
                             click_error_px=args.click_error)

        def ready():
            print(f"HIL ready: run  wvr run --rig {out / 'rig.toml'} --task fixate --out RUN_DIR", flush=True)
        session.ready = ready
        try:
            with _seed_hint("--seed"):
                st = session.run(progress=not args.quiet)
        finally:
            session.close()
            twin.close()
    print(f"served {st.frames} frames, {st.target_commands} target commands, {st.stalls} stalls; "
          f"truth in {out / 'groundtruth.txt'}")
    return 0


def cmd_calibrate(args) -> int:
    if args.what == "camera":
        from runtime.drivers.calibrate import calibrate_camera

        if not args.images or not args.board:
            raise ValueError("wvr calibrate camera needs --images DIR and --board chessboard:COLSxROWS:SQUARE_M")
        check_output_file(args.out, "--out", ".toml")      # before the images are read: a refusal loses no work
        res = calibrate_camera(args.images, args.board, args.model, args.out)
        print(f"{res.images_used} of {res.images_total} images used; RMS reprojection error {res.rms_px:.3f} px; "
              f"wrote {res.path}")
        return 0
    from runtime.drivers.calibrate import calibrate_imu

    if not args.rig:
        raise ValueError("wvr calibrate imu needs --rig rig.toml")
    res = calibrate_imu(args.rig, args.seconds)
    print(f"{res.samples} samples over {res.seconds:.1f} s: gyro bias {np.round(res.gyro_bias, 5).tolist()} rad/s, "
          f"accel bias {np.round(res.accel_bias, 4).tolist()} m/s^2 (camera frame); written into {args.rig}")
    return 0


def cmd_station(args) -> int:
    from runtime.apps.station.record import check_out
    from runtime.apps.station.station import Station, resolve_token, serve
    from runtime.gaze import ControllerSettings

    # Bad input is refused before anything starts (no address printed, no folder made).
    resolve_token(args.token)
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port {args.port} is not a port number (0-65535; 0: any free one)")
    if (args.scenario is None) == (args.rig is None):
        raise ValueError("wvr station needs one of --scenario NAME (the twin) or --rig rig.toml (the hardware)")
    if not (math.isfinite(args.limit) and args.limit > 0):
        raise ValueError(f"--limit {args.limit:g} deg/s: the controlled-motion limit must be above 0 (the paper's is 30)")
    if args.scenario is not None:
        _check_limit(args.limit, args.head)
        if args.seed < 0:
            raise ValueError(f"--seed {args.seed}: give a seed of 0 or more")
        if not (math.isfinite(args.click_error) and 0.0 <= args.click_error <= 50.0):
            raise ValueError(f"--click-error {args.click_error}: give the operator's click error in pixels, 0 to 50")
    if args.out:
        check_out(args.out)
    if args.scenario is not None:
        from runtime.twin.operator import TargetHidden
        from runtime.twin.scenarios import get_scenario
        from wvr.assemble import clicked_target, safe_twin

        sc = get_scenario(args.scenario)
        twin = make_twin(args.head, args.mount, args.camera)
        twin.configure(sc, seed=args.seed, seconds=args.seconds)
        robot = safe_twin(twin, math.radians(args.limit))

        def start(obs):
            try:
                return clicked_target(twin, args.click_error, args.seed)
            except TargetHidden as e:
                # The twin's own hint names sim record's options; the station's place is its --seed.
                raise TargetHidden(f"{str(e).split('; use another')[0]}; choose another --seed (the station's place "
                                   "follows it)") from None

        truth, seconds = twin, (args.seconds if args.seconds is not None else sc.seconds)
        notes = {"scenario": sc.name, "seed": args.seed}
    else:
        from runtime.drivers.rig import load_rig
        from runtime.sequence import load_target
        from wvr.assemble import make_rig

        cfg = load_rig(args.rig)
        top = math.degrees(float(np.min(cfg.head.max_speed)))
        if args.limit > top + 1e-9:
            raise ValueError(f"--limit {args.limit:g} deg/s: the controlled-motion limit must be at most the servos' "
                             f"{top:.0f} deg/s (the paper's is 30)")
        if cfg.start_target is None:
            raise ValueError(f"{args.rig}: the station starts SLAM from a known target: add [start] target = "
                             "\"target.toml\" (known points and their pixels in the first image)")
        start, truth, seconds = load_target(cfg.start_target), None, args.seconds
        robot = make_rig(cfg)
        notes = {"rig": str(Path(args.rig).resolve())}
    settings = ControllerSettings(motion_limit_rad_s=math.radians(args.limit))

    def finish():
        # In the loop's thread, as it ends: the rig's safe stop (hold, home slowly); the twin's
        # renderer closed in the thread that made it.
        out = robot.safe_stop(home=True) if args.rig is not None else None
        robot.close()
        return out

    station = Station(robot, start, host=args.host, port=args.port, token=args.token, out=args.out, truth=truth,
                      seconds=seconds, settings=settings, notes=notes, on_finish=finish,
                      session_log=not args.no_session_log)

    def ready(st):
        for line in st.address_lines():
            print(line, flush=True)

    try:
        s = serve(station, on_ready=ready)
    finally:
        if not station.live.started.is_set() and not station.live.finished.is_set():
            robot.close()                       # it never ran (a busy port): nothing to stop
    if args.rig is not None:
        print(f"station: safe stop: {station.live.finish_result}")
    print(f"station: {s['ended']}; {s['frames']} frames, {s['events']} actions ({s['accepted']} accepted), "
          f"{s['labels']} labels")
    if args.out:
        print(f"wrote {args.out}: {', '.join(s['written'])}")
    return 0


def cmd_demo(args) -> int:
    from wvr.demo import run_demo

    r = run_demo(Path(args.out))
    print(f"wrote {r.report}")
    if r.failed:
        print(f"wvr demo: {len(r.failed)} stage(s) failed: {'; '.join(r.failed)} (see {r.report})", file=sys.stderr)
        return 1
    return 0


def _twin_options(p: argparse.ArgumentParser, scenarios, required: bool = True, when: str = "") -> None:
    """The options every twin run takes (record, closed loop, tracking servo): scenario,
    duration, seed, and the head, mount and camera files. ``when`` prefixes their help."""
    p.add_argument("--scenario", required=required, choices=sorted(scenarios), help=f"{when}the twin scenario")
    p.add_argument("--seconds", type=_seconds, help=f"{when}duration, s, above 0 (default: the scenario's)")
    p.add_argument("--seed", type=_nonneg_int, default=0,
                   help=f"{when}run seed: motion variation and sensor noise, and the place (textures, layout)")
    p.add_argument("--head", help=f"{when}head.toml (default: the reference head)")
    p.add_argument("--mount", help=f"{when}mount.toml from wvr placement map (default: on the right shoulder)")
    p.add_argument("--camera", help=f"{when}camera.toml (default: 640x480, f = 514.7 px)")


def _session_log_option(p: argparse.ArgumentParser, when: str = "") -> None:
    """--no-session-log: the commands that write session.mcap (runtime.session_log) can leave it out."""
    p.add_argument("--no-session-log", action="store_true",
                   help=f"{when}do not write session.mcap (the run's images, poses, map, joints and events for "
                        "Foxglove or any MCAP reader); the other files are the same")


def _start_option(p: argparse.ArgumentParser, fixate_default: str) -> None:
    """--start: how the closed loop's SLAM starts (runtime.apps.closed_loop.STARTS)."""
    from runtime.apps.closed_loop import STARTS

    p.add_argument("--start", choices=list(STARTS), default="target",
                   help="how SLAM starts (every task runs it; stabilise, body and track only observe it): target "
                        "(the printed target's clicked corners, the default) or head-motion "
                        "(no target: once the wearer keeps still, the head goes along the diagonals of a box in pan and "
                        "elevation, and that known motion fixes the scale, then the task begins; not with track; "
                        "targets are then in its world frame: "
                        f"origin at the first camera, z up, x ahead; fixate's default target is {fixate_default})")


def _glances_option(p: argparse.ArgumentParser) -> None:
    """--glances: fixate's brief looks away where SLAM's pose is weakest (runtime.apps.glances)."""
    p.add_argument("--glances", action="store_true",
                   help="with --task fixate: when SLAM's camera position grows uncertain along one direction "
                        "(over 1 cm), the head looks briefly where that direction is best observed and comes back")


def _slam_imu_option(p: argparse.ArgumentParser) -> None:
    """--no-imu: the closed loop's SLAM from the camera alone (Task.slam_imu)."""
    p.add_argument("--no-imu", action="store_true",
                   help="SLAM from the camera alone, the paper's system: the IMU drives no prediction (the "
                        "head-motion start still reads it to wait for a still wearer and to fit its motion)")


def build_parser() -> argparse.ArgumentParser:
    from runtime.apps.closed_loop import TASKS
    from runtime.twin.scenarios import SCENARIOS
    from runtime.vision2d.track import METHODS

    p = _Parser(
        prog="wvr",
        description="wvr: design, place and run an active wearable camera (Mayol, Davison, Tordoff, Murray).",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    kin = sub.add_parser("kinematics", help="the head: chain summary, MJCF model, gaze IK, picture")
    ksub = kin.add_subparsers(dest="kinematics_command", metavar="SUBCOMMAND", required=True)
    show = ksub.add_parser("show", help="print the chain, masses, radii, torques and gaze coverage of a head")
    show.add_argument("head", help="head.toml, or 'reference'")
    show.add_argument("--json", action="store_true", help="print JSON instead of Markdown")
    show.add_argument("--directions", type=_directions, default=2000,
                      help="gaze directions sampled for coverage (default 2000, at most 200000)")
    show.set_defaults(func=cmd_kinematics_show)
    mj = ksub.add_parser("mjcf", help="write the head's MJCF model to standard output")
    mj.add_argument("head", help="head.toml, or 'reference'")
    mj.add_argument("--camera", help="camera.toml with the intrinsics (default: 640x480, f=514.7 px)")
    mj.set_defaults(func=cmd_kinematics_mjcf)
    ik = ksub.add_parser("ik", help="joint angles that fixate a direction or point (mount frame), image upright")
    ik.add_argument("head", help="head.toml, or 'reference'")
    ik.add_argument("--target", type=_point, required=True, metavar="X,Y,Z",
                    help="direction (or point in metres with --point), mount frame")
    ik.add_argument("--point", action="store_true", help="the target is a 3D point in metres, not a direction")
    ik.add_argument("--up", type=_direction, default=np.array([0.0, 0.0, 1.0]), metavar="X,Y,Z",
                    help="world up in the mount frame")
    ik.add_argument("--current", type=_angles, metavar="E,P,C", help="current joint angles, degrees")
    ik.set_defaults(func=cmd_kinematics_ik)
    pic = ksub.add_parser("picture", help="render the head to a PNG (offscreen)")
    pic.add_argument("head", help="head.toml, or 'reference'")
    pic.add_argument("--out", required=True, help="PNG path (or an existing folder: head.png in it)")
    pic.add_argument("--posture", type=_angles, action="append", metavar="E,P,C",
                     help="joint angles in degrees (repeatable)")
    pic.set_defaults(func=cmd_kinematics_picture)

    from design.sweep_file import ALGORITHMS as design_algorithms
    des = sub.add_parser("design", help="Pareto optimisation of the head's layout (7 criteria)")
    dsub = des.add_subparsers(dest="design_command", metavar="SUBCOMMAND", required=True)
    opt = dsub.add_parser("optimise", help="run (or resume) a design sweep; writes the front and chosen_head.toml")
    opt.add_argument("--sweep", help="sweep.toml (default: the shipped default sweep; see sweep-template)")
    opt.add_argument("--out", required=True, help="output directory")
    opt.add_argument("--evaluations", type=_positive_int, help="evaluation budget (default: the sweep file's)")
    opt.add_argument("--seed", type=_design_seed, help="random seed, 0 or more (default: the sweep file's)")
    opt.add_argument("--algorithm", choices=design_algorithms, help="default: the sweep file's")
    group = opt.add_mutually_exclusive_group()
    group.add_argument("--workers", type=_positive_int, help="evaluate on a local Dask cluster of N worker processes")
    group.add_argument("--scheduler", help="evaluate on an existing Dask cluster, e.g. tcp://HOST:8786")
    opt.add_argument("--dashboard", metavar="HOST:PORT", help="with --workers: where Dask's dashboard listens "
                     "(default loopback, a free port; it has no authentication)")
    opt.add_argument("--resume", action="store_true", help="continue a killed sweep in --out")
    opt.set_defaults(func=cmd_design_optimise)
    ev = dsub.add_parser("evaluate", help="print the 7 criteria and the constraints of a head")
    ev.add_argument("head", help="head.toml, or 'reference'")
    ev.add_argument("--sweep", help="sweep.toml for the workload and settings (default: the default sweep)")
    ev.set_defaults(func=cmd_design_evaluate)
    cmp_ = dsub.add_parser("compare", help="share of a baseline's evaluations a sweep needs to reach the "
                           "baseline's hypervolume (two evaluations.csv, or their folders)")
    cmp_.add_argument("run", help="the sweep's evaluations.csv (or folder)")
    cmp_.add_argument("baseline", help="the baseline's, e.g. an --algorithm random sweep of the same sweep file")
    cmp_.add_argument("--at", type=_positive_int, default=2520, help="the baseline's budget (default 2520)")
    cmp_.set_defaults(func=cmd_design_compare)
    tpl = dsub.add_parser("sweep-template", help="print the default sweep.toml to start your own")
    tpl.set_defaults(func=cmd_design_template)

    pla = sub.add_parser("placement", help="where on the body to wear the camera: scores, body maps, zones")
    psub = pla.add_subparsers(dest="placement_command", metavar="SUBCOMMAND", required=True)
    pm = psub.add_parser("map", help="score every polygon of a body; write scores.csv, maps, zones.md, mount.toml")
    pm.add_argument("--out", required=True, help="output directory")
    pm.add_argument("--body", help="labelled mesh (OBJ with a group per segment, or PLY with a face label)")
    pm.add_argument("--joints", help="joints JSON for --body: segment name -> joint centre (m)")
    pm.add_argument("--stature", type=_positive, default=1.75, help="stature of the generated body, m (default 1.75)")
    pm.add_argument("--motion", action="append", help="BVH motion file (repeatable); default: walk, sit, turn, reach")
    pm.add_argument("--motion-up", choices=["y", "z"], default="y",
                    help="the BVH files' up axis (default y, as most BVH files)")
    pm.add_argument("--motion-scale", type=_positive, metavar="M",
                    help="metres per BVH unit, e.g. 0.01 for centimetres (default: fitted to the body)")
    pm.add_argument("--allow-missing-joints", action="store_true",
                    help="keep segments no BVH joint drives at rest (default: refuse such files)")
    pm.add_argument("--rays", type=_positive_int, default=2048, help="rays per place for the field of view (default 2048)")
    pm.add_argument("--standoff", type=_nonnegative, default=0.02,
                    help="camera stand-off from the surface, m (default 0.02)")
    pm.set_defaults(func=cmd_placement_map)

    sim = sub.add_parser("sim", help="the MuJoCo twin: record sequences of the wearer and the head")
    ssub = sim.add_subparsers(dest="sim_command", metavar="SUBCOMMAND", required=True)
    rec = ssub.add_parser("record", help="record a scenario as a sequence (TUM layout, camera.toml, target.toml)")
    rec.add_argument("--out", required=True, help="output sequence folder")
    rec.add_argument("--dim-to", type=float, help="dim the lights linearly to this fraction by the end (e.g. 0.3)")
    rec.add_argument("--depth", action="store_true",
                     help="also write the true depth of every frame (depth.txt, depth/<t>.png, TUM RGB-D)")
    rec.add_argument("--scene-seed", type=_nonneg_int, metavar="S",
                     help="fix the place (textures, object layout) apart from --seed (default: --seed); recordings "
                          "of scenarios in one place with one scene seed show the same place")
    rec.add_argument("--ideal-imu", action="store_true",
                     help="an ideal IMU (white noise only) instead of a BMI088's biases, scale errors and clock offset")
    rec.add_argument("--ideal-camera", action="store_true",
                     help="clean renders: no motion blur, auto-exposure or sensor noise")
    rec.add_argument("--click-error", type=_click_error, default=2.5, metavar="PX",
                     help="how far off the operator clicks the target's corners in target.toml, pixels "
                          "(default 2.5; 0: the exact projection)")
    _twin_options(rec, SCENARIOS)
    rec.set_defaults(func=cmd_sim_record)

    run = ssub.add_parser("run", help="closed loop: twin, SLAM and gaze controller (fixate, saccade, Path A, Path B)")
    run.add_argument("--task", required=True, choices=list(TASKS))
    run.add_argument("--target", action="append", type=_point, metavar="X,Y,Z",
                     help="world point to fixate or saccade to, m (repeatable; default for fixate: the scenario's "
                          "known rectangle's centre)")
    run.add_argument("--targets", help="TOML file: targets = [[x, y, z], ...] (world, m), optional dwell_s")
    run.add_argument("--dwell", type=_positive, default=None,
                     help="seconds on each saccade target (default 2), or on each fixation explore chooses (default 1.5)")
    run.add_argument("--limit", type=float, default=MOTION_LIMIT_DEG_S,
                     help="controlled-motion limit on every joint rate, deg/s (default %(default)g; at most the servos')")
    run.add_argument("--init", type=_box, metavar="X,Y,W,H",
                     help="track: the region in the first frame, pixels (default: the known rectangle)")
    run.add_argument("--method", choices=METHODS, default="hyperplane", help="track: the 2D tracker")
    run.add_argument("--recentre", type=_nonnegative, default=0.0, metavar="PER_S",
                     help="stabilise: Path A's visual outer loop, 1/s: the held attitude turns towards where the software fovea wants to look (default 0: the IMU alone)")
    run.add_argument("--click-error", type=_click_error, default=2.5, metavar="PX",
                     help="how far off (px) the simulated person clicks the target's corners for SLAM's start "
                          "(default 2.5; 0: the exact projection)")
    _start_option(run, "the clicked point")
    _glances_option(run)
    _slam_imu_option(run)
    run.add_argument("--out", required=True, help="output directory")
    _session_log_option(run)
    _twin_options(run, SCENARIOS)
    run.set_defaults(func=cmd_sim_run)

    hil = ssub.add_parser("hil", help="hardware in the loop: the twin behind a virtual Maestro, IMU and camera; writes rig.toml")
    hil.add_argument("--out", required=True, help="folder for rig.toml, camera/, target.toml, groundtruth.txt")
    hil.add_argument("--imu", choices=["bno085-rvc", "text"], default="bno085-rvc",
                     help="the IMU stream rig.toml uses (both are served)")
    hil.add_argument("--wait", type=_positive, default=5.0, help="seconds of wall time the world waits for each command")
    hil.add_argument("--linger", type=_nonnegative, default=8.0, help="seconds the board stays up after the run (safe stop)")
    hil.add_argument("--click-error", type=_click_error, default=2.5, metavar="PX",
                     help="how far off (px) the simulated person clicks target.toml's corners (default 2.5)")
    hil.add_argument("--force", action="store_true", help="reuse an --out folder that holds a HIL session")
    hil.add_argument("--quiet", action="store_true", help="no progress bar")
    _twin_options(hil, SCENARIOS)
    hil.set_defaults(func=cmd_sim_hil)

    hd = sub.add_parser("head", help="bring-up of the real head: home, goto E,P,C, sweep; stop / reset the e-stop")
    hd.add_argument("--rig", required=True, help="rig.toml")
    hd.add_argument("action", choices=["home", "goto", "sweep", "stop", "reset"])
    hd.add_argument("angles", nargs="?", help="goto: E,P,C in degrees")
    hd.add_argument("--rate", type=_positive, default=20.0, help="joint speed for the move, deg/s (default 20)")
    hd.add_argument("--timeout", type=_positive, default=30.0, help="seconds to wait for each move")
    hd.set_defaults(func=cmd_head)

    rr = sub.add_parser("run", help="the closed loop on the hardware rig (the tasks of wvr sim run); records the session")
    rr.add_argument("--rig", required=True, help="rig.toml")
    rr.add_argument("--task", required=True, choices=list(TASKS))
    rr.add_argument("--target", action="append", type=_point, metavar="X,Y,Z", help="world point, m (repeatable; "
                    "default for fixate: the start target's centre)")
    rr.add_argument("--targets", help="TOML file: targets = [[x, y, z], ...] (world, m), optional dwell_s")
    rr.add_argument("--dwell", type=_positive, default=None,
                     help="seconds on each saccade target (default 2), or on each fixation explore chooses (default 1.5)")
    _start_option(rr, "the start target's clicked centre, else the image's centre")
    _glances_option(rr)
    _slam_imu_option(rr)
    rr.add_argument("--limit", type=_positive, default=MOTION_LIMIT_DEG_S,
                    help="controlled-motion limit, deg/s (at most rig.toml's)")
    rr.add_argument("--init", type=_box, metavar="X,Y,W,H", help="track: the region in the first frame, pixels")
    rr.add_argument("--method", choices=METHODS, default="hyperplane", help="track: the 2D tracker")
    rr.add_argument("--recentre", type=_nonnegative, default=0.0, metavar="PER_S",
                    help="stabilise: Path A's visual outer loop, 1/s: the held attitude turns towards where the software fovea wants to look (default 0: the IMU alone)")
    rr.add_argument("--start-target", help="target.toml: known points and their pixels in the first image "
                    "(default: rig.toml [start] target)")
    rr.add_argument("--seconds", type=_seconds, help="stop after this long (default: until Ctrl-C or the camera ends)")
    rr.add_argument("--out", required=True, help="output folder (the session's recording and results)")
    _session_log_option(rr)
    rr.set_defaults(func=cmd_run)

    cal = sub.add_parser("calibrate", help="camera intrinsics from board images; IMU still biases into rig.toml")
    cal.add_argument("what", choices=["camera", "imu"])
    cal.add_argument("--images", help="camera: a folder of board images")
    cal.add_argument("--board", help="camera: chessboard:COLSxROWS:SQUARE_M (inner corners), e.g. chessboard:9x6:0.025")
    cal.add_argument("--model", choices=["brown", "fisheye", "radial-sqrt"], default="brown", help="camera: lens model")
    cal.add_argument("--out", default="camera.toml", help="camera: the camera.toml to write")
    cal.add_argument("--rig", help="imu: rig.toml (its [imu] gets the biases)")
    cal.add_argument("--seconds", type=_seconds, default=10.0, help="imu: how long to hold still")
    cal.set_defaults(func=cmd_calibrate)

    stab = sub.add_parser("stabilise", help="visual (and inertial) stabilisation with a software fovea")
    stab.add_argument("seq", help="sequence folder (TUM layout with camera.toml)")
    stab.add_argument("--out", required=True, help="output directory")
    stab.add_argument("--fovea", default="320x240", help="fovea size WxH, pixels (default 320x240)")
    stab.add_argument("--imu", action="store_true", help="use imu.txt's gyro to predict each frame's rotation")
    stab.set_defaults(func=cmd_stabilise)

    trk = sub.add_parser("track", help="2D object tracking (hyperplane planar tracker or mean shift); --servo in the twin")
    trk.add_argument("seq", nargs="?", help="sequence folder (not with --servo)")
    trk.add_argument("--init", type=_box, metavar="X,Y,W,H", help="the target's box in the first frame, pixels")
    trk.add_argument("--method", choices=METHODS, default="hyperplane", help="the 2D tracker")
    trk.add_argument("--out", required=True, help="output directory")
    trk.add_argument("--servo", action="store_true",
                     help="closed loop in the twin: the gaze controller keeps the target centred")
    _twin_options(trk, SCENARIOS, required=False, when="with --servo: ")
    _session_log_option(trk, "with --servo: ")
    trk.set_defaults(func=cmd_track)

    sl = sub.add_parser("slam", help="single-camera EKF SLAM (MonoSLAM) over a sequence folder")
    sl.add_argument("seq", help="sequence folder (TUM layout with camera.toml and target.toml)")
    sl.add_argument("--out", required=True, help="output directory")
    sl.add_argument("--max-frames", type=_positive_int, help="stop after N frames")
    sl.add_argument("--video", action="store_true", help="write annotated frames (features, ellipses, particles) and video.mp4")
    sl.add_argument("--no-imu", action="store_true",
                    help="ignore imu.txt: camera only, the constant-velocity motion model (the paper's system)")
    sl.add_argument("--no-imu-biases", action="store_true",
                    help="with an IMU, take it as calibrated (no gyro and accelerometer bias states)")
    sl.add_argument("--no-imu-handover", action="store_true",
                    help="after a natural start, run camera only and take the IMU's scale after the run instead "
                         "of handing the map to the IMU once it has seen the scale")
    sl.add_argument("--imu-clock-offset", type=_milliseconds, default=0.0, metavar="MS",
                    help="the IMU's stamps' lag behind the camera's, ms, where the filter starts learning it "
                         "(default 0; learnt from 0 up to about 20 ms: give a measured latency beyond)")
    sl.add_argument("--features", choices=["inverse-depth", "particles"], default="inverse-depth",
                    help="how new features start: inverse depth, in the filter from the first frame (default), or "
                         "the paper's particle depth pdf")
    sl.add_argument("--measure", type=_positive_int, default=None, metavar="N",
                    help="features measured per frame, at most (default: MapSettings.measure.measure_max, 60)")
    sl.add_argument("--fixed-impulses", action="store_true",
                    help="predict with MonoSLAM's fixed impulses (4 m/s^2, 6 rad/s^2) instead of adapting them to the "
                         "track's own motion through fast turns (SlamConfig.impulses: adapt_sigma_a, "
                         "adapt_sigma_alpha, adapt_onset)")
    sl.add_argument("--save-map", metavar="FILE", help="save the final map there (.npz) to re-locate in it later")
    sl.add_argument("--map", metavar="FILE",
                    help="start from a saved map instead of target.toml: re-locate in it, continue in its frame")
    _session_log_option(sl)
    sl.set_defaults(func=cmd_slam)
    ev2 = sub.add_parser("eval", help="ATE and RPE of a SLAM result against the sequence's ground truth")
    ev2.add_argument("seq", help="the sequence folder wvr slam read (ours, TUM RGB-D, EuRoC mav0, KITTI), with its "
                     "ground truth")
    ev2.add_argument("result", help="the folder wvr slam wrote (trajectory.tum)")
    ev2.add_argument("--align", choices=["none", "se3", "sim3"], help="the ATE marked * (all three are printed; "
                     "default from the run's scale: none after a target or a saved map, se3 after a depth or IMU "
                     "scale, sim3 when arbitrary)")
    ev2.set_defaults(func=cmd_eval)
    cv = sub.add_parser("convert", help="write a public data set (EuRoC, KITTI odometry) as a sequence folder in our layout")
    cvsub = cv.add_subparsers(dest="format", metavar="FORMAT", required=True)
    cve = cvsub.add_parser("euroc", help="an EuRoC / ASL mav0 folder: cam0, imu0 into the camera frame, the camera's ground truth")
    cve.add_argument("src", help="the mav0 folder (or the folder holding mav0)")
    cve.add_argument("--groundtruth", metavar="FILE",
                     help="the camera's ground truth in ORB-SLAM3's MH01_GT.txt style (CSV: ns, tx, ty, tz, qw, qx, qy, qz) "
                          "instead of state_groundtruth_estimate0 (the body's)")
    cvk = cvsub.add_parser("kitti", help="a KITTI odometry sequence: image_0, times.txt, calib.txt's P0, poses")
    cvk.add_argument("src", help="the sequence folder (image_0/, times.txt, calib.txt)")
    cvk.add_argument("--poses", metavar="FILE",
                     help="the poses file (default: SRC/poses/NN.txt, or the data set's ../../poses/NN.txt)")
    for c in (cve, cvk):
        c.add_argument("--out", required=True, help="the new sequence folder")
        c.add_argument("--copy", action="store_true", help="copy the images (default: symbolic links to them)")
        c.set_defaults(func=cmd_convert)

    stn = sub.add_parser("station", help="the remote operator's web station: live 3D view and camera view, "
                         "click to saccade and fixate, labels, JSON API")
    stn.add_argument("--rig", help="rig.toml: run the hardware (instead of --scenario)")
    _twin_options(stn, SCENARIOS, required=False, when="twin: ")
    stn.add_argument("--host", default="127.0.0.1", help="address to serve on (default loopback; any other needs "
                     "the token, which is always required)")
    stn.add_argument("--port", type=int, default=8080, help="the page and the API (default 8080; the 3D view's "
                     "viser listens on loopback on the next port up)")
    stn.add_argument("--token", help="the access token (default: a new random one, printed once)")
    stn.add_argument("--out", help="folder for the recording when the station stops (trajectory.tum, events.csv, "
                     "labels.toml; groundtruth.txt on the twin)")
    stn.add_argument("--limit", type=float, default=MOTION_LIMIT_DEG_S,
                     help="controlled-motion limit, deg/s (default %(default)g)")
    stn.add_argument("--click-error", type=float, default=2.5, metavar="PX",
                     help="twin: how far off the simulated person clicks the target's corners (default 2.5)")
    _session_log_option(stn, "with --out: ")
    stn.set_defaults(func=cmd_station)

    demo = sub.add_parser("demo", help="run every stage of the pipeline with small budgets; writes DIR/report.md")
    demo.add_argument("--out", required=True, help="output directory")
    demo.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = _with_negative_vectors(list(sys.argv[1:] if argv is None else argv))
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except USER_ERRORS as e:
        print(f"wvr: error: {_short(str(e))}", file=sys.stderr)
        return 2
    except OSError as e:      # a file that cannot be written or read, named by the OS
        where = f"{e.filename}: " if e.filename else ""
        print(f"wvr: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("wvr: interrupted (an output folder it was writing stays marked INCOMPLETE)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
