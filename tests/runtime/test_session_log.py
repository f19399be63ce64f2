"""session.mcap read back with the mcap reader: each topic's count and values after a short
`wvr slam`, a short closed loop on the twin and a short station session, its pose stamps equal
to trajectory.tum's times in ns, the pose covariance's Jacobian against finite differences, and
a run that never closes its log leaving no session.mcap."""

from __future__ import annotations

import csv
import json
import time
from decimal import Decimal

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from runtime.apps.closed_loop import Task
from runtime.session_log import MAP_EVERY, SESSION_FILE, SessionLog, pose_covariance, stamp_ns
from runtime.sequence import open_sequence
from runtime.slam.run import run_slam
from runtime.twin.recorder import record
from wvr.assemble import make_twin, run_on_twin

pytestmark = pytest.mark.slow


def read(path):
    """{topic: [(log_time ns, publish_time ns, decoded message)]} and the file's metadata."""
    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        r = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, msg in r.iter_messages(log_time_order=False):
            if channel.message_encoding == "json":
                dec = json.loads(msg.data)
            else:
                dec = DecoderFactory().decoder_for("protobuf", schema)(msg.data)
            out.setdefault(channel.topic, []).append((msg.log_time, msg.publish_time, dec))
        meta = {m.name: m.metadata for m in r.iter_metadata()}
    return out, meta


def tum_ns(path):
    """trajectory.tum's times as exact ns (from their 9 decimals) and its (N, 7) values."""
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return [int(Decimal(r[0]) * 10**9) for r in rows], np.array([[float(v) for v in r[1:]] for r in rows])


def pose_row(p):
    return [p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y, p.orientation.z,
            p.orientation.w]


@pytest.fixture(scope="module")
def twin():
    t = make_twin()
    yield t
    t.close()


@pytest.fixture(scope="module")
def slam_run(tmp_path_factory, twin):
    seq = tmp_path_factory.mktemp("seq") / "rec"
    record(twin, "workbench-static", seq, seconds=1.0, seed=3, progress=False)
    out = tmp_path_factory.mktemp("slam")
    res = run_slam(seq, out, progress=False)
    return seq, out, res


def test_slam_session_holds_every_frame_pose_map_and_imu_sample(slam_run):
    seq_path, out, res = slam_run
    seq = open_sequence(seq_path)
    topics, meta = read(out / SESSION_FILE)
    assert not (out / (SESSION_FILE + ".part")).exists()
    frame_ns = [stamp_ns(t) for t in seq.timestamps]
    # One image per frame at the frame's stamp.
    assert [m[0] for m in topics["/camera/image"]] == frame_ns
    assert all(m[2].format == "jpeg" and m[2].data[:2] == b"\xff\xd8" for m in topics["/camera/image"])
    # The poses: exactly trajectory.tum's times (ns) and values.
    t_ns, tum = tum_ns(out / "trajectory.tum")
    assert len(t_ns) == res.frames > 20
    for topic in ("/slam/pose", "/slam/odometry"):
        assert [m[0] for m in topics[topic]] == t_ns
        assert [m[1] for m in topics[topic]] == t_ns
        got = np.array([pose_row(m[2].pose) for m in topics[topic]])
        sign = np.sign(np.sum(got[:, 3:] * tum[:, 3:], axis=1))[:, None]
        np.testing.assert_allclose(np.c_[got[:, :3], got[:, 3:] * sign], tum, atol=1e-8)
    # The covariance: symmetric, positive, position variances of a few mm at most.
    C = np.array([m[2].pose_covariance for m in topics["/slam/odometry"]]).reshape(-1, 6, 6)
    np.testing.assert_allclose(C, C.transpose(0, 2, 1), atol=1e-15)
    assert (np.diagonal(C, axis1=1, axis2=2) > 0).all() and np.sqrt(C[:, 0, 0]).max() < 0.01
    # The map every MAP_EVERY frames and on the last, with every feature of map.csv at the end.
    n = res.frames
    assert len(topics["/slam/map"]) == len(range(0, n, MAP_EVERY)) + ((n - 1) % MAP_EVERY != 0)
    last = topics["/slam/map"][-1][2]
    xyz = np.frombuffer(last.data, "<f4").reshape(-1, 3)
    with open(out / "map.csv") as fh:
        mapped = np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in csv.DictReader(fh)])
    np.testing.assert_allclose(xyz, mapped, atol=1e-6)
    # Every IMU sample up to the last frame, at its own stamp.
    imu_t = seq.imu.t[seq.imu.t <= seq.timestamps[-1]]
    assert [m[0] for m in topics["/imu"]] == [stamp_ns(t) for t in imu_t]
    assert topics["/imu"][5][2]["gyro"] == pytest.approx(seq.imu.gyro[5].tolist())
    assert len(topics["/slam/trajectory"]) == 1 and len(topics["/slam/trajectory"][0][2].poses) == len(t_ns)
    assert meta["session"]["ended"] == "complete" and meta["session"]["/slam/pose"] == str(len(t_ns))


def test_slam_without_session_log_writes_none(slam_run, tmp_path):
    seq_path, out, _ = slam_run
    run_slam(seq_path, tmp_path, max_frames=3, progress=False, session_log=False)
    assert not (tmp_path / SESSION_FILE).exists() and (tmp_path / "trajectory.tum").exists()


def test_the_commands_that_log_a_session_take_no_session_log(slam_run, tmp_path, capsys):
    from wvr.cli import build_parser, main

    seq_path, _, _ = slam_run
    assert main(["slam", str(seq_path), "--out", str(tmp_path / "s"), "--max-frames", "3", "--no-session-log"]) == 0
    assert not (tmp_path / "s" / SESSION_FILE).exists() and (tmp_path / "s" / "trajectory.tum").exists()
    assert main(["slam", str(seq_path), "--out", str(tmp_path / "t"), "--max-frames", "3"]) == 0
    assert (tmp_path / "t" / SESSION_FILE).exists()                  # the default still logs
    for argv in (["slam"], ["sim", "run"], ["run"], ["station"], ["track"]):
        with pytest.raises(SystemExit):
            build_parser().parse_args(argv + ["--help"])
        out = capsys.readouterr().out
        assert "--no-session-log" in out and "do not write session.mcap" in " ".join(out.split()), argv


def test_closed_loop_without_session_log_writes_none(twin, tmp_path):
    run_on_twin(twin, "workbench-static", Task("fixate", np.array([[0.0, -0.6, 0.86]])), tmp_path, seconds=0.3,
                progress=False, session_log=False)
    assert not (tmp_path / SESSION_FILE).exists() and (tmp_path / "joints.csv").exists()


def test_closed_loop_session_holds_images_joints_imu_pose_and_target(twin, tmp_path):
    target = np.array([0.0, -0.6, 0.86])
    run_on_twin(twin, "workbench-static", Task("fixate", target[None]), tmp_path, seconds=1.0, progress=False)
    topics, meta = read(tmp_path / SESSION_FILE)
    with open(tmp_path / "joints.csv") as fh:
        rows = list(csv.DictReader(fh))
    row_ns = [stamp_ns(float(r["t"])) for r in rows]
    assert len(rows) >= 25
    assert [m[0] for m in topics["/camera/image"]] == row_ns          # the twin renders every period
    for topic, prefix in (("/joints/commanded", "cmd_"), ("/joints/measured", "meas_")):
        assert [m[0] for m in topics[topic]] == row_ns
        got = np.array([[j.position for j in m[2].joints] for m in topics[topic]])
        want = np.array([[float(r[k]) for k in r if k.startswith(prefix) and "rate" not in k] for r in rows])
        np.testing.assert_allclose(got, want, atol=1e-12)
    t_ns, tum = tum_ns(tmp_path / "trajectory.tum")
    assert [m[0] for m in topics["/slam/pose"]] == t_ns
    got = np.array([pose_row(m[2].pose) for m in topics["/slam/pose"]])
    np.testing.assert_allclose(got[:, :3], tum[:, :3], atol=1e-8)
    assert [m[0] for m in topics["/task/target"]] == row_ns
    p = topics["/task/target"][0][2].point
    assert [p.x, p.y, p.z] == pytest.approx(target)
    # The IMU: each sample once, increasing stamps, as many as the twin gave (~200 Hz).
    imu_ns = [m[0] for m in topics["/imu"]]
    assert imu_ns == sorted(set(imu_ns)) and len(imu_ns) > 100
    assert meta["session"]["ended"] == "complete"


def test_closed_loop_session_holds_the_wearers_prompts_and_the_refusal(twin, tmp_path):
    run_on_twin(twin, "workbench-static", Task("fixate", np.array([[0.0, 2.0, 0.9]])), tmp_path, seconds=0.5,
                progress=False)
    topics, _ = read(tmp_path / SESSION_FILE)
    with open(tmp_path / "prompts.csv") as fh:
        prompts = list(csv.DictReader(fh))
    assert prompts
    assert [m[2].message for m in topics["/prompts"]] == [p["text"] for p in prompts]
    # prompts.csv keeps milliseconds; the log, the prompt's own stamp.
    np.testing.assert_allclose([m[0] * 1e-9 for m in topics["/prompts"]], [float(p["t"]) for p in prompts],
                               atol=5e-4)
    assert any("refused" in m[2].message for m in topics["/events"])


def test_pose_covariance_carries_the_quaternion_to_world_rotation_angles():
    rng = np.random.default_rng(1)
    q = Rotation.random(random_state=2).as_quat()                # x y z w
    x_v = np.r_[rng.normal(size=3), q[3], q[:3]]
    eps = 1e-6
    J = np.zeros((3, 4))
    R0 = Rotation.from_quat(q)
    for k in range(4):
        dq = np.zeros(4)
        dq[k] = eps
        qn = x_v[3:7] + dq
        qn /= np.linalg.norm(qn)
        J[:, k] = (Rotation.from_quat(np.r_[qn[1:], qn[0]]) * R0.inv()).as_rotvec() / eps
    A = rng.normal(size=(7, 7))
    P = A @ A.T
    # Along the quaternion's own direction the normalisation removes variance: compare on its complement.
    w = x_v[3:7]
    N = np.eye(7)
    N[3:7, 3:7] -= np.outer(w, w)
    P = N @ P @ N.T
    C = pose_covariance(x_v, P)
    np.testing.assert_allclose(C[:3, :3], P[:3, :3])
    np.testing.assert_allclose(C[3:, 3:], J @ P[3:7, 3:7] @ J.T, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(C[:3, 3:], P[:3, 3:7] @ J.T, rtol=1e-4, atol=1e-6)


def test_an_unclosed_log_leaves_no_session_mcap_and_a_closed_one_replaces_the_old(tmp_path):
    path = tmp_path / SESSION_FILE
    path.write_bytes(b"an older run's log")
    log = SessionLog(path)
    log.prompt(0.5, "turn left")
    assert not path.exists()                          # killed here: no session.mcap beside new results
    log.event(0.75, "stop")
    log.close()
    topics, _ = read(path)
    assert [(m[0], m[2].message) for m in topics["/prompts"]] == [(500_000_000, "turn left")]
    assert [(m[0], m[2].message) for m in topics["/events"]] == [(750_000_000, "stop")]
    with pytest.raises(ValueError, match="times >= 0"):
        stamp_ns(-1.0)


def test_a_failing_log_stops_itself_and_never_raises_into_the_run(tmp_path, capsys):
    log = SessionLog(tmp_path / SESSION_FILE)
    log.pose(0.1, np.eye(4))
    log.image(-0.5, np.zeros((4, 4, 3), np.uint8))          # a time MCAP cannot hold: said, not raised
    assert "logging stopped" in capsys.readouterr().out and log.error
    log.pose(0.2, np.eye(4))
    assert log.close() is None
    assert not (tmp_path / SESSION_FILE).exists() and (tmp_path / (SESSION_FILE + ".part")).exists()


def test_station_session_logs_the_operators_actions(tmp_path):
    from test_station_api import StillRobot

    from runtime.apps.station import Station
    from runtime.apps.station import actions as A

    robot = StillRobot()
    st = Station(robot, robot.target, port=0, token="secret-token-123", out=tmp_path, seconds=600).open()
    try:
        st.wait_started(timeout=600)
        res = st.live.request(A.Fixate(xyz=np.array([0.0, 0.0, 5.0])), "api")
        assert not res.accepted
        time.sleep(0.5)
    finally:
        st.close()
    topics, meta = read(tmp_path / SESSION_FILE)
    n = len(st.live.run.times)
    assert len(topics["/camera/image"]) == len(topics["/joints/measured"]) == n
    ev = [m[2].message for m in topics["/events"]]
    assert any("api: fixate" in e and "refused" in e for e in ev)
    t_ns, _ = tum_ns(tmp_path / "trajectory.tum")
    assert [m[0] for m in topics["/slam/pose"]] == t_ns
    assert meta["session"]["ended"] == "stopped"


def test_station_without_session_log_writes_its_files_but_no_session(tmp_path):
    from test_station_api import StillRobot

    from runtime.apps.station import Station

    robot = StillRobot()
    st = Station(robot, robot.target, port=0, token="secret-token-123", out=tmp_path, seconds=600,
                 session_log=False).open()
    try:
        st.wait_started(timeout=600)
        time.sleep(0.3)
    finally:
        st.close()
    assert (tmp_path / "trajectory.tum").exists() and not (tmp_path / SESSION_FILE).exists()
    assert SESSION_FILE not in st.written
