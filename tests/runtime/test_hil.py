"""Hardware in the loop, end to end: `wvr sim hil` serves the twin behind a virtual Maestro, IMU
and camera; `wvr run --rig` drives it through the real drivers and the safety chain. The
fixation it reaches (scored from the HIL's true trajectory) matches `wvr sim run`'s."""

import json
import subprocess
import sys
import threading

import numpy as np
import pytest

from runtime.apps.evaluate import fixation_errors
from runtime.sequence import load_target, open_sequence, read_trajectory
from runtime.twin.hil import HilSession
from wvr.assemble import make_twin
from wvr.cli import main

pytestmark = pytest.mark.slow


def test_wvr_run_against_the_hil_twin_fixates_as_sim_run_does(tmp_path):
    twin = make_twin()
    twin.configure("workbench-static", seed=0, seconds=1.5)
    hil = HilSession(twin, tmp_path / "hil", imu="bno085-rvc", linger_s=6.0)
    ready = threading.Event()
    hil.ready = ready.set
    th = threading.Thread(target=hil.run, kwargs={"progress": False})
    th.start()
    try:
        assert ready.wait(60)
        r = subprocess.run([sys.executable, "-m", "wvr", "run", "--rig", str(tmp_path / "hil" / "rig.toml"), "--task",
                            "fixate", "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
    finally:
        th.join(60)
        hil.close()
        twin.close()
    # The recording is a sequence wvr slam can replay, marked complete, with the head it used.
    seq = open_sequence(tmp_path / "run")
    assert len(seq) == 45 and seq.imu is not None and seq.joints is not None and seq.target is not None
    assert (tmp_path / "run" / "head.toml").exists()
    assert json.loads((tmp_path / "run" / "session.json").read_text())["complete"] is True
    # Scored from the HIL's truth, against the target's centre.
    gt = read_trajectory(tmp_path / "hil" / "groundtruth.txt")
    target = load_target(tmp_path / "hil" / "target.toml").xyz.mean(axis=0)
    err = np.degrees(fixation_errors(gt.T_world_cam(), np.repeat(target[None], len(gt), 0)))
    after = gt.t >= 1.0
    hil_rms = float(np.sqrt(np.mean(err[after] ** 2)))
    assert main(["sim", "run", "--scenario", "workbench-static", "--task", "fixate", "--seconds", "1.5",
                 "--out", str(tmp_path / "sim")]) == 0
    sim_summary = json.loads((tmp_path / "sim" / "summary.json").read_text())
    sim_rms = sim_summary["fixation_rms_deg"]
    # The IMU's clock offset the filter learnt, in both summaries (the rig's host stamps the
    # IMU's stream and the camera's frames on arrival).
    hil_offset = json.loads((tmp_path / "run" / "summary.json").read_text())["imu_clock_offset_ms"]
    print(f"\nIMU clock offset learnt: HIL {hil_offset:.1f} ms, sim run {sim_summary['imu_clock_offset_ms']:.1f} ms")
    assert np.isfinite(hil_offset) and np.isfinite(sim_summary["imu_clock_offset_ms"])
    assert hil_rms < 1.0 and abs(hil_rms - sim_rms) < 0.5, (hil_rms, sim_rms)
    # The board saw every period's targets and the safe stop homed the head.
    assert hil.stats.target_commands >= 44 and hil.stats.stalls == 0
    assert "homed" in r.stdout


def test_wvr_head_goto_against_a_virtual_board_and_refusals(tmp_path, capsys):
    from runtime.twin.hil import VirtualMaestro, WallClockMaestro
    from test_drivers import write_rig  # the same directory (pytest prepends it)

    vm = VirtualMaestro(channels=6, home_qus=[6000] * 6)
    wc = WallClockMaestro(vm)
    try:
        rig = write_rig(tmp_path, port=wc.path)
        assert main(["head", "--rig", str(rig), "goto", "10,-20,5", "--rate", "60"]) == 0
        out = capsys.readouterr().out
        assert "moving at 60 deg/s" in out
        # The rig calls a move done when the board reports (whole quarter-us) within 1 of the
        # target, so the output itself is within 1.5 quarter-us (0.375 us) of it.
        arrived_us = 0.375 + 1e-9
        np.testing.assert_allclose(vm.positions_qus([0, 1, 2]) / 4,
                                   [1500 + 10.2 * 10, 1500 - 10.2 * -20, 1500 + 10.2 * 5], atol=arrived_us)
        n = vm.commands
        assert main(["head", "--rig", str(rig), "goto", "100,0,0"]) == 2      # beyond the range: refused
        assert "beyond the head's range" in capsys.readouterr().err and vm.commands == n   # nothing sent
        assert main(["head", "--rig", str(rig), "stop"]) == 0
        assert main(["head", "--rig", str(rig), "home"]) == 2                   # latched
        assert "latched" in capsys.readouterr().err and vm.commands == n
        assert main(["head", "--rig", str(rig), "reset"]) == 0
        assert main(["head", "--rig", str(rig), "home", "--rate", "90"]) == 0
        np.testing.assert_allclose(vm.positions_qus([0, 1, 2]) / 4, [1500, 1500, 1500], atol=arrived_us)
    finally:
        wc.close()


def test_wvr_run_with_a_missing_port_is_one_line(tmp_path):
    from test_drivers import write_rig  # the same directory (pytest prepends it)

    rig = write_rig(tmp_path, port=str(tmp_path / "ttyACM7"))
    r = subprocess.run([sys.executable, "-m", "wvr", "run", "--rig", str(rig), "--task", "stabilise", "--out",
                        str(tmp_path / "run")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "cannot open" in r.stderr


def _serve(tmp_path, seconds, wait_s=5.0, linger_s=6.0):
    twin = make_twin()
    twin.configure("workbench-static", seed=0, seconds=seconds)
    hil = HilSession(twin, tmp_path / "hil", wait_s=wait_s, linger_s=linger_s)
    ready = threading.Event()
    hil.ready = ready.set
    th = threading.Thread(target=hil.run, kwargs={"progress": False})
    th.start()
    assert ready.wait(60)
    return twin, hil, th


def test_unplugging_the_board_mid_run_is_one_line_and_keeps_the_session(tmp_path):
    import time

    # wait_s as in the Ctrl-C test: a slow period on a loaded machine is not taken for a stop.
    twin, hil, th = _serve(tmp_path, seconds=1.2, wait_s=5.0, linger_s=0.0)

    def unplug():
        deadline = time.monotonic() + 300
        while hil.stats.frames < 12 and time.monotonic() < deadline:
            time.sleep(0.01)
        hil.maestro_pty.unplug()
    u = threading.Thread(target=unplug)
    u.start()
    try:
        r = subprocess.run([sys.executable, "-m", "wvr", "run", "--rig", str(tmp_path / "hil" / "rig.toml"), "--task",
                            "stabilise", "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=300)
    finally:
        u.join()
        th.join(60)
        hil.close()
        twin.close()
    errors = [line for line in r.stderr.splitlines() if line.startswith("wvr: error")]
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(errors) == 1   # (the rest is the progress bar)
    assert "unplugged" in errors[0]
    session = json.loads((tmp_path / "run" / "session.json").read_text())
    assert session["complete"] is False and "fault" in session["status"]
    seq = open_sequence(tmp_path / "run")                  # what was recorded before the fault is intact
    assert 8 <= len(seq) <= 20 and seq.imu is not None
    assert (tmp_path / "run" / "joints.csv").exists()


def test_ctrl_c_holds_homes_and_closes(tmp_path):
    import signal
    import time

    # The twin waits 5 s for each period's command: a period that compiles a kernel on a loaded
    # machine (a cold numba cache beside another test worker) is not taken for the stop.
    twin, hil, th = _serve(tmp_path, seconds=3.0, wait_s=5.0, linger_s=8.0)
    try:
        p = subprocess.Popen([sys.executable, "-m", "wvr", "run", "--rig", str(tmp_path / "hil" / "rig.toml"), "--task",
                              "stabilise", "--out", str(tmp_path / "run")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
        deadline = time.monotonic() + 300
        while hil.stats.frames < 20:
            if p.poll() is not None or time.monotonic() > deadline:
                p.kill()
                out, err = p.communicate()
                raise AssertionError(f"the rig stopped after {hil.stats.frames} frames: {err[-2000:]}")
            time.sleep(0.01)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        th.join(60)
        hil.close()
        twin.close()
    assert p.returncode == 0, err
    assert "homed" in out and hil.stats.frames < 80 and hil.stats.stalls == 1
    session = json.loads((tmp_path / "run" / "session.json").read_text())
    assert session["complete"] is False and "Ctrl-C" in session["status"]
    # The board's outputs went home (0 deg: the calibration's neutral pulses), slowly.
    home = hil._to_qus(np.zeros(3))
    np.testing.assert_allclose(hil.maestro.positions_qus(hil.channels), home, atol=2)
