"""wvr slam with no target and no saved map: it starts from natural features (two views, or the
first depth image), waits and says why while it cannot, and never invents a map."""

import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

import slam_testing
from runtime.eval import trajectory_errors
from runtime.sequence import open_sequence, read_trajectory
from runtime.slam.config import MapSettings
from runtime.slam.run import run_slam
from runtime.slam.system import SlamStartError
from runtime.twin.recorder import record
from wvr.assemble import make_twin

CAMERA_ONLY = MapSettings(use_imu=False)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """A 3 s walk with the twin's depth images, and copies of it without the target (and without
    the depth, or with its first frames blanked)."""
    root = tmp_path_factory.mktemp("anywhere")
    src = root / "src"
    twin = make_twin()
    try:
        record(twin, "walk", src, seconds=3.0, seed=5, progress=False, depth=True)
    finally:
        twin.close()
    copies = {}
    for name, drop in (("two_view", ("target.toml", "depth", "depth.txt", "imu.txt")),
                       ("two_view_imu", ("target.toml", "depth", "depth.txt")),
                       ("depth", ("target.toml", "imu.txt"))):
        shutil.copytree(src, root / name, ignore=shutil.ignore_patterns(*drop))
        copies[name] = root / name
    return src, copies


def _scores(out, src):
    totals = json.loads((out / "stats.json").read_text())["totals"]
    return totals, trajectory_errors(read_trajectory(out / "trajectory.tum"), open_sequence(src).groundtruth)


@pytest.mark.slow
def test_two_view_start_tracks_a_walk_up_to_scale(walk, tmp_path):
    src, seqs = walk
    r = run_slam(seqs["two_view"], tmp_path / "out", settings=CAMERA_ONLY, progress=False)
    totals, e = _scores(tmp_path / "out", src)
    assert totals["scale"] == "arbitrary" and r.lost_frames == 0
    # Frames before the start get no pose; every frame from it on does.
    n = len(open_sequence(src))
    assert r.frames_before_start + r.frames == n and r.frames_before_start < 30
    assert e.matched == r.frames
    assert e.ate_sim3_rmse_m < 0.015, e


@pytest.mark.slow
def test_a_map_the_imu_scaled_is_saved_in_metres(walk, tmp_path):
    """A two-view start with the IMU: the saved map is the one map.csv writes (metres, gravity
    up), not the filter's own unit, and it carries the scale's source."""
    from runtime.slam.map_io import load_map

    src, seqs = walk
    r = run_slam(seqs["two_view_imu"], tmp_path / "out", progress=False, save_map=tmp_path / "m.npz")
    totals = json.loads((tmp_path / "out" / "stats.json").read_text())["totals"]
    assert totals["scale"] == "imu" and r.lost_frames == 0
    saved = load_map(tmp_path / "m.npz")
    assert saved.scale == "imu"
    rows = np.genfromtxt(tmp_path / "out" / "map.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    np.testing.assert_allclose(slam_testing.feature_points(saved.y, saved.kinds, saved.anchors),
                               np.column_stack([rows["x"], rows["y"], rows["z"]]), atol=1e-9)
    # The last pose is the trajectory's, which is in metres (the similarity onto the truth is ~1).
    traj = read_trajectory(tmp_path / "out" / "trajectory.tum")
    np.testing.assert_allclose(saved.T_world_cam[:3, 3], traj.p_world_cam[-1], atol=1e-6)
    assert abs(trajectory_errors(traj, open_sequence(src).groundtruth).sim3_scale - 1) < 0.05


@pytest.mark.slow
def test_depth_start_is_metric_from_the_first_frame(walk, tmp_path):
    src, seqs = walk
    r = run_slam(seqs["depth"], tmp_path / "out", settings=CAMERA_ONLY, progress=False)
    totals, e = _scores(tmp_path / "out", src)
    assert totals["scale"] == "depth" and r.frames_before_start == 0 and r.lost_frames == 0
    assert abs(e.sim3_scale - 1.0) < 0.03, e
    assert e.ate_aligned_rmse_m < 0.015, e


@pytest.mark.slow
def test_blank_frames_wait_then_the_start_comes(walk, tmp_path):
    src, seqs = walk
    seq = tmp_path / "seq"
    shutil.copytree(seqs["two_view"], seq)
    rows = [ln.split() for ln in (seq / "rgb.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    for _, rel in rows[:8]:
        img = cv2.imread(str(seq / rel))
        cv2.imwrite(str(seq / rel), np.full_like(img, 120))
    r = run_slam(seq, tmp_path / "out", settings=CAMERA_ONLY, progress=False)
    assert r.frames_before_start >= 8
    assert any("corners" in k for k in r.start_waits), r.start_waits
    assert read_trajectory(tmp_path / "out" / "trajectory.tum").t[0] >= float(rows[8][0]) - 1e-9


def test_a_sequence_with_nothing_to_start_from_ends_without_a_trajectory(tmp_path):
    seq = tmp_path / "blank"
    (seq / "rgb").mkdir(parents=True)
    lines = []
    for k in range(12):
        cv2.imwrite(str(seq / "rgb" / f"{k}.png"), np.full((240, 320), 90, np.uint8))
        lines.append(f"{k / 30:.6f} rgb/{k}.png")
    (seq / "rgb.txt").write_text("\n".join(lines) + "\n")
    (seq / "camera.toml").write_text("[camera]\nwidth = 320\nheight = 240\nfx = 260.0\nfy = 260.0\ncx = 159.5\n"
                                     "cy = 119.5\n")
    with pytest.raises(SlamStartError, match="no start could be made"):
        run_slam(seq, tmp_path / "out", settings=CAMERA_ONLY, progress=False)
    assert not (tmp_path / "out").exists()
    p = subprocess.run([sys.executable, "-m", "wvr", "slam", str(seq), "--out", str(tmp_path / "out2")],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "no start could be made" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "out2" / "trajectory.tum").exists()


def test_the_start_warms_a_copy_of_the_track_and_changes_nothing(walk, tmp_path, monkeypatch):
    """MonoSLAM._warm_up: one frame tracked at the start on a copy of the track (so the compiled
    kernels are loaded there, not in the first tracked frame), and the run's results the same
    to the bit as without it."""
    from runtime.slam.system import MonoSLAM
    from runtime.slam.track import Track

    _, copies = walk
    stepped = []
    step = Track.step
    monkeypatch.setattr(Track, "step", lambda self, *a, **k: (stepped.append((id(self), a[4].frame)), step(self, *a, **k))[1])
    run_slam(copies["depth"], tmp_path / "warm", settings=CAMERA_ONLY, progress=False, max_frames=20)
    warm_id, warm_frame = stepped[0]
    assert warm_frame == 1 and all(i != warm_id for i, _ in stepped[1:]) and len(stepped) == 1 + 19
    monkeypatch.setattr(MonoSLAM, "_warm_up", lambda self, g, t: None)
    run_slam(copies["depth"], tmp_path / "cold", settings=CAMERA_ONLY, progress=False, max_frames=20)
    for name in ("trajectory.tum", "map.csv"):
        assert (tmp_path / "warm" / name).read_bytes() == (tmp_path / "cold" / name).read_bytes(), name


def test_a_two_view_start_widens_new_features_depth_prior_and_a_depth_start_does_not(walk, tmp_path, monkeypatch):
    """A two-view start's points hold the map's scale loosely: its tracks give new features the
    relative width ``two_view_relative_width``; a depth start (its scale held by the depth)
    keeps ``scene_relative_width``."""
    from runtime.slam.track import Track

    widths = []
    init = Track.__init__

    def spy(self, *a, **k):
        init(self, *a, **k)
        widths.append(self.mapping.settings.inverse_depth.scene_relative_width)

    monkeypatch.setattr(Track, "__init__", spy)
    idp = CAMERA_ONLY.inverse_depth
    assert idp.two_view_relative_width > idp.scene_relative_width
    _, copies = walk
    for name, want in (("two_view", idp.two_view_relative_width), ("depth", idp.scene_relative_width)):
        widths.clear()
        run_slam(copies[name], tmp_path / name, settings=CAMERA_ONLY, progress=False, max_frames=12)
        assert widths and set(widths) == {want}, (name, widths)
