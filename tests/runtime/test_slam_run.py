"""MonoSLAM end to end over short twin recordings (run_slam), against the recordings' ground
truth, and its handling of bad input.

Two recordings: ``workbench-static`` (the head sweeps the bench: 22 degrees of rotation, under
2 cm of travel) and ``walk`` (53 cm of travel, 9 degrees). The tracking check bounds both the
position and the rotation error of every frame, so an estimator that reports the start pose
every frame fails it on each recording (proved below by monkeypatching it to do so). The start
is from clicks 2-3 px off the target's corners, as a person gives them."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import dataclass, replace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.camera import load_camera, save_camera
from runtime.sequence import SequenceError, load_target, open_sequence, read_trajectory, save_target
from runtime.slam.config import MapSettings
from runtime.eval import associate
from runtime.slam.run import run_slam
from runtime.slam.system import MonoSLAM, SlamStartError
from runtime.twin.recorder import record

try:                                    # the composition root (wvr.assemble in later layouts)
    from wvr.assemble import make_twin
except ImportError:
    from wvr.cli import make_twin

CAMERA_ONLY = MapSettings(use_imu=False)
#: The bounds every tracked frame must meet (the issue's accuracy targets are benchmarks').
MAX_POSITION_M = 0.03
MAX_ROTATION_DEG = 2.0
MAX_ATE_M = 0.015


def recording(tmp_path_factory, scenario: str, seed: int):
    out = tmp_path_factory.mktemp("seq") / scenario
    twin = make_twin()
    try:
        record(twin, scenario, out, seconds=2.0, seed=seed, progress=False)
    finally:
        twin.close()
    # The target's corners as a person clicks them: 2-3 px off the recorder's pixels.
    target = load_target(out / "target.toml")
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, len(target.uv))
    target.uv += rng.uniform(2.0, 3.0, (len(a), 1)) * np.column_stack([np.cos(a), np.sin(a)])
    save_target(target, out / "target.toml")
    return out


@pytest.fixture(scope="module")
def static_seq(tmp_path_factory):
    return recording(tmp_path_factory, "workbench-static", 4)


@pytest.fixture(scope="module")
def walk_seq(tmp_path_factory):
    return recording(tmp_path_factory, "walk", 4)


@dataclass(frozen=True)
class Tracking:
    frames: int
    ate_m: float
    max_position_m: float
    max_rotation_deg: float
    truth_travel_m: float
    truth_turn_deg: float


def tracking(out, seq) -> Tracking:
    """Every estimated pose against the ground truth at its time (no alignment: the target fixes
    the frame), and how far the truth itself moved and turned from its first pose."""
    est = read_trajectory(out / "trajectory.tum")
    gt = open_sequence(seq).groundtruth
    ie, ig = associate(est, gt)
    assert len(ie) == len(est)
    e_pos = np.linalg.norm(est.p_world_cam[ie] - gt.p_world_cam[ig], axis=1)
    Re, Rg = est.R_world_cam()[ie], gt.R_world_cam()[ig]
    e_rot = np.degrees(Rotation.from_matrix(np.swapaxes(Re, 1, 2) @ Rg).magnitude())
    G = gt.R_world_cam()
    turn = np.degrees(Rotation.from_matrix(np.swapaxes(G[:1], 1, 2) @ G).magnitude())
    return Tracking(len(ie), float(np.sqrt(np.mean(e_pos**2))), float(e_pos.max()), float(e_rot.max()),
                    float(np.linalg.norm(gt.p_world_cam - gt.p_world_cam[0], axis=1).max()), float(turn.max()))


def assert_tracks(tr: Tracking, frames: int) -> None:
    assert tr.frames == frames, tr
    assert tr.ate_m < MAX_ATE_M, tr
    assert tr.max_position_m < MAX_POSITION_M, tr
    assert tr.max_rotation_deg < MAX_ROTATION_DEG, tr


def start_pose_only(monkeypatch) -> None:
    """Make the estimator report its start pose every frame (the estimate itself runs on)."""
    first = {}
    original = MonoSLAM.T_world_cam

    def frozen(self):
        T = original(self)
        return first.setdefault(id(self), T) if np.isfinite(T).all() else T

    monkeypatch.setattr(MonoSLAM, "T_world_cam", frozen)


# -- tracking ------------------------------------------------------------------------------------

@pytest.mark.slow
def test_tracks_a_rotating_head_camera_only(static_seq, tmp_path):
    res = run_slam(static_seq, tmp_path, progress=False, video=True, settings=CAMERA_ONLY)
    tr = tracking(tmp_path, static_seq)
    print(f"\nworkbench-static: {tr}, {res.mean_matched:.1f} matched per frame")
    assert tr.truth_turn_deg > 10 * MAX_ROTATION_DEG        # the check can tell a frozen pose
    assert_tracks(tr, 60)
    assert not res.lost and res.frames == 60 and res.skipped == 0 and res.imu_frames == 0
    assert res.mean_matched >= 10 and res.features > 10
    cap = cv2.VideoCapture(str(tmp_path / "video.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 60 and len(list((tmp_path / "video").glob("*.png"))) == 60
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert len(stats["frames"]) == 60 and stats["totals"]["mean_matched"] == res.mean_matched
    rows = (tmp_path / "map.csv").read_text().splitlines()
    assert rows[0].startswith("id,kind,x,y,z,P00") and len(rows) == res.features + 1
    assert {r.split(",")[1] for r in rows[1:]} <= {"point", "inverse-depth"}


@pytest.mark.slow
@pytest.mark.parametrize("use_imu", [False, True], ids=["camera-only", "imu"])
def test_tracks_a_walk(walk_seq, tmp_path, use_imu):
    res = run_slam(walk_seq, tmp_path, progress=False, settings=replace(CAMERA_ONLY, use_imu=use_imu))
    tr = tracking(tmp_path, walk_seq)
    print(f"\nwalk ({'imu' if use_imu else 'camera only'}): {tr}, {res.mean_matched:.1f} matched per frame")
    assert tr.truth_travel_m > 10 * MAX_POSITION_M
    assert_tracks(tr, 60)
    assert not res.lost
    assert (res.imu_frames > 50) == use_imu


@pytest.mark.slow
@pytest.mark.parametrize("which", ["static", "walk"])
def test_an_estimator_reporting_the_start_pose_fails_the_check(which, static_seq, walk_seq, tmp_path, monkeypatch):
    seq = static_seq if which == "static" else walk_seq
    start_pose_only(monkeypatch)
    run_slam(seq, tmp_path, progress=False, settings=CAMERA_ONLY)
    poses = read_trajectory(tmp_path / "trajectory.tum")
    assert np.ptp(poses.p_world_cam, axis=0).max() == 0             # it did report one pose
    tr = tracking(tmp_path, seq)
    with pytest.raises(AssertionError):
        assert_tracks(tr, 60)
    # Each recording fails it on its own count: the rotation for the static head, the
    # position for the walk.
    if which == "static":
        assert tr.max_rotation_deg > 5 * MAX_ROTATION_DEG
    else:
        assert tr.max_position_m > 5 * MAX_POSITION_M


@pytest.mark.slow
def test_the_papers_particle_initialisation_tracks_too(static_seq, tmp_path):
    res = run_slam(static_seq, tmp_path, progress=False, settings=replace(CAMERA_ONLY, features="particles"))
    assert_tracks(tracking(tmp_path, static_seq), 60)
    frames = json.loads((tmp_path / "stats.json").read_text())["frames"]
    assert not res.lost and max(f["initialising"] for f in frames) > 0 and res.added > 0
    kinds = {r.split(",")[1] for r in (tmp_path / "map.csv").read_text().splitlines()[1:]}
    assert kinds == {"point"}                                     # rays become points, never inverse depth


# -- frames that cannot be read, a lost track -----------------------------------------------------

def copy_of(seq, tmp_path):
    dst = tmp_path / "seq"
    shutil.copytree(seq, dst)
    return dst


@pytest.mark.slow
def test_a_corrupt_frame_is_skipped_counted_and_named(static_seq, tmp_path, capsys):
    seq = copy_of(static_seq, tmp_path)
    bad = open_sequence(seq).paths[10]
    bad.write_bytes(b"not a png")
    res = run_slam(seq, tmp_path / "out", max_frames=30, progress=False, settings=CAMERA_ONLY)
    assert res.skipped == 1 and res.frames == 30
    frames = json.loads((tmp_path / "out" / "stats.json").read_text())["frames"]
    assert "not a readable image" in frames[10]["skipped"]
    assert not any(f["skipped"] for i, f in enumerate(frames) if i != 10)
    said = capsys.readouterr().out
    assert f"frame 10 ({bad.name}, t = " in said and "skipped" in said
    # Predicted through the bad frame, tracked on.
    assert_tracks(tracking(tmp_path / "out", seq), 30)


@pytest.mark.slow
def test_frames_the_recorder_dropped_are_counted_and_tracked_through(walk_seq, tmp_path):
    """Runs of 2, 4 and 1 frames missing from rgb.txt (a recorder under load): the gaps are
    counted, and the prediction spans them (white accelerations: a 5-frame step is not taken as
    25 frames' worth of variance, whose ellipses would pass searching)."""
    seq = copy_of(walk_seq, tmp_path)
    lines = (seq / "rgb.txt").read_text().splitlines(keepends=True)
    head = [ln for ln in lines if ln.startswith("#")]
    rows = [ln for ln in lines if not ln.startswith("#")]
    missing = {12, 13, 30, 31, 32, 33, 45}
    (seq / "rgb.txt").write_text("".join(head + [r for i, r in enumerate(rows) if i not in missing]))
    res = run_slam(seq, tmp_path / "out", progress=False, settings=CAMERA_ONLY)
    t = open_sequence(walk_seq).timestamps
    assert res.frame_gaps == 3 and res.longest_interval_s == pytest.approx(t[34] - t[29])
    tr = tracking(tmp_path / "out", seq)
    print(f"\nwalk with {len(missing)} frames missing: {tr}")
    assert_tracks(tr, len(rows) - len(missing))
    assert not res.lost


def blacken(seq, first: int, last: int) -> None:
    for p in open_sequence(seq).paths[first:last]:
        cv2.imwrite(str(p), np.zeros_like(cv2.imread(str(p))))



@pytest.mark.slow
@pytest.mark.parametrize("use_imu", [False, True], ids=["camera-only", "imu"])
def test_a_lost_track_is_said_and_found_again_in_the_maps_frame(static_seq, tmp_path, capsys, use_imu):
    seq = copy_of(static_seq, tmp_path)
    blacken(seq, 12, 30)                       # the lens covered for 18 frames (0.6 s)
    res = run_slam(seq, tmp_path / "out", progress=False, settings=replace(CAMERA_ONLY, use_imu=use_imu))
    frames = json.loads((tmp_path / "out" / "stats.json").read_text())["frames"]
    lost = [f["lost"] for f in frames]
    assert res.lost and res.lost_frames >= 5 and any(lost[20:30]), lost       # counted, in stats.json
    assert not any(lost[40:]), lost                                              # and over once the view is back
    said = capsys.readouterr().out
    assert "track lost at frame" in said and "camera located in the map at frame" in said
    if not use_imu:
        # Camera only, the pose has drifted in the dark: the whole-image relocaliser finds it.
        assert any(f["relocalised"] for f in frames[29:40])
    # Back in the map's own frame: no jump, the error bounded.
    est = read_trajectory(tmp_path / "out" / "trajectory.tum")
    gt = open_sequence(seq).groundtruth
    ie, ig = associate(est, gt)
    late = est.t[ie] >= gt.t[45]
    err = np.linalg.norm(est.p_world_cam[ie][late] - gt.p_world_cam[ig][late], axis=1)
    assert late.sum() >= 14 and err.max() < MAX_POSITION_M, err


@pytest.mark.slow
def test_a_pose_the_map_does_not_confirm_leaves_the_track_lost(walk_seq, tmp_path, monkeypatch):
    import runtime.slam.relocalisation as relocalisation
    from runtime.slam.relocalise import Relocalisation

    seq = copy_of(walk_seq, tmp_path)
    blacken(seq, 12, 30)
    # Every re-acquisition proposes a pose 1 m off: the active search cannot confirm it.
    proposed = []

    def wrong_pose(*args, **kw):
        proposed.append(1)
        return Relocalisation(np.eye(3), np.array([1.0, 1.0, 1.0]), np.arange(4))

    monkeypatch.setattr(relocalisation, "relocalise", wrong_pose)
    run_slam(seq, tmp_path / "out", progress=False, settings=CAMERA_ONLY)
    frames = json.loads((tmp_path / "out" / "stats.json").read_text())["frames"]
    assert len(proposed) >= 5                     # the relocaliser was asked, and proposed
    first = next(i for i, f in enumerate(frames) if f["lost"])
    assert all(f["lost"] for f in frames[first:]), [f["lost"] for f in frames]
    # From the first frame processed as lost on, the map stays frozen.
    assert not any(f["relocalised"] or f["added"] or f["deleted"] for f in frames[first + 1:])


# -- map reuse -----------------------------------------------------------------------------------

@pytest.mark.slow
def test_a_saved_map_relocalises_a_second_run_without_a_target(static_seq, tmp_path):
    run_slam(static_seq, tmp_path / "first", progress=False, settings=CAMERA_ONLY, save_map=tmp_path / "bench.npz")
    seq = copy_of(static_seq, tmp_path)
    (seq / "target.toml").unlink()
    res = run_slam(seq, tmp_path / "second", progress=False, settings=CAMERA_ONLY, map_path=tmp_path / "bench.npz")
    assert res.first_localised_s is not None and res.first_localised_s < 1.0
    tr = tracking(tmp_path / "second", seq)
    assert tr.max_position_m < MAX_POSITION_M and tr.max_rotation_deg < MAX_ROTATION_DEG, tr


# -- bad input -----------------------------------------------------------------------------------

def bad_inputs(seq, tmp_path) -> dict:
    """Sequences (and options) that must be refused before any work, each with its message."""
    cases = {}
    cases["max frames 0"] = (seq, {"max_frames": 0}, ValueError, r"--max-frames 0: give at least 1 frame")
    empty = copy_of(seq, tmp_path / "empty")
    (empty / "rgb.txt").write_text("# timestamp filename\n")
    cases["empty rgb.txt"] = (empty, {}, SequenceError, r"rgb.txt lists no images")
    lens = copy_of(seq, tmp_path / "lens")
    # Strong barrel distortion: the forward map folds over before the image's corners.
    save_camera(replace(load_camera(lens / "camera.toml"), k1=-0.6), lens / "camera.toml")
    cases["lens"] = (lens, {}, SequenceError, r"distortion has no inverse over the whole image")
    no_target = copy_of(seq, tmp_path / "no_target")
    (no_target / "target.toml").unlink()
    # No target and a still view: the natural start waits for parallax that never comes.
    cases["no target"] = (no_target, {}, SlamStartError, r"no start could be made from natural features")
    swapped = copy_of(seq, tmp_path / "swapped")
    t = load_target(swapped / "target.toml")
    t.xyz[[0, 1]] = t.xyz[[1, 0]]              # xyz in another order than the clicks
    save_target(t, swapped / "target.toml")
    cases["target fits no pose"] = (swapped, {}, SlamStartError, r"(do not fit one camera pose|no camera pose in front)")
    return cases


def test_bad_input_is_refused_in_one_line_before_any_work(static_seq, tmp_path):
    for name, (seq, kw, error, message) in bad_inputs(static_seq, tmp_path).items():
        out = tmp_path / "out" / name.replace(" ", "_")
        with pytest.raises(error, match=message) as e:
            run_slam(seq, out, progress=False, settings=CAMERA_ONLY, **kw)
        assert "\n" not in str(e.value), (name, str(e.value))
        if name != "target fits no pose":           # refused before the outputs are touched
            assert not out.exists(), name


def test_wvr_slam_says_bad_input_in_one_line_with_exit_2(static_seq, tmp_path, capsys):
    from wvr.cli import main

    for name, (seq, kw, _, message) in bad_inputs(static_seq, tmp_path).items():
        argv = ["slam", str(seq), "--out", str(tmp_path / "out" / name.replace(" ", "_"))]
        if "max_frames" in kw:
            argv += ["--max-frames", str(kw["max_frames"])]
        try:
            code = main(argv)
        except SystemExit as e:            # an option's value refused by the parser: also one line
            code = e.code
        assert code == 2, name
        err = capsys.readouterr().err.strip()
        assert err.startswith("wvr") and "error:" in err and "\n" not in err, (name, err)
        if "max_frames" not in kw:
            assert re.search(message, err), (name, err)


@pytest.mark.slow
def test_the_imus_clock_offset_is_estimated_through_the_whole_run(walk_seq, tmp_path):
    """The walk's IMU stamps moved 15 ms later (a sample taken at camera time t stamped t +
    15 ms, as a host stamping on arrival does): the run's estimated clock offset moves by the
    same, within 4 ms after these 2 s (it is still converging), and the walk still tracks; a
    no-op or a wrong sign fails."""
    import shutil

    late = tmp_path / "late"
    shutil.copytree(walk_seq, late)
    rows = np.loadtxt(walk_seq / "imu.txt", comments="#")
    rows[:, 0] += 0.015
    np.savetxt(late / "imu.txt", rows, fmt="%.9f", header="timestamp wx wy wz ax ay az  (rad/s, m/s^2, camera frame)")
    imu = replace(CAMERA_ONLY, use_imu=True)
    a = run_slam(walk_seq, tmp_path / "a", progress=False, settings=imu)
    b = run_slam(late, tmp_path / "b", progress=False, settings=imu)
    print(f"\nclock offset {1000 * a.imu_clock_offset_s:.2f} ms, with the stamps 15 ms late "
          f"{1000 * b.imu_clock_offset_s:.2f} ms (sd {1000 * b.imu_clock_offset_sd_s:.2f})")
    assert abs((b.imu_clock_offset_s - a.imu_clock_offset_s) - 0.015) < 0.004
    assert b.imu_frames > 50 and not b.lost
    assert_tracks(tracking(tmp_path / "b", late), 60)
    stats = json.loads((tmp_path / "b" / "stats.json").read_text())["totals"]
    assert stats["imu_clock_offset_s"] == b.imu_clock_offset_s


@pytest.mark.slow
def test_a_measured_latency_starts_the_clock_offset_where_learning_from_zero_fails(walk_seq, tmp_path, capsys):
    """IMU stamps 50 ms late are beyond what the filter learns from zero; given as the start
    (`wvr slam --imu-clock-offset 50`), the walk tracks and the estimate ends at the same
    offset plus what the unshifted run learnt. A flag that does not reach the filter, or
    its units taken as seconds, fails here."""
    import shutil

    from wvr.cli import main

    late = tmp_path / "late"
    shutil.copytree(walk_seq, late)
    rows = np.loadtxt(walk_seq / "imu.txt", comments="#")
    rows[:, 0] += 0.050
    np.savetxt(late / "imu.txt", rows, fmt="%.9f", header="timestamp wx wy wz ax ay az  (rad/s, m/s^2, camera frame)")
    a = run_slam(walk_seq, tmp_path / "a", progress=False, settings=replace(CAMERA_ONLY, use_imu=True))
    assert main(["slam", str(late), "--out", str(tmp_path / "b"), "--imu-clock-offset", "50"]) == 0
    assert "IMU clock offset" in capsys.readouterr().out
    b = json.loads((tmp_path / "b" / "stats.json").read_text())["totals"]
    print(f"\nclock offset {1000 * a.imu_clock_offset_s:.2f} ms; stamps 50 ms late, started at 50: "
          f"{1000 * b['imu_clock_offset_s']:.2f} ms")
    assert abs((b["imu_clock_offset_s"] - a.imu_clock_offset_s) - 0.050) < 0.004
    assert not b["lost"] and b["imu_frames"] > 50
    assert_tracks(tracking(tmp_path / "b", late), 60)
    # A number that is not one is refused by the parser in one line.
    with pytest.raises(SystemExit) as e:
        main(["slam", str(late), "--out", str(tmp_path / "c"), "--imu-clock-offset", "abc"])
    assert e.value.code == 2 and "--imu-clock-offset" in capsys.readouterr().err
