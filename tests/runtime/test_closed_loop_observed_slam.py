"""SLAM in every task of the closed loop (issue 49): stabilise, body and track run it too,
observed and scored but never steering the head; without a start target they run without it."""

import numpy as np
import pytest

from runtime.apps.closed_loop import Task, run_closed_loop
from runtime.sequence import read_trajectory
from wvr.assemble import clicked_target, make_twin, run_on_twin, safe_twin

pytestmark = pytest.mark.slow

SECONDS = 2.5


@pytest.fixture(scope="module")
def twin():
    t = make_twin()
    yield t
    t.close()


def test_path_b_writes_slams_trajectory_and_its_joints_are_those_of_a_run_without_slam(twin, tmp_path):
    """Path B while walking: trajectory.tum is SLAM's (near the truth, from the frame after the
    start on), and every joint command is the same to the bit as with no SLAM at all."""
    with_slam, without = tmp_path / "slam", tmp_path / "none"
    s = run_on_twin(twin, "walk", Task("body"), with_slam, seconds=SECONDS, seed=2, progress=False, session_log=False)
    est, gt = read_trajectory(with_slam / "trajectory.tum"), read_trajectory(with_slam / "groundtruth.txt")
    assert len(est.t) == len(gt.t) > 60 and s["lost_frames"] == 0
    # A map that did not follow the camera (SLAM frozen at its start) would be off by the walk.
    walked = np.linalg.norm(gt.p_world_cam[-1] - gt.p_world_cam[0])
    assert walked > 0.4 and s["ate_rmse_m"] < 0.03 and s["ate_max_m"] < 0.1 * walked
    assert s["map_features"] >= 10 and s["map_cone_sr"] > 0
    # The same run with no start target: the loop cannot start SLAM, and says so.
    twin.configure("walk", seed=2, seconds=SECONDS)
    s0 = run_closed_loop(safe_twin(twin), Task("body"), without, start_target=None, seconds=SECONDS, progress=False,
                         session_log=False)
    assert not (without / "trajectory.tum").exists() and "lost_frames" not in s0
    assert any("SLAM not run" in e.get("text", "") for e in s0["events"])
    assert (with_slam / "joints.csv").read_bytes() == (without / "joints.csv").read_bytes()


def test_stabilise_scores_slam_from_its_start(twin, tmp_path):
    s = run_on_twin(twin, "workbench-static", Task("stabilise"), tmp_path, seconds=1.5, seed=3, progress=False,
                    session_log=False)
    assert (tmp_path / "trajectory.tum").exists() and s["ate_rmse_m"] < 0.02 and s["lost_frames"] == 0
