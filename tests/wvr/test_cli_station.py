"""`wvr station` as a user runs it: bad input is one line and exit 2 before anything starts; a
run prints its address with the token once, serves the API, and records the session when it
stops, by --seconds or by SIGINT / SIGTERM."""

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest


def run(*args, timeout=180):
    return subprocess.run([sys.executable, "-m", "wvr", *args], capture_output=True, text=True, timeout=timeout)


def one_line_error(r):
    return r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr


def test_bad_input_is_one_line_and_nothing_starts(tmp_path):
    r = run("station")
    assert one_line_error(r) and "--scenario NAME" in r.stderr
    r = run("station", "--scenario", "walk", "--rig", "rig.toml")
    assert one_line_error(r)
    r = run("station", "--scenario", "walk", "--token", "short")
    assert one_line_error(r) and "at least 8 characters" in r.stderr
    f = tmp_path / "a-file"
    f.write_text("x")
    r = run("station", "--scenario", "walk", "--out", str(f))
    assert one_line_error(r) and "is a file" in r.stderr
    r = run("station", "--scenario", "walk", "--port", "70000")
    assert one_line_error(r) and "port" in r.stderr
    with socket.socket() as s:                       # a busy port: one line, no recording written
        s.bind(("127.0.0.1", 0))
        s.listen()
        busy = s.getsockname()[1]
        r = run("station", "--scenario", "workbench-static", "--port", str(busy), "--out", str(tmp_path / "o"))
    assert one_line_error(r) and "cannot listen" in r.stderr
    assert not (tmp_path / "o" / "events.csv").exists()


def _start(tmp_path, *extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-m", "wvr", "station", "--scenario", "workbench-static", "--port", "0",
                          "--out", str(tmp_path), *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=env)
    t0 = time.time()
    line, seen = "", []
    while "station: open" not in line:
        line = p.stdout.readline()
        seen.append(line)
        assert line or p.poll() is None, p.stderr.read()
        assert time.time() - t0 < 180
    m = re.search(r"(http://[^/]+/)\?token=(\S+)", line)
    p.seen = seen
    return p, m.group(1), m.group(2)


def _state(base, token):
    req = urllib.request.Request(base + "api/state", headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_the_station_and_the_session_is_recorded(tmp_path, sig):
    p, base, token = _start(tmp_path, "--seconds", "120")
    try:
        assert json.loads((tmp_path / "station.json").read_text())["complete"] is False
        t0 = time.time()
        while _state(base, token)["t"] is None or _state(base, token)["t"] < 0.5:
            assert time.time() - t0 < 120
            time.sleep(0.2)
        p.send_signal(sig)
        out, err = p.communicate(timeout=120)
        out = "".join(p.seen) + out
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert f"stopped by {signal.Signals(sig).name}" in out
    assert out.count(token) == 1                      # the token is printed once
    doc = json.loads((tmp_path / "station.json").read_text())
    assert doc["complete"] is True and doc["frames"] > 5 and doc["status"] == f"stopped by {signal.Signals(sig).name}"
    for f in ("groundtruth.txt", "trajectory.tum", "events.csv", "labels.toml"):
        assert (tmp_path / f).stat().st_size > 0
    n_gt = len([ln for ln in (tmp_path / "groundtruth.txt").read_text().splitlines() if not ln.startswith("#")])
    assert n_gt == doc["frames"]
