"""The station on the hardware rig, unchanged: the twin behind a virtual Maestro, IMU and camera
(hardware in the loop), driven through the real drivers and the safety chain. A fixation is
accepted through the API; the operator's stop trips the rig's own latch (its latch file, which
``wvr head stop`` uses too) and the board is sent the same pulses until reset."""

import json
import threading
import time
import urllib.request

import numpy as np
import pytest

from runtime.apps.station import Station
from runtime.drivers.rig import load_rig
from runtime.sequence import load_target
from runtime.twin.hil import HilSession
from wvr.assemble import make_rig, make_twin

pytestmark = pytest.mark.slow


def call(st, method, path, body=None):
    req = urllib.request.Request(st.public_url.rstrip("/") + path, method=method,
                                 data=json.dumps(body).encode() if body is not None else None,
                                 headers={"Authorization": f"Bearer {st.token}", "Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_the_station_drives_the_rig_and_its_stop_trips_the_rigs_latch(tmp_path):
    twin = make_twin()
    twin.configure("workbench-static", seed=0, seconds=6.0)
    hil = HilSession(twin, tmp_path / "hil", imu="bno085-rvc", linger_s=6.0)
    ready = threading.Event()
    hil.ready = ready.set
    def serve():
        try:
            hil.run(progress=False)
        finally:
            twin.close()            # in the thread whose GL context rendered it

    th = threading.Thread(target=serve)
    th.start()
    st = None
    try:
        assert ready.wait(60)
        cfg = load_rig(tmp_path / "hil" / "rig.toml")
        rig = make_rig(cfg)

        def finish():
            out = rig.safe_stop(home=False)
            rig.close()
            return out

        st = Station(rig, load_target(cfg.start_target), port=0, out=tmp_path / "session", on_finish=finish).open()
        st.wait_started(120)
        t0 = time.time()
        while st.live.latest().t < 0.5:
            assert time.time() - t0 < 120
            time.sleep(0.05)
        state = call(st, "GET", "/api/state")[1]
        corner = [f for f in state["features"] if f["known"]][2]
        p_corner = np.array(corner["xyz"])            # a known corner: world frame, exact

        def off_axis_deg() -> float:
            """The true optic axis's angle to the corner (the twin's truth behind the board)."""
            T = np.array(twin.ground_truth.T_world_cam)
            d = p_corner - T[:3, 3]
            return float(np.degrees(np.arccos(np.clip(T[:3, 2] @ d / np.linalg.norm(d), -1, 1))))

        before = off_axis_deg()
        t_fix = st.live.latest().t
        code, body = call(st, "POST", "/api/fixate", {"feature": corner["id"]})
        assert code == 200 and body["accepted"]
        t0 = time.time()
        while st.live.latest().t < t_fix + 2.5:       # the head turns at 30 deg/s, then settles
            assert time.time() - t0 < 180
            time.sleep(0.05)
        after = off_axis_deg()
        print(f"\nthe corner off the optic axis: {before:.2f} deg before the fixation, {after:.2f} deg after")
        # The head turned to the corner: a no-op fixation stays at `before`, a wrong sign grows it.
        assert after < 1.5 and after < before - 2.0, (before, after)
        code, _ = call(st, "POST", "/api/stop", {"reason": "station test"})
        assert code == 200
        assert rig.estop.tripped and cfg.estop_file.exists()
        n = len(rig.robot.sent_qus)
        code, body = call(st, "POST", "/api/fixate", {"feature": corner["id"]})
        assert code == 409
        t0 = time.time()
        while len(rig.robot.sent_qus) < n + 5:
            assert time.time() - t0 < 60
            time.sleep(0.05)
        held = np.array(rig.robot.sent_qus[n:n + 5])
        assert (held == held[0]).all()                      # the board held its pulses
        code, _ = call(st, "POST", "/api/reset", {})
        assert code == 200 and not rig.estop.tripped and not cfg.estop_file.exists()
    finally:
        if st is not None:
            st.stop()
            st.close()
        th.join(60)
        hil.close()
    doc = json.loads((tmp_path / "session" / "station.json").read_text())
    assert doc["frames"] > 10
    assert not (tmp_path / "session" / "groundtruth.txt").exists()        # no truth on a rig
