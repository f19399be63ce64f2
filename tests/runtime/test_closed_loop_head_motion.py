"""The closed loop's head-motion start on the twin: no target in SLAM's start, the head's own
known motion fixes the map's scale; scored against the twin's truth from the written files."""

import csv
import json

import numpy as np
import pytest

from runtime.sequence import read_trajectory
from wvr.cli import main

pytestmark = pytest.mark.slow


def test_a_still_wearer_gets_a_metric_map_from_the_heads_motion(tmp_path):
    out = tmp_path / "run"
    code = main(["sim", "run", "--task", "fixate", "--scenario", "office-static", "--seed", "1", "--start",
                 "head-motion", "--seconds", "9", "--no-session-log", "--out", str(out)])
    assert code == 0
    est, gt = read_trajectory(out / "trajectory.tum"), read_trajectory(out / "groundtruth.txt")
    # SLAM gave no pose before the motion was made (wait for stillness, about 5 s of motion) ...
    assert 3.0 < est.t[0] - gt.t[0] < 8.0 and len(est.t) > 30
    # ... and from then on its map is metric without any target: the start's points' depths
    # against the twin's true depth image at that frame.
    s = json.loads((out / "summary.json").read_text())
    assert abs(s["start_map_scale_error"]) < 0.05 and s["start_map_points"] >= 20
    assert s["lost_frames"] == 0
    assert s["ate_rmse_m"] < 0.02                  # the estimate put on the truth by its first pose only
    # The start is solved beside the loop: the task waits for SLAM to go through the frames seen
    # meanwhile, and those frames have their poses too, from the start's frame on without a gap.
    assert s["task_start_s"] - s["slam_start_s"] > 0.3
    frames = json.loads((out / "slam_stats.json").read_text())["frames"]
    assert sum(f["imu"] for f in frames) > 0.9 * len(frames)        # the IMU drives SLAM's prediction
    assert np.all(np.diff([f["t"] for f in frames]) > 0)              # each frame once, in order
    assert abs(est.t[0] - gt.t[0] - s["slam_start_s"]) < 1e-6 and np.diff(est.t).max() < 1.5 / 30
    said = [e["text"] for e in s["events"] if e["event"] == "start"]
    assert any("SLAM started metric" in t for t in said)
    # The head fixated the clicked point once the start was made.
    assert s["fixation_rms_deg"] < 1.0
    with open(out / "joints.csv") as fh:
        pan = np.array([float(r["meas_pan"]) for r in csv.DictReader(fh)])
    assert np.ptp(np.degrees(pan)) > 15             # the start's motion did happen


def test_head_motion_start_with_track_is_refused_with_the_reason(tmp_path, capsys):
    code = main(["sim", "run", "--task", "track", "--scenario", "workbench-static", "--start", "head-motion",
                 "--seconds", "1", "--out", str(tmp_path / "x")])
    assert code == 2
    err = capsys.readouterr().err
    assert "track learns its region from the first image" in err and "--start target" in err
    assert not (tmp_path / "x" / "summary.json").exists()


def test_a_task_that_only_observes_slam_says_it_wrote_its_trajectory(tmp_path, capsys):
    out = tmp_path / "b"
    assert main(["sim", "run", "--task", "body", "--scenario", "workbench-static", "--seconds", "0.5",
                 "--no-session-log", "--out", str(out)]) == 0
    said = capsys.readouterr().out.splitlines()[-1]
    assert said.startswith(f"wrote {out}:") and "joints.csv" in said
    assert "trajectory.tum" in said and (out / "trajectory.tum").exists()


def test_path_b_after_a_head_motion_start_holds_the_head_where_the_motion_ended(tmp_path):
    """Also SLAM from the camera alone (--no-imu): the start still reads the IMU, SLAM does not."""
    out = tmp_path / "hb"
    assert main(["sim", "run", "--task", "body", "--scenario", "office-static", "--seed", "1", "--start",
                 "head-motion", "--seconds", "8", "--no-imu", "--no-session-log", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    frames = json.loads((out / "slam_stats.json").read_text())["frames"]
    assert len(frames) > 30 and not any(f["imu"] for f in frames)
    assert "slam_imu = false" in (out / "task.toml").read_text()
    assert 3.0 < s["slam_start_s"] < 8.0 and abs(s["start_map_scale_error"]) < 0.05 and s["ate_rmse_m"] < 0.02
    # The task began once SLAM had gone through the frames seen while the start was solved.
    assert s["slam_start_s"] < s["task_start_s"] < s["slam_start_s"] + 2.0
    with open(out / "joints.csv") as fh:
        rows = [(float(r["t"]), float(r["cmd_pan"]), float(r["cmd_elevation"])) for r in csv.DictReader(fh)]
    t, pan, elev = (np.array(c) for c in zip(*rows))
    before, after = t - t[0] < s["slam_start_s"], t - t[0] > s["task_start_s"] + 0.5
    assert np.ptp(np.degrees(pan[before])) > 15                # the start's motion ran first
    # then the task: the head holds its direction on the still wearer's body
    assert np.ptp(np.degrees(pan[after])) < 0.5 and np.ptp(np.degrees(elev[after])) < 0.5
    assert s["pitch_max_dev_deg"] < 2.0                         # scored from the task's start
