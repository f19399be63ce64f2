"""The `wvr` command: help, kinematics subcommands, clear errors, and the demo's report."""

import re
import subprocess
import sys
from pathlib import Path

import mujoco
import pytest

from wvr.cli import main


def run(*args):
    return subprocess.run([sys.executable, "-m", "wvr", *args], capture_output=True, text=True)


def test_help_lists_subcommands():
    r = run("--help")
    assert r.returncode == 0
    assert "kinematics" in r.stdout and "demo" in r.stdout
    r = run("kinematics", "--help")
    for sub in ("show", "mjcf", "ik", "picture"):
        assert sub in r.stdout


def test_show_and_mjcf(capsys):
    assert main(["kinematics", "show", "reference", "--directions", "200"]) == 0
    assert "Radii of rotation" in capsys.readouterr().out
    assert main(["kinematics", "mjcf", "reference"]) == 0
    model = mujoco.MjModel.from_xml_string(capsys.readouterr().out)
    assert model.njnt == 3 and model.ncam == 1


def test_ik_reports_solution_and_refusal(capsys):
    assert main(["kinematics", "ik", "reference", "--target", "1,0,0"]) == 0
    assert "q_deg = 0.0000, 0.0000, 0.0000" in capsys.readouterr().out
    assert main(["kinematics", "ik", "reference", "--target=-1,0.1,0"]) == 1
    assert "unreachable" in capsys.readouterr().out


def test_bad_head_file_is_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "head.toml"
    bad.write_text(Path(__file__).parents[2].joinpath("kinematics/data/reference_head.toml").read_text()
                   .replace('axis = [0.0, 0.0, 1.0]', 'axis = [0.0, 0.0, 2.0]'))
    r = run("kinematics", "show", str(bad))
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "joints.pan.axis" in r.stderr and "not a unit vector" in r.stderr


@pytest.mark.slow
def test_demo_writes_a_report_whose_links_exist(tmp_path):
    assert main(["demo", "--out", str(tmp_path)]) == 0      # 1 if any stage failed
    report = (tmp_path / "report.md").read_text()
    assert "FAILED" not in report
    links = re.findall(r"\]\(([^)]+)\)", report)
    assert links, "the report links its stages' outputs"
    for link in links:
        assert (tmp_path / link).exists(), link
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "kinematics" / "head.xml"))
    assert model.nu == 3


def test_a_failed_demo_stage_fails_the_demo_and_is_named_in_the_report(tmp_path, monkeypatch, capsys):
    import wvr.demo as demo

    def ok(out, context):
        (out / "x.txt").write_text("x")
        context["ran"] = True
        return "[x](ok/x.txt)"

    def refused(out, context):
        raise demo.StageFailed("the closed loop could not run with the chosen head and mount: unreachable")

    def crashes(out, context):
        raise ValueError("broken")

    def after(out, context):
        return "later stages still run" if context.get("ran") else "no context"

    stages = [("ok", "Fine", ok), ("gaze", "Gaze", refused), ("crash", "Crash", crashes), ("after", "After", after)]
    monkeypatch.setattr(demo, "STAGES", stages)
    assert main(["demo", "--out", str(tmp_path / "d")]) == 1
    assert "Gaze" in capsys.readouterr().err
    report = (tmp_path / "d" / "report.md").read_text()
    assert "2 stage(s) FAILED**: Gaze, Crash" in report
    assert "**FAILED**: the closed loop could not run" in report and "(ValueError): broken" in report
    assert "later stages still run" in report and not (tmp_path / "d" / "INCOMPLETE").exists()
    r = demo.run_demo(tmp_path / "e", stages=stages[:1])
    assert r.failed == [] and "FAILED" not in r.report.read_text()


def test_recentre_is_refused_outside_path_a_before_any_work(tmp_path):
    out = tmp_path / "run"
    r = run("sim", "run", "--scenario", "workbench-static", "--task", "fixate", "--recentre", "2", "--out", str(out))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--task stabilise" in r.stderr
    assert not out.exists()


def test_glances_are_refused_on_a_task_without_a_fixation_target_before_any_work(tmp_path):
    out = tmp_path / "run"
    r = run("sim", "run", "--scenario", "workbench-static", "--task", "body", "--glances", "--out", str(out))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "task fixate" in r.stderr and "glances" in r.stderr
    assert not out.exists()
