"""The station's JSON API and gate over a live loop on a small stand-in robot (a still camera
over a printed target, the head following its commands): 401 without the token and nothing
else, 422 for NaN and unknown ids, the latched stop (checked on the commands the robot was sent),
the recording, the page's and websocket's gate, and a stalled browser that never slows the loop."""

import asyncio
import http.client
import json
import math
import socket
import struct
import time

import cv2
import numpy as np
import pytest

from kinematics import reference_head
from kinematics.camera import default_camera
from runtime.apps.station import Station
from runtime.apps.station.geometry import world_to_pixels
from runtime.robot import ImuSamples, JointCommand, Observation, RobotInfo
from runtime.sequence import Target

CAM = default_camera()
TARGET_XYZ = np.array([[-0.1, -0.07, 0.0], [0.1, -0.07, 0.0], [0.1, 0.07, 0.0], [-0.1, 0.07, 0.0]])


def _T_world_cam():
    # 0.6 m from the target on the bench (z = 0), looking down at it at about 35 deg, world z up.
    eye = np.array([0.0, -0.5, 0.35])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


class StillRobot:
    """A Robot whose camera sees the same textured image every frame (so SLAM holds its pose)
    and whose joints are what it was last commanded; it keeps every command it was sent."""

    def __init__(self, rate=20.0):
        head = reference_head()
        self.info = RobotInfo(head, CAM, rate, head.max_speed, name="still")
        rng = np.random.default_rng(0)
        # Coloured texture: SLAM matches its grey level, the operator's colour tracker its hue.
        self.image = cv2.GaussianBlur((rng.random((480, 640, 3)) * 255).astype(np.uint8), (5, 5), 1.5)
        uv = world_to_pixels(CAM, _T_world_cam(), TARGET_XYZ)
        # The printed target: a black rectangle on a white card (corners the start-up refines
        # the clicks to), drawn with sub-pixel corners, on the texture.
        card = world_to_pixels(CAM, _T_world_cam(), 1.4 * TARGET_XYZ)
        cv2.fillConvexPoly(self.image, np.round(card * 16).astype(np.int32), (255, 255, 255), cv2.LINE_AA, 4)
        cv2.fillConvexPoly(self.image, np.round(uv * 16).astype(np.int32), (0, 0, 0), cv2.LINE_AA, 4)
        self.target = Target(TARGET_XYZ, uv)
        self.commands: list[np.ndarray] = []
        self.t, self.q = 0.0, np.zeros(3)

    def _obs(self):
        return Observation(self.t, self.image, ImuSamples(), self.q.copy(), q_source="commanded")

    def reset(self):
        self.t, self.q, self.commands = 0.0, np.zeros(3), []
        return self._obs()

    def step(self, command: JointCommand):
        self.commands.append(command.q.copy())
        self.q = command.q.copy()
        self.t += 1.0 / self.info.frame_rate
        return self._obs()

    def close(self):
        pass


@pytest.fixture(scope="module")
def station(tmp_path_factory):
    out = tmp_path_factory.mktemp("station")
    robot = StillRobot()
    st = Station(robot, robot.target, port=0, token="secret-token-123", out=out, seconds=600).open()
    st.wait_started()
    # The first periods compile SLAM's kernels when numba's on-disk cache is cold (a fresh
    # checkout, another test worker compiling beside it): minutes, not a stall.
    wait_periods(st, 3, timeout=600)
    st.robot, st.out_dir = robot, out
    yield st
    st.close()


def call(st, method, path, body=None, token="secret-token-123", headers=None, raw=None):
    c = http.client.HTTPConnection("127.0.0.1", st.port, timeout=10)
    h = dict(headers or {})
    if token is not None:
        h["Authorization"] = f"Bearer {token}"
    data = raw if raw is not None else (json.dumps(body) if body is not None else None)
    if data is not None:
        h["Content-Type"] = "application/json"
    c.request(method, path, body=data, headers=h)
    r = c.getresponse()
    payload = r.read()
    c.close()
    return r.status, payload, dict(r.getheaders())


def state(st):
    code, body, _ = call(st, "GET", "/api/state")
    assert code == 200
    return json.loads(body)


def wait_periods(st, n, timeout=30.0):
    s0 = st.live.latest().seq
    t0 = time.time()
    while st.live.latest().seq < s0 + n:
        assert time.time() - t0 < timeout, "the loop stalled"
        time.sleep(0.02)


@pytest.mark.parametrize("method,path,body", [("GET", "/api/state", None), ("POST", "/api/fixate", {"feature": 0}),
                                              ("POST", "/api/stop", {}), ("GET", "/api/frame.jpg", None),
                                              ("GET", "/api/stream", None)])
@pytest.mark.parametrize("token", [None, "wrong-token-456", "secret-token-12", ""])
def test_without_the_token_401_and_nothing_else(station, method, path, body, token):
    n_events = len(station.live.run.events)
    code, payload, headers = call(station, method, path, body, token=token)
    assert code == 401
    assert json.loads(payload) == {"error": "unauthorized"}
    assert len(station.live.run.events) == n_events           # nothing reached the loop
    assert not station.live.latest().estop


def test_the_token_in_the_query_is_no_api_token(station):
    code, _, _ = call(station, "GET", "/api/state?token=secret-token-123", token=None)
    assert code == 401


def test_state_follows_the_contract(station):
    wait_periods(station, 3)
    s = state(station)
    assert isinstance(s["t"], float) and s["mode"] in ("fixate", "saccade", "hold", "stabilise", "body", "track")
    T = np.array(s["T_world_cam"])
    assert T.shape == (4, 4)
    # SLAM holds the still camera where the target put it.
    assert np.allclose(T, _T_world_cam(), atol=0.01)
    assert len(s["joints_deg"]) == 3
    ids = [f["id"] for f in s["features"]]
    known = [f for f in s["features"] if f["known"]]
    assert len(known) == 4 and len(set(ids)) == len(ids)
    for f in known:                                             # the target's points, at their place
        assert min(np.linalg.norm(TARGET_XYZ - f["xyz"], axis=1)) < 0.005


@pytest.mark.parametrize("body,why", [({"xyz": [float("nan"), 0.0, 0.0]}, "NaN"),
                                      ({"xyz": [1e400, 0.0, 0.0]}, "infinity"),
                                      ({"feature": 987654}, "unknown feature id 987654"),
                                      ({"uv": [5.0, 5.0]}, "no map feature"),
                                      ({"xyz": [0, 0]}, "3 numbers"),
                                      ({}, "exactly one")])
def test_422_with_the_reason_and_the_loop_goes_on(station, body, why):
    code, payload, _ = call(station, "POST", "/api/fixate", raw=json.dumps(body))   # json.dumps writes NaN
    assert code == 422
    doc = json.loads(payload)
    assert doc["accepted"] is False and why in doc["reason"]
    wait_periods(station, 2)


def test_an_unknown_mode_is_422_naming_the_modes_there_are(station):
    code, payload, _ = call(station, "POST", "/api/mode", {"mode": "map"})
    assert code == 422
    reason = json.loads(payload)["reason"]
    assert "'map'" in reason and "hold, stabilise, body, track, explore" in reason


def test_a_body_that_is_not_json_is_422(station):
    code, payload, _ = call(station, "POST", "/api/label", raw="{not json")
    assert code == 422 and "not JSON" in json.loads(payload)["reason"]


def test_an_unreachable_point_is_refused_with_the_wearers_prompt(station):
    # Straight behind the camera: beyond the head's elevation range.
    T = np.array(state(station)["T_world_cam"])
    behind = (T[:3, 3] - 1.5 * T[:3, 2]).tolist()
    code, payload, _ = call(station, "POST", "/api/fixate", {"xyz": behind})
    doc = json.loads(payload)
    assert code == 422 and doc["reason"].startswith("unreachable") and "outside its range" in doc["reason"]
    assert isinstance(doc["prompt"], str) and doc["prompt"]
    # The wearer's prompt is on the pages (the state they poll) for a while.
    wait_periods(station, 1)
    assert state(station)["prompt"] == doc["prompt"]


def test_fixate_a_feature_moves_the_head_and_stop_latches_until_reset(station):
    robot = station.robot
    s = state(station)
    corner = [f for f in s["features"] if f["known"]][0]
    code, payload, _ = call(station, "POST", "/api/fixate", {"feature": corner["id"]})
    assert code == 200 and json.loads(payload)["accepted"] and json.loads(payload)["feature"] == corner["id"]
    wait_periods(station, 3)
    n0 = len(robot.commands)
    wait_periods(station, 4)
    moving = np.abs(np.diff(np.array(robot.commands[n0 - 1:]), axis=0)).max()
    assert moving > 1e-4                                         # the saccade is under way
    # Stop: latched; the head holds where it was last commanded, whatever is asked.
    code, _, _ = call(station, "POST", "/api/stop", {"reason": "test"})
    assert code == 200 and state(station)["estop"] and state(station)["mode"] == "stopped"
    n1 = len(robot.commands)
    q_stop = robot.commands[n1 - 1] if n1 else None
    for body in ({"feature": corner["id"]}, {"xyz": corner["xyz"]}):
        code, payload, _ = call(station, "POST", "/api/fixate", body)
        assert code == 409 and "emergency stop is latched" in json.loads(payload)["reason"]
    code, _, _ = call(station, "POST", "/api/mode", {"mode": "body"})
    assert code == 409
    wait_periods(station, 5)
    held = np.array(robot.commands[n1:])
    assert len(held) >= 5 and np.abs(held - held[0]).max() == 0.0
    assert np.abs(held[0] - q_stop).max() < math.radians(30) / 20 + 1e-9   # at most one period's motion
    assert state(station)["estop"]
    # Reset clears it; the head is commanded again.
    code, _, _ = call(station, "POST", "/api/reset", {})
    assert code == 200 and not state(station)["estop"]
    code, _, _ = call(station, "POST", "/api/fixate", {"xyz": TARGET_XYZ.mean(axis=0).tolist()})
    assert code == 200
    n2 = len(robot.commands)
    wait_periods(station, 6)
    assert np.abs(np.array(robot.commands[n2:]) - held[0]).max() > 1e-4


def test_labels_and_objects_are_kept_and_listed(station):
    code, payload, _ = call(station, "POST", "/api/label", {"xyz": [0.1, 0.2, 0.0], "text": "cup"})
    assert code == 200
    code, payload, _ = call(station, "POST", "/api/object", {"kind": "box", "xyz": [0.0, 0.0, 0.05],
                                                            "size": [0.1, 0.1, 0.1]})
    assert code == 200
    wait_periods(station, 2)
    s = state(station)
    assert any(lb["text"] == "cup" and np.allclose(lb["xyz"], [0.1, 0.2, 0.0]) for lb in s["labels"])
    assert any(ob["kind"] == "box" for ob in s["objects"])


def test_the_page_and_its_websocket_need_the_token(station):
    code, payload, _ = call(station, "GET", "/", token=None)
    assert code == 401 and b"needs its token" in payload
    code, _, _ = call(station, "GET", "/?token=wrong-token-456", token=None)
    assert code == 401
    code, _, headers = call(station, "GET", "/?token=secret-token-123", token=None)
    assert code == 303 and "wvr_station=secret-token-123" in headers["Set-Cookie"] and "HttpOnly" in headers["Set-Cookie"]
    cookie = {"Cookie": "wvr_station=secret-token-123"}
    code, page, _ = call(station, "GET", "/", token=None, headers=cookie)
    assert code == 200 and b"/viser/" in page
    code, viser_page, _ = call(station, "GET", "/viser/", token=None, headers=cookie)
    assert code == 200 and b"<html" in viser_page.lower()
    for h in ({}, {"Cookie": "wvr_station=wrong"}):
        assert call(station, "GET", "/viser/", token=None, headers=h)[0] == 401
        assert call(station, "GET", "/wearer", token=None, headers=h)[0] == 401

    import viser
    import websockets

    async def probe(url, headers):
        got = 0
        try:
            async with websockets.connect(url, subprotocols=[f"viser-v{viser.__version__}"], additional_headers=headers,
                                          max_size=None, open_timeout=10) as ws:
                t0 = time.time()
                while time.time() - t0 < 1.5:
                    try:
                        got += len(await asyncio.wait_for(ws.recv(), 0.5))
                    except asyncio.TimeoutError:
                        pass
        except websockets.exceptions.InvalidStatus as e:
            return "refused", e.response.status_code, got
        except websockets.exceptions.ConnectionClosed as e:
            return "closed", e.rcvd.code if e.rcvd else None, got
        return "open", None, got

    gate = f"ws://127.0.0.1:{station.port}/viser"
    assert asyncio.run(probe(gate, {})) == ("refused", 401, 0)
    assert asyncio.run(probe(gate, {"Cookie": "wvr_station=wrong"})) == ("refused", 401, 0)
    # viser's own port (loopback): a websocket that did not come through the gate gets nothing.
    assert asyncio.run(probe(f"ws://127.0.0.1:{station.view.port}/", {})) == ("closed", 1008, 0)
    status, _, got = asyncio.run(probe(gate, cookie))
    assert status == "open" and got > 1000                       # the scene streams through the gate


def test_a_stalled_browser_never_slows_the_loop_and_gets_the_newest_frame(station):
    s = socket.create_connection(("127.0.0.1", station.port))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.sendall(b"GET /api/stream HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer secret-token-123\r\n\r\n")
    seq0 = station.live.latest().seq
    t0 = time.time()
    time.sleep(3.0)                       # reads nothing: the server's writes block, not the loop
    advanced = station.live.latest().seq - seq0
    # A loop that waited on this socket would stop within a few frames (about 60 KB each
    # against the stream's 96 KB send buffer); 10 in 3 s holds on a loaded machine too.
    assert advanced >= 10, advanced
    now = station.live.latest().seq
    s.settimeout(10)
    f = s.makefile("rb")
    while f.readline() not in (b"\r\n", b""):      # headers
        pass
    seqs = []
    while len(seqs) < 8:
        size = int(f.readline().strip(), 16)
        chunk = f.read(size)
        f.read(2)
        assert chunk[:4] == b"WVRF"
        seqs.append(struct.unpack(">I", chunk[4:8])[0])
    s.close()
    # A few frames were in the socket's buffers; then the newest, not the ones in between.
    assert seqs == sorted(seqs) and max(seqs) >= now - 2
    assert seqs[-1] - seqs[0] > len(seqs) - 1 or seqs[0] >= now - 2
    assert time.time() - t0 < 30


def test_the_recording_is_marked_incomplete_while_running_and_written_at_the_end(tmp_path):
    robot = StillRobot()
    st = Station(robot, robot.target, port=0, out=tmp_path, seconds=2.0)
    st.open()
    st.wait_started()
    assert json.loads((tmp_path / "station.json").read_text())["complete"] is False
    st.wait(60)
    # Before close: nothing else written yet.
    assert not (tmp_path / "events.csv").exists()
    code, _, _ = call(st, "POST", "/api/label", {"xyz": [0, 0, 0], "text": "late"}, token=st.token)
    assert code == 409                                          # the loop has ended
    written = st.close()
    assert set(written) == {"trajectory.tum", "events.csv", "labels.toml", "station.json", "session.mcap"}
    doc = json.loads((tmp_path / "station.json").read_text())
    assert doc["complete"] is True and doc["frames"] == 40
    rows = (tmp_path / "events.csv").read_text().splitlines()
    assert rows[0].startswith("t,wall_time,source,action") and "refused" in rows[1]
    assert not list(tmp_path.glob("*.part"))
    assert len((tmp_path / "trajectory.tum").read_text().strip().splitlines()) >= 40


def test_modes_switch_from_outside_and_what_cannot_run_is_refused():
    # A fresh station: the stand-in's image never moves with its joints, so after the other
    # tests its head's posture says little about where "up" is.
    robot = StillRobot()
    station = Station(robot, robot.target, port=0, token="secret-token-123", seconds=600).open()
    station.wait_started()
    try:
        _modes(station)
    finally:
        station.close()


def _modes(station):
    wait_periods(station, 3)
    for mode in ("body", "track", "hold"):
        code, payload, _ = call(station, "POST", "/api/mode", {"mode": mode})
        assert code == 200 and json.loads(payload)["mode"] == mode, payload
        wait_periods(station, 2)
        assert state(station)["mode"] == mode
    # Path A holds an attitude from the IMU: this robot has none, so it is refused, with why.
    code, payload, _ = call(station, "POST", "/api/mode", {"mode": "stabilise"})
    assert code == 422 and "attitude" in json.loads(payload)["reason"]
    assert state(station)["mode"] == "hold"


def test_a_server_that_never_started_closes_at_once():
    # A station whose start failed half-way (its 3D view could not start) must still close.
    import threading

    from runtime.apps.station.server import StationServer

    srv = StationServer("127.0.0.1", 0, "token", None, None)
    t = threading.Thread(target=srv.close, daemon=True)
    t.start()
    t.join(5.0)
    assert not t.is_alive()
