"""The Dynamixel driver against a virtual Protocol 2.0 bus on a pseudo-terminal: the packets
against ROBOTIS's own SDK, rig.toml's Dynamixel form, start-up (modes, limits, profile, watchdog),
hostile command streams through the safety chain to the servos' goals, the bus watchdog, and
the rig as a Robot."""

import math
import time

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.drivers import DriverError
from runtime.drivers.dynamixel import (ADDR_BUS_WATCHDOG, ADDR_DRIVE_MODE, ADDR_GOAL_POSITION, ADDR_OPERATING_MODE,
                                       ADDR_PROFILE_ACCELERATION, ADDR_PROFILE_VELOCITY, ADDR_TORQUE_ENABLE,
                                       TICKS_PER_TURN, VELOCITY_UNIT_RAD_S, DynamixelBoard, DynamixelBus,
                                       velocity_units, watchdog_units)
from runtime.drivers.rig import RigFileError, load_rig
from runtime.safety import SafetyChain, SafetySettings
from runtime.robot import JOINTS_MEASURED, JointCommand
from runtime.twin.hil import PtyDevice
from runtime.twin.virtual_dynamixel import VirtualDynamixelBus, crc16, packet, patient_host, stuff, unstuff
from wvr.assemble import make_rig

DT = 1 / 30
TICKS_PER_RAD = TICKS_PER_TURN / (2 * math.pi)

RIG = """head = "reference"
[servo]
driver = "dynamixel"
port = "{port}"
ids = {{ elevation = 1, pan = 2, cyclotorsion = 3 }}
baud = 1000000
watchdog_ms = {watchdog_ms}
speed_limit_deg_s = {speed}
[servo.calibration.elevation]
zero_ticks = 2048.0
ticks_per_deg = 11.3778
sign = 1
min_ticks = 1024.0
max_ticks = 3072.0
[servo.calibration.pan]
zero_ticks = 2000.0
ticks_per_deg = 11.3778
sign = -1
min_ticks = 1000.0
max_ticks = 3000.0
[servo.calibration.cyclotorsion]
zero_ticks = 2100.0
ticks_per_deg = 11.3778
sign = 1
min_ticks = 1100.0
max_ticks = 3100.0
[camera]
source = "{frames}"
camera_toml = "camera.toml"
"""


def write_rig(tmp_path, port="/dev/ttyUSB0", watchdog_ms=100, speed=200.0, text=None):
    from kinematics.camera import default_camera, save_camera

    cam = default_camera()
    save_camera(cam, tmp_path / "camera.toml")
    for k in range(40):
        cv2.imwrite(str(tmp_path / f"f{k:03d}.png"), np.full((cam.height, cam.width, 3), 3 * k, np.uint8))
    p = tmp_path / "rig.toml"
    p.write_text(text if text is not None else
                 RIG.format(port=port, watchdog_ms=watchdog_ms, speed=speed, frames=str(tmp_path / "f*.png")))
    return p


@pytest.fixture(autouse=True, scope="module")
def _patient_host():
    """The virtual bus answers from a thread: wait for it as long as a loaded machine needs."""
    with patient_host():
        yield


@pytest.fixture
def bus():
    vb = VirtualDynamixelBus(ids=(1, 2, 3), positions=[2048, 2000, 2100], run=False)
    dev = PtyDevice(vb.feed, "dynamixel")
    yield vb, dev
    dev.close()
    vb.close()


def test_packets_match_robotis_sdk():
    """Our virtual bus's CRC and byte stuffing are ROBOTIS's: checked against the SDK's own code."""
    from dynamixel_sdk import Protocol2PacketHandler

    sdk = Protocol2PacketHandler()
    rng = np.random.default_rng(0)
    for n in (1, 7, 300):
        data = rng.integers(0, 256, n).tolist()
        assert crc16(data) == sdk.updateCRC(0, data, len(data))
    params = bytes([0x74, 0x00, 0xFF, 0xFF, 0xFD, 0x10])            # an FF FF FD inside the parameters
    body = bytes([0x03]) + params
    raw = [0xFF, 0xFF, 0xFD, 0x00, 1, (len(body) + 2) & 0xFF, (len(body) + 2) >> 8, *body, 0, 0]
    stuffed = sdk.addStuffing(raw)
    ours = packet(1, 0x03, params)
    assert bytes(stuffed[7:7 + len(ours) - 9]) == stuff(body) == ours[7:-2]
    assert unstuff(stuff(body)) == body and stuff(body).count(0xFD) == 2


def test_rig_toml_dynamixel_form_and_its_errors(tmp_path):
    cfg = load_rig(write_rig(tmp_path))
    assert cfg.servo_driver == "dynamixel" and cfg.channels == (1, 2, 3) and cfg.baud == 1000000
    assert cfg.watchdog_s == pytest.approx(0.1) and cfg.calibration[1].sign == -1
    assert cfg.calibration[0].to_ticks(math.radians(10)) == round(2048 + 113.778)
    assert cfg.calibration[0].to_ticks(1e9) == 3072 and cfg.calibration[0].to_ticks(-1e9) == 1024   # clipped
    text = (tmp_path / "rig.toml").read_text()
    for change, message in [
        (("ids = {", "channels = {"), "servo.channels: unknown key"),
        (("watchdog_ms = 100", "watchdog_ms = 5"), "servo.watchdog_ms"),
        (("min_ticks = 1024.0", "min_ticks = 1500.0"), "[servo.calibration.elevation]: the head's elevation range"),
        (("sign = -1", "sign = 0"), "servo.calibration.pan.sign"),
        (("cyclotorsion = 3 }", "cyclotorsion = 2 }"), "each joint needs its own servo ID"),
        (("driver = \"dynamixel\"", "driver = \"herkulex\""), "servo.driver"),
    ]:
        (tmp_path / "rig.toml").write_text(text.replace(*change))
        with pytest.raises(RigFileError) as e:
            load_rig(tmp_path / "rig.toml")
        assert message in str(e.value) and "\n" not in str(e.value), (change, str(e.value))


def test_start_sets_the_profile_limits_and_arms_the_watchdog(tmp_path, bus):
    vb, dev = bus
    cfg = load_rig(write_rig(tmp_path, dev.path, speed=200.0))
    board = DynamixelBoard(cfg, DynamixelBus(cfg.port, cfg.baud, cfg.channels))
    try:
        board.start()
        for i in (1, 2, 3):
            s = vb.servos[i]
            pv = s.get(ADDR_PROFILE_VELOCITY, 4)
            assert pv == velocity_units(math.radians(200.0)) and pv * VELOCITY_UNIT_RAD_S <= math.radians(200.0)
            assert s.get(ADDR_PROFILE_ACCELERATION, 4) > 0 and s.table[ADDR_TORQUE_ENABLE] == 1
            assert s.table[ADDR_BUS_WATCHDOG] == watchdog_units(0.1) == 5
        np.testing.assert_allclose(board.positions(), [0, 0, 0], atol=1e-9)     # held where they were
        assert [vb.servos[i].get(ADDR_GOAL_POSITION, 4) for i in (1, 2, 3)] == [2048, 2000, 2100]
    finally:
        board.close()


@pytest.mark.parametrize("addr, value, message", [(ADDR_OPERATING_MODE, 1, "operating mode 1"),
                                                  (ADDR_DRIVE_MODE, 0x04, "time-based"),
                                                  (52, 1500, "exceed the servo's position limits")])
def test_start_refuses_a_servo_set_up_wrongly(tmp_path, bus, addr, value, message):
    vb, dev = bus
    vb.servos[2].set(addr, 4 if addr == 52 else 1, value)
    cfg = load_rig(write_rig(tmp_path, dev.path))
    board = DynamixelBoard(cfg, DynamixelBus(cfg.port, cfg.baud, cfg.channels))
    try:
        with pytest.raises(DriverError, match=message) as e:
            board.start()
        assert "Dynamixel 2" in str(e.value)
        assert all(vb.servos[i].table[ADDR_TORQUE_ENABLE] == 0 for i in (1, 2, 3))   # nothing was powered
    finally:
        board.close()


def test_an_absent_servo_and_a_missing_port_are_one_line_errors(tmp_path, bus):
    vb, dev = bus
    del vb.servos[3]
    cfg = load_rig(write_rig(tmp_path, dev.path))
    board = DynamixelBoard(cfg, DynamixelBus(cfg.port, cfg.baud, cfg.channels))
    try:
        with pytest.raises(DriverError, match="Dynamixel 3 .*ping failed"):
            board.start()
    finally:
        board.close()
    with pytest.raises(DriverError, match="cannot open"):
        DynamixelBus(str(tmp_path / "no-such-port"), 57600, [1])


hostile = st.one_of(st.floats(-1e6, 1e6, allow_nan=False), st.just(float("nan")), st.just(float("inf")),
                    st.just(-float("inf")), st.floats(-2.0, 2.0))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(hostile, hostile, hostile), min_size=1, max_size=40), st.floats(5.0, 60.0))
def test_no_goal_leaves_the_calibration_and_no_servo_moves_too_fast(tmp_path_factory, cmds, limit_deg):
    """Hostile commands through the safety chain and the driver to the bus: every goal the
    servos decoded lies in min..max ticks, steps at most the motion limit, and each servo moves
    no faster than the profile velocity set on it."""
    tmp = tmp_path_factory.mktemp("dxl")
    vb = VirtualDynamixelBus(ids=(1, 2, 3), positions=[2048, 2000, 2100], run=False)
    dev = PtyDevice(vb.feed, "dynamixel")
    cfg = load_rig(write_rig(tmp, dev.path, speed=100.0))
    board = DynamixelBoard(cfg, DynamixelBus(cfg.port, cfg.baud, cfg.channels))
    try:
        board.start()
        chain = SafetyChain(cfg.head, np.zeros(3), SafetySettings(motion_limit_rad_s=math.radians(limit_deg)))
        lo = np.array([c.min_ticks for c in cfg.calibration])
        hi = np.array([c.max_ticks for c in cfg.calibration])
        per_rad = np.array([c.ticks_per_rad for c in cfg.calibration])
        prev = np.array([2048, 2000, 2100], float)
        n0 = len(vb.goal_writes)
        for k, c in enumerate(cmds):
            q = chain.apply(JointCommand(np.array(c, float), basis_t=k * DT), k * DT, DT)
            board.send(q)
            board.positions()                                     # a round trip: the bus has read the goals
            vb.advance(DT)
            goal = np.array([vb.servos[i].get(ADDR_GOAL_POSITION, 4) for i in (1, 2, 3)], float)
            assert np.all(goal >= lo) and np.all(goal <= hi)
            assert np.all(np.abs(goal - prev) <= per_rad * math.radians(limit_deg) * DT + 1.0)
            prev = goal
        assert len(vb.goal_writes) == n0 + len(cmds)             # every command reached the bus as a goal
        vmax = velocity_units(math.radians(100.0)) * VELOCITY_UNIT_RAD_S * TICKS_PER_RAD
        assert all(vb.servos[i].max_speed_seen <= vmax + 1e-6 for i in (1, 2, 3))
        assert vb.crc_errors == 0
    finally:
        board.close()
        dev.close()
        vb.close()


def test_the_bus_watchdog_stops_a_servo_when_the_host_goes_silent(tmp_path, bus):
    vb, dev = bus
    cfg = load_rig(write_rig(tmp_path, dev.path, watchdog_ms=60, speed=30.0))
    board = DynamixelBoard(cfg, DynamixelBus(cfg.port, cfg.baud, cfg.channels))
    try:
        board.start()
        board.send([1.0, 0.0, 0.0])                                # a long, slow move
        board.positions()                                          # (a round trip: the goal has arrived)
        vb.advance(0.05)
        time.sleep(0.15)                                           # the host says nothing for 150 ms
        vb.advance(0.01)
        moved = vb.servos[1].position
        assert vb.servos[1].table[ADDR_BUS_WATCHDOG] == 0xFF and 2048 < moved < 2048 + 1.0 * TICKS_PER_RAD
        vb.advance(0.5)
        assert vb.servos[1].position == moved                      # stopped where it was
        with pytest.raises(DriverError, match="Dynamixel 1: its bus watchdog tripped"):
            board.check_errors()
        board.start()                                              # a fresh start clears it and holds
        assert vb.servos[1].table[ADDR_BUS_WATCHDOG] == watchdog_units(0.06)
        board.check_errors()
    finally:
        board.close()


def test_the_rig_runs_on_dynamixel_servos_and_reports_their_encoders(tmp_path, bus):
    vb, dev = bus
    cfg_path = write_rig(tmp_path, dev.path, speed=200.0)
    rig = make_rig(load_rig(cfg_path))                  # behind the safety chain, as wvr run drives it
    try:
        obs = rig.reset()
        assert obs.q_source == JOINTS_MEASURED
        np.testing.assert_allclose(obs.q, [0, 0, 0], atol=1e-9)
        for k in range(10):
            vb.advance(DT)
            obs = rig.step(JointCommand([0.2, -0.1, 0.05], basis_t=obs.t))
        q_enc = np.array([cfg.to_rad(vb.servos[i].get(132, 4)) for cfg, i in zip(rig.robot.cfg.calibration, (1, 2, 3))])
        np.testing.assert_allclose(rig.robot.board.positions(), q_enc, atol=1e-12)
        assert np.all(np.sign(q_enc) == np.sign([0.2, -0.1, 0.05])) and np.all(np.abs(q_enc) > 0.01)
    finally:
        rig.close()


def test_start_holds_when_the_bus_answers_late(tmp_path):
    """A loaded machine holds the virtual bus's thread off: answers 100 ms late (three times the
    SDK's own 34 ms deadline) must still be taken, not read as a missing servo."""
    vb = VirtualDynamixelBus(ids=(1, 2, 3), positions=[2048, 2000, 2100], run=False)

    def late(data: bytes) -> bytes:
        answer = vb.feed(data)
        if answer:
            time.sleep(0.1)
        return answer

    dev = PtyDevice(late, "dynamixel")
    cfg = load_rig(write_rig(tmp_path, dev.path))
    board = DynamixelBoard(cfg, DynamixelBus(cfg.port, cfg.baud, cfg.channels))
    try:
        board.start()
        np.testing.assert_allclose(board.positions(), [0, 0, 0], atol=1e-9)
    finally:
        board.close()
        dev.close()
        vb.close()
