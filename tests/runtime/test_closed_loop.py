"""The closed loop (twin + SLAM + gaze controller) against the twin's ground truth, and proof that
the control path runs with the twin's truth made unavailable."""

import csv
import math

import numpy as np
import pytest

from runtime.sequence import read_trajectory
from runtime.apps.closed_loop import Task, run_closed_loop
from runtime.apps.evaluate import fixation_errors, pitch_roll
from runtime.twin.scenarios import get_scenario
from wvr.assemble import clicked_target, make_twin, run_on_twin
from wvr.cli import main

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def twin():
    t = make_twin()
    yield t
    t.close()


def test_fixation_while_walking_holds_the_true_optic_axis_on_the_target(twin, tmp_path):
    sc = get_scenario("walk-ahead")
    target = sc.bench.target_corners().mean(axis=0)
    s = run_on_twin(twin, sc, Task("fixate", target[None]), tmp_path, seconds=3.0, progress=False)
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
    s = run_on_twin(twin, "walk", Task("stabilise"), tmp_path, seconds=3.0, progress=False)
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


@pytest.mark.parametrize("text, words", [
    ("targets = [[0.0, -0.6, nan], [0.1, -0.6, 0.85]]\n", "target 1 [0.0, -0.6, nan] is not a finite world point"),
    ("targets = [[0.0, -0.6, 1e300], [0.1, -0.6, 0.85]]\n", "target 1 [0.0, -0.6, 1e+300] is not a finite world"),
    ("targets = [[0.0, -0.6, 0.85], [0.1, -0.6, 0.85]]\ndwell_s = -1.0\n", "dwell_s = -1.0 must be"),
])
def test_a_bad_targets_file_is_named_with_its_fault(tmp_path, capsys, text, words):
    (tmp_path / "targets.toml").write_text(text)
    code = main(["sim", "run", "--scenario", "workbench-static", "--task", "saccade", "--targets",
                 str(tmp_path / "targets.toml"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "targets.toml: " in err and words in err, err


def test_tracking_servo_keeps_the_tracked_region_centred(twin, tmp_path):
    s = run_on_twin(twin, "workbench-static", Task("track"), tmp_path, seconds=3.0, progress=False)
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


def test_the_control_path_runs_with_the_twins_truth_unavailable(twin, tmp_path, monkeypatch):
    """The closed loop, handed only the Robot (no TruthSource), with every truth of the twin
    raising: its ground truth, its truth() and landmarks(), the scripted gaze, depth, and the
    scenario's geometry (target corners, look-at points). Only the simulator's own reset may
    use its world to build the scene. The run still fixates, and scoring it afterwards from the
    truth logged by an outside observer agrees with a run that had truth."""
    from runtime.twin.scenarios import Scenario
    from runtime.twin.scene import Workbench
    from runtime.twin.twin import Twin

    sc = get_scenario("workbench-static")
    target_xyz = sc.bench.target_corners().mean(axis=0)
    twin.reset(sc, seed=0, seconds=1.5)
    start = clicked_target(twin, seed=0)                 # a person's clicks, made before the run
    assert 1.5 < np.abs(start.uv - clicked_target(twin, error_px=0.0).uv).max() < 3.4   # 0.8-1.2 x 2.5 px, on a 0.5 px grid

    allowed = {"on": False}

    def forbidden(name):
        def f(*a, **k):
            if not allowed["on"]:
                raise AssertionError(f"the runtime path read the twin's truth: {name}")
            return orig[name](*a, **k)
        return f

    orig = {"ground_truth": Twin.ground_truth.fget, "truth": Twin.truth, "landmarks": Twin.landmarks,
            "scripted_command": Twin.scripted_command, "render_depth": Twin.render_depth,
            "target_corners": Workbench.target_corners, "look_at": Scenario.look_at}
    monkeypatch.setattr(Twin, "ground_truth", property(forbidden("ground_truth")))
    for name in ("truth", "landmarks", "scripted_command", "render_depth"):
        monkeypatch.setattr(Twin, name, forbidden(name))
    monkeypatch.setattr(Workbench, "target_corners", forbidden("target_corners"))
    monkeypatch.setattr(Scenario, "look_at", forbidden("look_at"))
    reset = Twin.reset

    def sim_reset(self, *a, **k):            # the simulator builds its world: allowed
        allowed["on"] = True
        try:
            return reset(self, *a, **k)
        finally:
            allowed["on"] = False
    monkeypatch.setattr(Twin, "reset", sim_reset)

    class RobotOnly:
        """Only the Robot protocol of the twin: reset, step, close, info."""
        info = property(lambda self: twin.info)
        reset = lambda self: twin.reset()          # noqa: E731
        step = lambda self, cmd: twin.step(cmd)    # noqa: E731
        close = lambda self: None                  # noqa: E731

    with pytest.raises(AssertionError, match="truth"):
        twin.truth()                        # the guard bites
    twin.configure(sc, seed=0, seconds=1.5)
    ended = []                                # on_end: once, before anything is written
    s = run_closed_loop(RobotOnly(), Task("fixate", target_xyz[None]), tmp_path, start_target=start, seconds=1.5,
                        progress=False, on_end=lambda: ended.append(sorted(p.name for p in tmp_path.iterdir())))
    assert len(ended) == 1 and "joints.csv" not in ended[0] and "report.md" not in ended[0]
    assert (tmp_path / "joints.csv").exists() and (tmp_path / "report.md").exists()
    assert not (tmp_path / "groundtruth.txt").exists() and "fixation_rms_deg" not in s
    assert s["lost_frames"] == 0 and not s["refusals"]
    # Score it now, outside the run: the true optic axis at the end is on the target.
    allowed["on"] = True
    T = twin.ground_truth.T_world_cam
    assert np.degrees(fixation_errors(T[None], target_xyz[None]))[0] < 1.5
