"""Issue 47's output and bad-input classes through `wvr`: no command writes into another's results,
a killed run's leftovers go before a run into its folder, outputs are checked before the work and
a refused run leaves no folder, nesting and sizes are bounded, and messages name the option."""

import json
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest

from kinematics.camera import default_camera, save_camera
from kinematics.outdir import INCOMPLETE, output_folder
from runtime.sequence import SequenceWriter, write_trajectory
from wvr.cli import main


def one_line(err: str) -> bool:
    return err.count("\n") == 1 and "Traceback" not in err


def make_recording(root, frames: int = 3):
    """A tiny recording (a SequenceWriter's folder, as wvr sim record writes) with ground truth."""
    cam = default_camera()
    with SequenceWriter(root, cam) as w:
        for k in range(frames):
            w.add_frame(0.1 * k, np.full((cam.height, cam.width), 40 * k, np.uint8))
            T = np.eye(4)
            T[0, 3] = 0.01 * k
            w.add_groundtruth(0.1 * k, T)
    return root


def make_sim_run(root):
    """A folder as wvr sim run leaves it (its kind recorded), with a report."""
    with output_folder(root, kind="sim run") as d:
        (d / "report.md").write_text("the sim run's report\n")
        (d / "summary.json").write_text("{}\n")
    return root


# ------------------------------------------------------------------ another command's folder

@pytest.mark.parametrize("argv", [
    ["sim", "run", "--scenario", "workbench-static", "--task", "fixate", "--seconds", "0.2", "--out", "{out}"],
    ["stabilise", "{rec}", "--out", "{out}"],
    ["placement", "map", "--out", "{out}"],
    ["design", "optimise", "--out", "{out}", "--evaluations", "10"],
    ["slam", "{rec}", "--out", "{out}"],
    ["track", "{rec}", "--init", "10,10,50,50", "--out", "{out}"],
])
def test_no_command_writes_into_another_commands_results(tmp_path, capsys, argv):
    rec = make_recording(tmp_path / "rec")
    run0 = make_sim_run(tmp_path / "run0")
    # Into a sim run's folder (or, for sim run, into the recording): refused, nothing changed.
    victim = rec if argv[0] == "sim" else run0
    before = {p.name: p.read_bytes() for p in victim.iterdir() if p.is_file()}
    args = [a.format(out=victim, rec=rec) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "another command" in err and str(victim) in err and "another --out" in err
    assert ("wvr sim record" if victim == rec else "wvr sim run") in err
    assert {p.name: p.read_bytes() for p in victim.iterdir() if p.is_file()} == before


def test_a_folder_no_wvr_run_wrote_is_refused_unless_empty(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's own\n")
    assert main(["slam", str(tmp_path / "nothing"), "--out", str(mine)]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "no wvr run wrote it" in err and "notes.txt" in err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]


def test_a_finished_run_of_the_same_kind_is_not_overwritten(tmp_path, capsys):
    rec = make_recording(tmp_path / "rec")
    assert main(["sim", "record", "--scenario", "workbench-static", "--out", str(rec)]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "already holds the finished results" in err
    assert len((rec / "groundtruth.txt").read_text().splitlines()) == 4     # header and 3 poses, as before


_HOLD = textwrap.dedent("""
    import sys, time
    from kinematics.outdir import output_folder
    with output_folder(sys.argv[1], kind="station"):
        print("holding", flush=True)
        time.sleep(60)
""")


def test_a_second_station_into_a_folder_being_written_is_refused(tmp_path, capsys):
    out = tmp_path / "S"
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "holding"
        assert main(["station", "--scenario", "workbench-static", "--port", "0", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert one_line(err) and "another run is writing" in err and f"pid {p.pid}" in err
        from runtime.apps.station.record import claim_out

        with pytest.raises(ValueError, match="another run is writing"):
            claim_out(out)
    finally:
        p.kill()
        p.wait()


# ------------------------------------------------------------------ a killed run's leftovers

def test_a_run_into_a_killed_folder_of_its_kind_clears_the_leftovers_first(tmp_path, capsys):
    out = tmp_path / "S"
    with pytest.raises(KeyboardInterrupt):
        with output_folder(out, kind="slam") as d:
            (d / "video").mkdir()
            (d / "video" / "000001.png").write_bytes(b"x")
            (d / "video.mp4").write_bytes(b"half a video")
            raise KeyboardInterrupt          # killed mid-run: INCOMPLETE stays
    assert (out / INCOMPLETE).exists()
    rec = make_recording(tmp_path / "rec", frames=3)
    main(["slam", str(rec), "--out", str(out), "--max-frames", "2"])
    err = capsys.readouterr().err
    assert "killed wvr slam run left it incomplete; removed its" in err
    assert not (out / "video").exists() and not (out / "video.mp4").exists()


# ------------------------------------------------------------------ outputs checked first, no empty folders

def test_output_files_are_checked_before_the_work(tmp_path, capsys, monkeypatch):
    import kinematics.picture

    monkeypatch.setattr(kinematics.picture, "render_head",
                        lambda *a, **k: pytest.fail("rendered before the output was checked"))
    assert main(["kinematics", "picture", "reference", "--out", str(tmp_path / "missing" / "x.png")]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "--out" in err and "does not exist" in err
    f = tmp_path / "file"
    f.write_text("x")
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for out, why in ((f / "c.toml", "is a file"), (tmp_path / "nowhere" / "c.toml", "does not exist"),
                     (imgs, "is a folder")):
        assert main(["calibrate", "camera", "--images", str(imgs), "--board", "chessboard:9x6:0.025",
                     "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert one_line(err) and "--out" in err and why in err, err


def test_hil_and_rig_outputs_are_refused_before_work_and_no_folder_is_left(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    for out in (f, f / "x"):
        assert main(["sim", "hil", "--scenario", "workbench-static", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert one_line(err) and "--out" in err and "is a file" in err
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parents[1] / "runtime"))
    from test_drivers import write_rig

    rig = write_rig(tmp_path, port=str(tmp_path / "ttyACM7"))          # no board there
    save_target_for(tmp_path / "t.toml")
    assert main(["run", "--rig", str(rig), "--task", "fixate", "--start-target", str(tmp_path / "t.toml"),
                 "--out", str(tmp_path / "run")]) == 2
    assert one_line(capsys.readouterr().err)
    assert not (tmp_path / "run").exists()               # refused: no folder left behind
    with pytest.raises(SystemExit) as e:
        main(["sim", "hil", "--scenario", "workbench-static", "--click-error", "nan", "--out", str(tmp_path / "hil")])
    assert e.value.code == 2 and "argument --click-error" in capsys.readouterr().err
    assert not (tmp_path / "hil").exists()


def save_target_for(path):
    from runtime.sequence import Target, save_target

    save_target(Target(xyz=np.array([[0, 0, 1], [0.1, 0, 1], [0.1, 0.1, 1], [0, 0.1, 1.0]]),
                       uv=np.array([[300, 200], [350, 200], [350, 250], [300, 250.0]])), path)


# ------------------------------------------------------------------ nesting and sizes

def test_deep_nesting_is_one_line_in_every_reader(tmp_path, capsys):
    head = tmp_path / "head.toml"
    head.write_text("x = " + "[" * 5000 + "]" * 5000 + "\n")
    assert main(["kinematics", "show", str(head)]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "nested more than" in err
    bvh = tmp_path / "deep.bvh"
    body = ["HIERARCHY", "ROOT hips", "{", "OFFSET 0 0 0", "CHANNELS 3 Xrotation Yrotation Zrotation"]
    for k in range(3000):
        body += [f"JOINT j{k}", "{", "OFFSET 0 1 0", "CHANNELS 3 Xrotation Yrotation Zrotation"]
    body += ["}"] * 3001 + ["MOTION", "Frames: 1", "Frame Time: 0.033", " ".join(["0"] * 3 * 3001)]
    bvh.write_text("\n".join(body) + "\n")
    assert main(["placement", "map", "--motion", str(bvh), "--out", str(tmp_path / "pm")]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "nested more than" in err and "deep.bvh" in err
    assert not (tmp_path / "pm").exists()
    from placement.body import BodyError
    from placement.io import load_joints_json

    j = tmp_path / "j.json"
    j.write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(BodyError, match="nested more than"):
        load_joints_json(j)


def test_image_sizes_are_bounded(tmp_path, capsys):
    big = tmp_path / "big.toml"
    save_camera(default_camera(), big)
    big.write_text(big.read_text().replace("width = 640", "width = 100000").replace("height = 480", "height = 100000"))
    assert main(["kinematics", "mjcf", "reference", "--camera", str(big)]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "width" in err and "8192" in err
    assert main(["sim", "record", "--scenario", "workbench-static", "--camera", str(big),
                 "--out", str(tmp_path / "rec")]) == 2
    assert one_line(capsys.readouterr().err) and not (tmp_path / "rec").exists()


def test_huge_numbers_are_refused_not_computed_to_inf(tmp_path, capsys):
    from kinematics import reference_head, save_head

    p = tmp_path / "head.toml"
    save_head(reference_head(), p)
    text = p.read_text()
    i = text.index("origin_m", text.index("[camera]"))
    j = text.index("]", i)                          # the array spans lines
    p.write_text(text[:i] + "origin_m = [1e308, 0.0, 0.0" + text[j:])
    assert main(["kinematics", "show", str(p), "--json"]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "camera.origin_m" in err and "metres" in err


# ------------------------------------------------------------------ messages

def test_eval_with_no_poses_names_the_file(tmp_path, capsys):
    rec = make_recording(tmp_path / "rec")
    res = tmp_path / "res"
    res.mkdir()
    T = np.tile(np.eye(4), (3, 1, 1))
    write_trajectory(res / "trajectory.tum", np.array([0.0, 0.1, 0.2]), T)
    (rec / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n")
    assert main(["eval", str(rec), str(res)]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "groundtruth.txt: holds 0 poses" in err
    make_recording(tmp_path / "rec2")
    write_trajectory(res / "trajectory.tum", np.zeros(0), np.zeros((0, 4, 4)))
    assert main(["eval", str(tmp_path / "rec2"), str(res)]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "trajectory.tum: holds 0 poses" in err and "same clock" not in err


@pytest.mark.parametrize("argv", [
    ["sim", "run", "--scenario", "workbench-static", "--task", "fixate", "--seed", "-1", "--out", "X"],
    ["sim", "record", "--scenario", "workbench-static", "--seed", "-1", "--out", "X"],
    ["design", "optimise", "--seed", "-1", "--out", "X"],
])
def test_a_negative_seed_names_the_flag(capsys, argv):
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and one_line(err) and "argument --seed" in err and "whole number >= 0" in err


def test_a_folder_given_for_a_file_says_so(tmp_path, capsys):
    assert main(["kinematics", "show", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "is a folder, not a file" in err


def test_a_hidden_start_target_advises_the_commands_own_options(tmp_path, capsys, monkeypatch):
    import runtime.twin.operator as op
    import wvr.assemble
    import wvr.cli

    fake = SimpleNamespace(scenario=SimpleNamespace(name="workbench-static"), close=lambda: None,
                           ground_truth=SimpleNamespace(T_world_cam=np.eye(4)))
    monkeypatch.setattr(op, "target_in_first_frame", lambda twin: SimpleNamespace(xyz=np.zeros((4, 3))))
    monkeypatch.setattr(op, "hidden_points", lambda twin, p, xyz: np.ones(4, bool))
    monkeypatch.setattr(wvr.cli, "make_twin", lambda *a, **k: fake)
    monkeypatch.setattr(wvr.assemble, "run_on_twin", lambda twin, *a, **k: op.clicked_target(twin))
    assert main(["sim", "run", "--scenario", "workbench-static", "--task", "fixate",
                 "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "hidden" in err and "--seed" in err and "--scene-seed" not in err


# ------------------------------------------------------------------ the head's bring-up

def servo_only_rig(tmp_path, port, estop=None):
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parents[1] / "runtime"))
    from test_drivers import RIG

    text = RIG.format(port=port)
    text = text[:text.index("[camera]")] + ("[safety]\nestop_file = " + json.dumps(estop) + "\n" if estop else "")
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def test_head_bring_up_needs_no_camera(tmp_path, capsys):
    from runtime.twin.hil import VirtualMaestro, WallClockMaestro

    vm = VirtualMaestro(channels=6, home_qus=[6000] * 6)
    wc = WallClockMaestro(vm)
    try:
        rig = servo_only_rig(tmp_path, wc.path)        # no [camera], no camera.toml
        assert not (tmp_path / "camera.toml").exists()
        assert main(["head", "--rig", str(rig), "goto", "5,-5,0", "--rate", "60"]) == 0
        assert main(["head", "--rig", str(rig), "stop"]) == 0
        assert main(["head", "--rig", str(rig), "reset"]) == 0
        assert main(["head", "--rig", str(rig), "home", "--rate", "60"]) == 0
        capsys.readouterr()
        np.testing.assert_allclose(vm.positions_qus([0, 1, 2]) / 4, [1500, 1500, 1500], atol=0.5)
    finally:
        wc.close()
    from runtime.drivers.rig import RigFileError, load_rig

    with pytest.raises(RigFileError, match=r"\[camera\]: missing table"):
        load_rig(rig)                                  # the full load (wvr run --rig) still needs it


def test_a_stop_that_cannot_latch_says_it_is_not_latched(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    rig = servo_only_rig(tmp_path, "/dev/null", estop="afile/estop.latch")
    assert main(["head", "--rig", str(rig), "stop"]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and "NOT latched" in err


@pytest.mark.parametrize("angles, words", [
    ("0,0,80.0001", "cyclotorsion 80.0001 deg is beyond the head's range -80.0..80.0 deg"),
    ("-80.25,0,0", "elevation -80.25 deg is beyond the head's range -80.0..80.0 deg"),
])
def test_goto_beyond_the_range_prints_the_angle_as_given(tmp_path, capsys, angles, words):
    rig = servo_only_rig(tmp_path, "/dev/null")            # refused before the board is opened
    assert main(["head", "--rig", str(rig), "goto", angles]) == 2
    err = capsys.readouterr().err
    assert one_line(err) and words in err and "nothing was sent" in err, err


# ------------------------------------------------------------------ progress in log files

def test_progress_off_a_terminal_is_a_line_every_few_seconds(capsys):
    from kinematics.progress import PlainProgress, progress_bar

    now = [0.0]
    bar = progress_bar(range(100), desc="slam", unit="frame", clock=lambda: now[0])
    assert isinstance(bar, PlainProgress)          # pytest's stderr is not a terminal
    for _ in bar:
        now[0] += 0.26                             # 26 s over 100 frames
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert "\r" not in err and len(lines) == 6      # every 5 s (5 lines in 26 s) and the end
    assert lines[0].startswith("slam: ") and "/100 frame" in lines[0]
    assert lines[-1].startswith("slam: 100/100 frame done")
    bar = progress_bar(total=10, disable=True)
    bar.update(10)
    bar.close()
    assert capsys.readouterr().err == ""


def test_show_bounds_its_directions(capsys):
    with pytest.raises(SystemExit) as e:
        main(["kinematics", "show", "reference", "--directions", "2000000"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and one_line(err) and "argument --directions" in err and "200000" in err
