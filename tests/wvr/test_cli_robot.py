"""The robot commands of `wvr`: they exist, and bad input is one line with exit status 2."""

import subprocess
import sys


def run(*args):
    return subprocess.run([sys.executable, "-m", "wvr", *args], capture_output=True, text=True, timeout=120)


def one_line_error(r):
    return r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr


def test_help_lists_the_robot_commands():
    r = run("--help")
    for sub in ("head", "run", "calibrate"):
        assert sub in r.stdout
    assert "hil" in run("sim", "--help").stdout


def test_bad_rig_files_and_options_are_one_line(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text('head = "reference"\n[servo]\ndriver = "maestro"\n')
    r = run("run", "--rig", str(bad), "--task", "fixate", "--out", str(tmp_path / "out"))
    assert one_line_error(r) and "[camera]: missing table" in r.stderr
    r = run("head", "--rig", str(tmp_path / "missing.toml"), "home")
    assert one_line_error(r)
    (tmp_path / "imgs").mkdir()
    r = run("calibrate", "camera", "--images", str(tmp_path / "imgs"), "--board", "chessboard:9x6:0.025")
    assert one_line_error(r) and "no images" in r.stderr
    r = run("calibrate", "camera", "--images", str(tmp_path / "imgs"), "--board", "9x6")
    assert one_line_error(r) and "chessboard:COLSxROWS" in r.stderr
    r = run("sim", "run", "--scenario", "workbench-static", "--task", "fixate", "--click-error", "-1", "--seconds", "0.2",
            "--out", str(tmp_path / "sim"))
    assert one_line_error(r) and "click error" in r.stderr


def test_a_recording_carries_the_head_it_was_made_with(tmp_path):
    from kinematics import load_head, reference_head

    r = run("sim", "record", "--scenario", "workbench-static", "--seconds", "0.2", "--out", str(tmp_path / "seq"))
    assert r.returncode == 0, r.stderr
    assert load_head(tmp_path / "seq" / "head.toml") == reference_head()
