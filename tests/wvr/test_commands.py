"""Every subcommand of the README run as a user runs it (a subprocess), and the defects a user
hit with them: vectors, negative numbers, output folders, half-written results, bad options.

One short recording (1 s of workbench-static, with depth) made by ``wvr sim record`` feeds
``slam``, ``eval``, ``stabilise`` and ``track``; every run is kept small (``--seconds 1``, a few
evaluations, few rays) so that the whole file stays well under a minute and a half.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tomli_w

pytestmark = pytest.mark.slow

ROOT = Path(__file__).parents[2]


def wvr(*args, timeout=240):
    env = dict(os.environ, MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl")
    return subprocess.run([sys.executable, "-m", "wvr", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


class _Result:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


def in_process(capsys, *args):
    """The command run in this process (as main() runs it for the console script): for the
    checks that need no fresh interpreter, which costs seconds on a busy machine."""
    from wvr.cli import main

    capsys.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as e:          # argparse's errors
        code = e.code
    out, err = capsys.readouterr()
    return _Result(code, out, err)


def one_line_error(r, *words):
    """Exit status 2, one line on stderr, no traceback, the words in it."""
    assert r.returncode == 2, (r.returncode, r.stdout[-500:], r.stderr[-2000:])
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in r.stderr, (w, r.stderr)
    return r.stderr


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "static"
    r = wvr("sim", "record", "--scenario", "workbench-static", "--seconds", "1", "--depth", "--out", out)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "recorded workbench-static" in r.stdout
    assert not (out / "INCOMPLETE").exists() and (out / "depth.txt").exists()
    return out


@pytest.fixture(scope="module")
def slam_result(seq, tmp_path_factory):
    out = tmp_path_factory.mktemp("slam") / "run"
    r = wvr("slam", seq, "--out", out)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "frames" in r.stdout and (out / "trajectory.tum").exists() and not (out / "INCOMPLETE").exists()
    return out


# -- kinematics ---------------------------------------------------------------------------------

def test_kinematics_show_mjcf_ik_picture(tmp_path, capsys):
    import json

    r = in_process(capsys, "kinematics", "show", "reference", "--json", "--directions", "100")
    assert r.returncode == 0 and isinstance(json.loads(r.stdout), dict), r.stderr
    r = in_process(capsys, "kinematics", "mjcf", "reference")
    assert r.returncode == 0 and r.stdout.lstrip().startswith("<mujoco")
    # Negative numbers as the README writes them, with and without '='.
    r = in_process(capsys, "kinematics", "ik", "reference", "--target", "1,0.2,0", "--current", "-10,0,0")
    assert r.returncode == 0 and "q_deg" in r.stdout, r.stderr
    r = in_process(capsys, "kinematics", "ik", "reference", "--point", "--target", "-1.35,-0.6,0.85")
    assert r.returncode == 1 and r.stdout.startswith("unreachable"), r.stderr
    # Far points: the joint that blocks, not "too close".
    r = in_process(capsys, "kinematics", "ik", "reference", "--point", "--target", "0,1e9,0")
    assert r.returncode == 1 and "pan would need" in r.stdout and "too close" not in r.stdout
    r = in_process(capsys, "kinematics", "ik", "reference", "--point", "--target", "1e9,0,0")
    assert r.returncode == 0 and "q_deg" in r.stdout
    ik = ("kinematics", "ik", "reference")
    one_line_error(in_process(capsys, *ik, "--target", "1,0,0", "--current", "10,nan,0"), "finite")
    one_line_error(in_process(capsys, *ik, "--target", "1,0,0", "--current", "500,0,0"),
                   "elevation = 500 deg is outside its range")
    one_line_error(in_process(capsys, *ik, "--target", "1,0"), "3 components X,Y,Z")
    r = in_process(capsys, *ik, "--target", "-1,0.1,0", "--current", "-10,-5,0")
    assert r.returncode == 1 and "unreachable" in r.stdout
    # picture: a .png path, or a folder; anything else is refused before rendering.
    r = wvr("kinematics", "picture", "reference", "--out", tmp_path, "--posture", "-30,-60,-25")
    assert r.returncode == 0 and r.stdout.strip() == f"wrote {tmp_path / 'head.png'}"
    assert (tmp_path / "head.png").stat().st_size > 1000
    one_line_error(in_process(capsys, "kinematics", "picture", "reference", "--out", tmp_path / "nosuffix"),
                   "ending in .png")
    assert not (tmp_path / "nosuffix.png").exists()


def test_head_file_errors_are_short(tmp_path):
    from kinematics import reference_head

    d = reference_head().to_dict()
    d["joints"]["pan"]["origin_m"] = [0.0] * 1_000_000      # a 5 MB line before the cut
    huge = tmp_path / "huge.toml"
    huge.write_text(tomli_w.dumps(d))
    msg = one_line_error(wvr("kinematics", "show", huge), "joints.pan.origin_m")
    assert len(msg) < 400
    d = reference_head().to_dict()
    d["parts"][0]["mass_kg"] = float("inf")
    inf = tmp_path / "inf.toml"
    inf.write_text(tomli_w.dumps(d))
    msg = one_line_error(wvr("kinematics", "show", inf), "not a finite number")
    assert "negative" not in msg


# -- design -------------------------------------------------------------------------------------

def _tiny_sweep(tmp_path, name="sweep.toml", **sweep):
    from dataclasses import replace

    from design.sweep_file import dump_spec, load_sweep, spec_to_dict

    s = load_sweep()
    s = replace(s, name="tiny", evaluations=7, partitions=1, voxel_m=0.008, collision_steps=4,
                workload=replace(s.workload, saccade_amplitudes_deg=(10.0,), walk_seconds=0.3, rate_hz=40.0))
    d = spec_to_dict(s)
    d["sweep"].update(sweep)
    path = tmp_path / name
    path.write_text(tomli_w.dumps(d) if sweep else dump_spec(s))
    return path


def test_design_optimise_evaluate_template(tmp_path, capsys):
    r = in_process(capsys, "design", "sweep-template")
    assert r.returncode == 0 and "[sweep]" in r.stdout
    sweep = _tiny_sweep(tmp_path)
    r = in_process(capsys, "design", "evaluate", "reference", "--sweep", sweep)
    assert r.returncode == 0 and "max_torque_nm" in r.stdout
    out = tmp_path / "out"
    r = wvr("design", "optimise", "--sweep", sweep, "--out", out)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "7 evaluations (7 computed now, 0 reused)" in r.stdout
    assert (out / "report.md").exists() and not (out / "INCOMPLETE").exists()
    if "chosen head:" in r.stdout:
        assert (out / "chosen_head.toml").exists()
    # Options refused up front, one line each, in seconds.
    t0 = time.perf_counter()
    opt = ("design", "optimise", "--sweep", sweep, "--out", tmp_path / "a")
    one_line_error(in_process(capsys, *opt, "--evaluations", "0"), "--evaluations", "above 0")
    one_line_error(in_process(capsys, *opt, "--workers", "0"), "--workers")
    one_line_error(wvr(*opt, "--scheduler", "tcp://127.0.0.1:9"), "no Dask scheduler answered")
    one_line_error(in_process(capsys, "design", "optimise", "--sweep", _tiny_sweep(tmp_path, "bad.toml", clearance_m=-1.0),
                              "--out", tmp_path / "a"), "clearance_m = -1.0 must be >= 0")
    assert time.perf_counter() - t0 < 60 and not (tmp_path / "a").exists()
    one_line_error(in_process(capsys, "design", "optimise", "--sweep", sweep, "--out", out), "already holds a sweep",
                   "--resume")


# -- placement ----------------------------------------------------------------------------------

def test_placement_map_with_a_bvh_missing_a_joint(tmp_path):
    sys.path.insert(0, str(ROOT / "tests" / "placement"))
    from placement.body import make_body
    from test_io import _standing, _write_bvh

    body = make_body()
    bvh = _write_bvh(tmp_path / "nofoot.bvh", body, [_standing()] * 4, rename={"LeftFoot": "LeftPaw"})
    msg = one_line_error(wvr("placement", "map", "--out", tmp_path / "m", "--motion", bvh, "--rays", "16"),
                         "['foot_l']", "--allow-missing-joints")
    assert not (tmp_path / "m").exists()
    r = wvr("placement", "map", "--out", tmp_path / "m", "--motion", bvh, "--rays", "16", "--allow-missing-joints")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "LeftPaw" in r.stdout and "shoulder" in r.stdout and (tmp_path / "m" / "mount.toml").exists()
    assert not (tmp_path / "m" / "INCOMPLETE").exists()
    del msg


# -- the twin and the closed loop ---------------------------------------------------------------

def test_sim_run_saccade_with_negative_and_far_targets(tmp_path, capsys):
    out = tmp_path / "run"
    r = wvr("sim", "run", "--scenario", "workbench-static", "--task", "saccade", "--target", "-0.1,0.45,0.86",
            "--target", "1e9,0,0", "--dwell", "0.3", "--seconds", "1", "--out", out)
    assert r.returncode in (0, 1), r.stderr[-2000:]
    assert (out / "report.md").exists() and not (out / "INCOMPLETE").exists()
    if r.returncode == 1:   # a refusal names the blocking joint, never "too close" for a far point
        assert "too close" not in r.stdout
    msg = one_line_error(in_process(capsys, "sim", "run", "--scenario", "workbench-static", "--task", "fixate",
                                    "--limit", "1000", "--seconds", "1", "--out", tmp_path / "x"),
                         "--limit 1000 deg/s", "deg/s")
    assert "rad/s" not in msg and "motion_limit" not in msg and not (tmp_path / "x").exists()


def test_track_servo_closed_loop(tmp_path):
    r = wvr("track", "--servo", "--scenario", "workbench-card", "--seconds", "0.3", "--out", tmp_path / "t")
    assert r.returncode in (0, 1), r.stderr[-2000:]
    assert (tmp_path / "t" / "report.md").exists()
    r = wvr("sim", "run", "--scenario", "workbench-card", "--task", "track", "--init", "250,180,140,110",
            "--method", "hyperplane", "--seconds", "0.3", "--out", tmp_path / "t2")
    assert r.returncode in (0, 1) and "must have three components" not in r.stderr, r.stderr[-2000:]


def test_seconds_must_be_positive(tmp_path, capsys):
    for s in ("0", "-1"):
        one_line_error(in_process(capsys, "sim", "record", "--scenario", "walk", "--seconds", s, "--out",
                                  tmp_path / "r"), "--seconds", "above 0")
    assert not (tmp_path / "r").exists()


def test_outputs_checked_before_the_work(tmp_path, seq, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    for args in (("slam", seq, "--out", f), ("sim", "run", "--scenario", "workbench-static", "--task", "fixate",
                                               "--seconds", "1", "--out", f),
                 ("stabilise", seq, "--out", f), ("placement", "map", "--out", f, "--rays", "16"),
                 ("sim", "record", "--scenario", "walk", "--seconds", "1", "--out", f),
                 ("design", "optimise", "--sweep", _tiny_sweep(tmp_path), "--out", f)):
        t0 = time.perf_counter()
        one_line_error(in_process(capsys, *args), "is a file")
        assert time.perf_counter() - t0 < 20, args     # refused up front, not after the run
    # A place nobody can write (even root): one line, not an OSError traceback.
    one_line_error(wvr("slam", seq, "--out", "/proc/wvr-out"), "/proc/wvr-out")


# -- sequences: slam, eval, stabilise, track ----------------------------------------------------

def test_slam_and_eval(seq, slam_result):
    r = wvr("eval", seq, slam_result)
    assert r.returncode == 0, r.stderr
    assert "ATE (no alignment)" in r.stdout and "map against the true depth" in r.stdout
    assert "nan" not in r.stdout
    # A 1 s recording cannot give a 1 s RPE: said, not "nan".
    assert "RPE over 1 s: cannot be computed" in r.stdout


def test_eval_skips_and_counts_an_8_bit_depth_image(seq, slam_result, tmp_path, capsys):
    import shutil

    import cv2

    copy = tmp_path / "seq"
    shutil.copytree(seq, copy)
    first = sorted((copy / "depth").glob("*.png"))[0]          # the frame the target's features start in
    cv2.imwrite(str(first), (cv2.imread(str(first), cv2.IMREAD_UNCHANGED) // 256).astype(np.uint8))
    r = in_process(capsys, "eval", copy, slam_result)
    assert r.returncode == 0, r.stderr
    assert "ATE (no alignment)" in r.stdout and "map against the true depth" in r.stdout
    assert r.stderr.count("\n") == 1 and "warning: 1 depth images skipped" in r.stderr
    assert f"{first.name}: the image is 8-bit, not a 16-bit grey depth image" in r.stderr


def test_eval_warns_when_the_ground_truth_covers_a_third(tmp_path):
    from kinematics.camera import CameraIntrinsics
    from runtime.sequence import SequenceWriter, write_trajectory

    cam = CameraIntrinsics(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    t = np.arange(90) / 30.0
    with SequenceWriter(tmp_path / "seq", cam) as w:
        for ti in t:
            w.add_frame(ti, np.zeros((24, 32), np.uint8))
        for ti in t[:30]:
            T = np.eye(4)
            T[0, 3] = 0.1 * ti
            w.add_groundtruth(ti, T)
    T = np.tile(np.eye(4), (90, 1, 1))
    T[:, 0, 3] = 0.1 * t
    (tmp_path / "res").mkdir()
    write_trajectory(tmp_path / "res" / "trajectory.tum", t, T)
    r = wvr("eval", tmp_path / "seq", tmp_path / "res")
    assert r.returncode == 0, r.stderr
    assert "poses matched: 30 of 90" in r.stdout
    assert "warning: the ground truth covers only 30 of the 90 estimated poses (33%)" in r.stderr
    assert "RPE over 1 s: cannot be computed" in r.stdout     # the matched third spans under 1 s


def test_stabilise_and_track(seq, tmp_path):
    import tomllib

    r = wvr("stabilise", seq, "--out", tmp_path / "s", "--fovea", "320x240")
    assert r.returncode == 0, r.stderr[-2000:]
    assert '"frames": 30' in r.stdout and (tmp_path / "s" / "rotations.tum").exists()
    uv = np.array([p["uv"] for p in tomllib.loads((seq / "target.toml").read_text())["point"]])
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    box = ",".join(f"{v:.0f}" for v in (*lo, *(hi - lo)))
    for method in ("hyperplane", "meanshift"):
        r = wvr("track", seq, "--init", box, "--method", method, "--out", tmp_path / method)
        if method == "meanshift" and r.returncode == 2:
            assert "colour" in r.stderr      # the black rectangle has no colour to track: said so
            continue
        assert r.returncode == 0, r.stderr[-2000:]
        assert '"frames": 30' in r.stdout and (tmp_path / method / "polygons.csv").exists()
    one_line_error(wvr("track", seq, "--init", "10,10,50", "--out", tmp_path / "x"), "X,Y,W,H")
    r = wvr("track", seq, "--out", tmp_path / "y")
    one_line_error(r, "--init X,Y,W,H is required")


def test_a_killed_recording_is_refused_by_slam_and_eval(tmp_path, seq, slam_result):
    out = tmp_path / "killed"
    env = dict(os.environ, MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl")
    p = subprocess.Popen([sys.executable, "-m", "wvr", "sim", "record", "--scenario", "workbench-static",
                          "--seconds", "6", "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         env=env)
    deadline = time.time() + 120
    while time.time() < deadline:
        if (out / "rgb.txt").exists() and len((out / "rgb.txt").read_text().splitlines()) > 10:
            break
        time.sleep(0.1)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    assert (out / "INCOMPLETE").exists()
    one_line_error(wvr("slam", out, "--out", tmp_path / "s"), "incomplete", "stopped before the end")
    one_line_error(wvr("eval", out, slam_result), "incomplete")
    assert not (tmp_path / "s").exists()
    # And a SLAM result folder that is not finished is refused by eval.
    (slam_result / "INCOMPLETE").write_text("")
    try:
        one_line_error(wvr("eval", seq, slam_result), "SLAM result is incomplete")
    finally:
        (slam_result / "INCOMPLETE").unlink()
