"""The closed loop (twin + SLAM + gaze controller) against the twin's ground truth."""

import csv
import math

import numpy as np
import pytest

from runtime.sequence import read_trajectory
from runtime.twin.loop import Task, fixation_errors, pitch_roll, run_closed_loop
from runtime.twin.scenarios import get_scenario
from wvr.cli import main, make_twin

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def twin():
    t = make_twin()
    yield t
    t.close()


def test_fixation_while_walking_holds_the_true_optic_axis_on_the_target(twin, tmp_path):
    sc = get_scenario("walk-ahead")
    target = sc.bench.target_corners().mean(axis=0)
    s = run_closed_loop(twin, sc, Task("fixate", target[None]), tmp_path, seconds=3.0, progress=False)
    assert s["lost_frames"] == 0 and not s["refusals"]
    # Recompute the error from the written files (true poses), independently of the summary.
    gt = read_trajectory(tmp_path / "groundtruth.txt")
    err = np.degrees(fixation_errors(gt.T_world_cam(), np.repeat(target[None], len(gt), 0)))
    after = gt.t >= 1.0
    assert np.sqrt(np.mean(err[after] ** 2)) < 1.0 and err[after].max() < 3.0
    with open(tmp_path / "joints.csv") as fh:
        rows = list(csv.DictReader(fh))
    rates = np.array([[float(r[f"cmd_rate_{n}"]) for n in ("elevation", "pan", "cyclotorsion")] for r in rows])
    assert np.abs(rates).max() <= math.radians(30) + 1e-9
    assert (tmp_path / "report.md").read_text().count("Fixation error") == 1
    for f in ("trajectory.tum", "task.toml", "prompts.csv", "fixation_error.png", "joint_rates.png"):
        assert (tmp_path / f).exists()


def test_path_a_holds_pitch_and_roll_from_the_imu_while_walking(twin, tmp_path):
    s = run_closed_loop(twin, "walk", Task("stabilise"), tmp_path, seconds=3.0, progress=False)
    gt = read_trajectory(tmp_path / "groundtruth.txt")
    pr = np.degrees(pitch_roll(gt.R_world_cam()))
    dev = np.abs(pr - pr[0]).max(axis=0)
    assert dev.max() < 1.0, dev
    # Without the head moving, the wearer's gait tilts the camera by more than that.
    assert s["peak_cmd_rate_deg_s"] > 1.0


def test_an_unreachable_target_is_refused_and_the_wearer_prompted(tmp_path):
    code = main(["sim", "run", "--scenario", "workbench-static", "--task", "fixate", "--target", "0,2,0.9",
                 "--seconds", "0.5", "--out", str(tmp_path)])
    assert code == 1
    with open(tmp_path / "prompts.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and rows[0]["kind"] in ("turn", "step")
    assert "refused" in (tmp_path / "report.md").read_text()


def test_sim_run_refuses_a_saccade_without_two_targets(tmp_path, capsys):
    code = main(["sim", "run", "--scenario", "workbench-static", "--task", "saccade", "--target", "0,-0.6,0.86",
                 "--out", str(tmp_path)])
    assert code == 2
    assert "at least two targets" in capsys.readouterr().err


def test_tracking_servo_keeps_the_tracked_region_centred(twin, tmp_path):
    s = run_closed_loop(twin, "workbench-static", Task("track"), tmp_path, seconds=3.0, progress=False)
    with open(tmp_path / "tracking.csv") as fh:
        rows = list(csv.DictReader(fh))
    lost = [int(float(r["lost"])) for r in rows]
    assert sum(lost) == 0
    # Against the truth written beside each polygon: the tracker's corners, and the region's
    # true centre (where the diagonals cross) against the image centre once the loop settles.
    poly = np.array([[float(r[f"{a}{k}"]) for k in range(4) for a in "xy"] for r in rows[1:]]).reshape(-1, 4, 2)
    true = np.array([[float(r[f"true_{a}{k}"]) for k in range(4) for a in "xy"] for r in rows[1:]]).reshape(-1, 4, 2)
    assert np.sqrt(np.mean(np.sum((poly - true) ** 2, axis=2))) < 1.0
    assert s["servo_centre_rms_px"] < 5.0
    # The head moved to centre it (it starts off-centre), within the motion limit.
    assert 1.0 < s["peak_cmd_rate_deg_s"] <= 30.0 + 1e-9
