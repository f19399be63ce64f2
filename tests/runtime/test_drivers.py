"""The drivers against simulated devices on pseudo-terminals (no hardware): the Maestro's bytes
against Pololu's published examples, start-up limits in the board's units, errors, garbage and
unplugging; the BNO085 RVC parser against the datasheet's example frame, resynchronisation,
checksums, dropped reports, rates by differencing; the text IMU; camera sources; rig.toml."""

import math
import time

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from runtime.drivers import DriverError
from runtime.drivers import maestro as mp
from runtime.drivers.camera import CameraStalled, FolderSource, LiveCapture, ReplaySource
from runtime.drivers.imu import ImuReader, RvcParser, RvcRates, TextParser, encode_rvc
from runtime.drivers.rig import RigFileError, ServoBoard, load_rig
from runtime.robot import SessionEnded
from runtime.twin.hil import PtyDevice, VirtualMaestro, WallClockMaestro


# ------------------------------------------------------------------ Maestro bytes
def test_maestro_bytes_match_pololus_examples():
    # User's guide 5.e: channel 2 to 1500 us (6000 quarter-us) = 0x84 0x02 0x70 0x2E; the Pololu
    # protocol with device 12: 0xAA 0x0C 0x04 0x02 0x70 0x2E; Set Speed channel 5 to 140:
    # 0x87 0x05 0x0C 0x01; Set Multiple Targets channel 3 off and 4 neutral: 0x9F 02 03 00 00 70 2E.
    assert mp.set_target_bytes(2, 6000) == bytes([0x84, 0x02, 0x70, 0x2E])
    assert mp.set_target_bytes(2, 6000, device=12) == bytes([0xAA, 0x0C, 0x04, 0x02, 0x70, 0x2E])
    assert mp.set_speed_bytes(5, 140) == bytes([0x87, 0x05, 0x0C, 0x01])
    assert mp.set_multiple_targets_bytes(3, [0, 6000]) == bytes([0x9F, 0x02, 0x03, 0x00, 0x00, 0x70, 0x2E])
    with pytest.raises(DriverError):
        mp.set_target_bytes(0, 20000)


def test_limits_in_the_boards_units_never_exceed_the_rig_limit():
    # 10 rad/s at 10.2 us/deg = 5844 us/s: 233 units of 0.25 us / 10 ms (233.8 rounded down).
    us_s = 10.0 * 180 / math.pi * 10.2
    assert mp.speed_units(us_s) == 233
    assert mp.speed_us_per_s(mp.speed_units(us_s)) <= us_s
    # The guide: speed 140 is 3.5 us/ms; acceleration units are 0.25 us / 10 ms / 80 ms.
    assert mp.speed_us_per_s(140) == pytest.approx(3500.0)
    assert mp.accel_us_per_s2(1) == pytest.approx(312.5)
    assert mp.accel_units(5000 * 10.2) == 163 and mp.accel_units(1e9) == 255
    assert mp.speed_units(1.0) == 1          # never 0: that would mean unlimited


def eventually(check, timeout_s: float = 2.0) -> bool:
    """Whether ``check()`` holds within ``timeout_s`` of wall time: the virtual board's outputs
    move on its own clock thread, which a loaded machine may run late."""
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


@pytest.fixture
def board():
    vm = VirtualMaestro(channels=6, home_qus=[6000] * 6)
    wc = WallClockMaestro(vm)
    yield vm, wc
    wc.close()


def test_maestro_driver_against_the_virtual_board_both_protocols(board):
    vm, wc = board
    for device in (None, 12):
        m = mp.Maestro.open(wc.path, device=device)
        try:
            m.set_speed(0, 0)
            m.set_target(0, 7000)
            assert eventually(lambda: m.get_position(0) == 7000)
            assert m.get_errors() == 0
            m.set_targets(1, [5000, 6400])
            assert eventually(lambda: [m.get_position(c) for c in (1, 2)] == [5000, 6400])
        finally:
            m.close()
    # A command for another device number is ignored by this board.
    m = mp.Maestro.open(wc.path, device=5)
    try:
        m.set_target(0, 6500)
    finally:
        m.close()
    m = mp.Maestro.open(wc.path)
    try:
        assert m.get_position(0) == 7000 and vm.commands > 0   # the query is answered after the other's bytes
    finally:
        m.close()
    assert vm.ch[0].target == 7000


def test_outputs_move_at_the_boards_speed_limit(board):
    vm, wc = board
    m = mp.Maestro.open(wc.path)
    try:
        m.set_speed(0, 10)                     # 10 x 0.25 us / 10 ms = 250 us/s = 1000 quarter-us/s
        m.set_target(0, 6800)                  # 200 us away: 0.8 s
        t0 = time.monotonic()
        time.sleep(0.3)
        p = m.get_position(0)
        dt = time.monotonic() - t0
        assert 6000 < p < 6800
        assert p - 6000 <= 1000 * dt + 20
        assert eventually(lambda: m.get_position(0) == 6800)
    finally:
        m.close()


def test_board_errors_stop_the_driver_and_garbage_is_flushed(board):
    vm, wc = board
    m = mp.Maestro.open(wc.path)
    try:
        m.port.write(bytes([0x12, 0x34]))      # stray data bytes: the board flags a protocol error
        time.sleep(0.05)
        with pytest.raises(DriverError, match="serial protocol error"):
            m.check_errors()
        assert m.get_errors() == 0             # reading cleared it
        wc.pty.write(b"\x55\x66\x77")          # garbage from the board's side before a query
        time.sleep(0.05)
        m.set_speed(3, 0)
        m.set_target(3, 6200)
        assert eventually(lambda: m.get_position(3) == 6200)
        assert m.stats.flushed_bytes == 3
    finally:
        m.close()


def test_a_silent_board_a_missing_port_and_unplugging_are_one_line_errors(tmp_path):
    from runtime.drivers.rig import load_rig, open_servo_board

    silent = PtyDevice(lambda data: b"", "silent")
    # rig.toml's answer_timeout_ms reaches the driver: the silent board is given up after it.
    rig = write_rig(tmp_path, RIG.format(port=silent.path).replace('driver = "maestro"',
                                                                   'driver = "maestro"\nanswer_timeout_ms = 300', 1))
    board = open_servo_board(load_rig(rig))
    t0 = time.monotonic()
    with pytest.raises(DriverError, match="no answer within 300 ms"):
        board.maestro.get_errors()
    assert 0.25 < time.monotonic() - t0 < 2.0
    board.maestro.close()
    m = mp.Maestro.open(silent.path, answer_timeout_s=0.1)
    with pytest.raises(DriverError, match="no answer"):
        m.get_errors()
    silent.unplug()
    with pytest.raises(DriverError, match="unplugged"):
        m.get_errors()
        m.set_target(0, 6000)
    m.close()
    with pytest.raises(DriverError, match="cannot open") as e:
        mp.Maestro.open(str(tmp_path / "ttyACM9"))
    assert "\n" not in str(e.value)


def test_a_busy_port_is_refused():
    vm = VirtualMaestro()
    wc = WallClockMaestro(vm)
    try:
        m = mp.Maestro.open(wc.path)
        with pytest.raises(DriverError, match="holds it"):
            mp.Maestro.open(wc.path)
        m.close()
    finally:
        wc.close()


# ------------------------------------------------------------------ BNO085 RVC
DATASHEET_FRAME = bytes.fromhex("AAAADE0100 92FF25088DFEECFFD10300 0000E7".replace(" ", ""))


def test_rvc_parser_decodes_the_datasheets_example():
    r = RvcParser().feed(DATASHEET_FRAME)[0]
    assert r.index == 222
    np.testing.assert_allclose(np.degrees([r.yaw, r.pitch, r.roll]), [0.01, -1.10, 20.85], atol=1e-9)
    np.testing.assert_allclose(r.accel / 9.80665 * 1000, [-371, -20, 977], atol=1e-9)
    assert encode_rvc(222, 0.01, -1.10, 20.85, [-371, -20, 977]) == DATASHEET_FRAME


def test_rvc_parser_resynchronises_counts_checksums_and_drops():
    frames = [encode_rvc(i, 10.0, 2.0, -3.0, [0, 0, 1000]) for i in range(250, 262)]
    bad = bytearray(frames[3])
    bad[7] ^= 0x40                                            # a corrupted byte: the checksum fails
    stream = b"\x00\xaa\x13" + frames[0] + frames[1] + b"\xaa\xaa\x01" + frames[2] + bytes(bad) + frames[5] \
        + frames[6][:7]
    p = RvcParser()
    got = []
    for k in range(0, len(stream), 5):                        # arriving in small chunks
        got += p.feed(stream[k:k + 5])
    got += p.feed(frames[6][7:] + frames[7])
    assert [r.index for r in got] == [250, 251, 252, 255, 0, 1]
    assert p.checksum_errors >= 1 and p.skipped_bytes > 0
    assert p.dropped == 2                                     # 253 (corrupt) and 254 (never sent)


def test_rvc_rates_held_from_their_stamps_give_back_the_orientation_at_every_report():
    """A rate that ramps up (a saccade starting): each sample held from its stamp until the next
    (as SLAM's inertial prediction holds them) integrates to the reported orientation at every
    report time, to the quantisation; a sample stamped at its interval's end would be one report
    late (0.5 deg behind here). The acceleration is the interval's mean."""
    R0 = Rotation.from_euler("ZYX", [-20, 5, 3], degrees=True)
    axis = np.array([0.2, 1.0, -0.1]) / np.linalg.norm([0.2, 1.0, -0.1])

    def angle(t):                                   # 0 -> 1.2 rad/s over 0.4 s, then steady
        return 1.5 * min(t, 0.4) ** 2 + 1.2 * max(t - 0.4, 0.0)
    p, rr, samples, truth = RvcParser(), RvcRates(), [], []
    for n in range(61):
        R = R0 * Rotation.from_rotvec(axis * angle(n * 0.01))
        truth.append(R)
        y, pi, ro = R.as_euler("ZYX", degrees=True)
        for rep in p.feed(encode_rvc(n, y, pi, ro, [0, 0, 1000 + 10 * n])):
            s = rr.push(rep)
            if s is not None:
                samples.append(s)
    R = R0
    for k, (t, w, a) in enumerate(samples):
        assert t == pytest.approx(0.01 * k)
        assert a[2] == pytest.approx((1000 + 10 * k + 5) * 1e-3 * 9.80665, abs=0.01)
        R = R * Rotation.from_rotvec(w * 0.01)      # held over [t, t + 0.01)
        assert math.degrees((R.inv() * truth[k + 1]).magnitude()) < 0.03


def test_rvc_rates_by_differencing_give_back_the_rotation():
    """A constant body rate, quantised to 0.01 deg: each rate is within the quantisation's
    ~1 deg/s, and their integral returns the final orientation to 0.01 deg."""
    w_true = np.array([0.4, -0.25, 0.6])
    R0 = Rotation.from_euler("ZYX", [30, 10, -5], degrees=True)
    rates, p, rr = [], RvcParser(), RvcRates()
    for n in range(101):
        R = R0 * Rotation.from_rotvec(w_true * n * 0.01)
        y, pi, ro = R.as_euler("ZYX", degrees=True)
        for rep in p.feed(encode_rvc(n, y, pi, ro, [0, 0, 1000])):
            s = rr.push(rep)
            if s is not None:
                rates.append(s)
    assert rates[0][0] == pytest.approx(0.0) and rates[-1][0] == pytest.approx(0.99)   # each at its interval's start
    w = np.array([s[1] for s in rates])
    assert np.abs(w - w_true).max() < math.radians(3.0)
    R = R0
    for wi in w:
        R = R * Rotation.from_rotvec(wi * 0.01)
    truth = R0 * Rotation.from_rotvec(w_true * 1.0)
    assert math.degrees((R.inv() * truth).magnitude()) < 0.03


def test_text_protocol_and_bad_lines():
    p = TextParser()
    rows = p.feed(b"# header\n0.01 0.1 0.2 0.3 0 0 9.81\nnot a line\n0.02 1 2 3 4 5 nan\n0.03 0 0 0 0 0 9.8")
    rows += p.feed(b"1\n")
    assert [r[0] for r in rows] == [0.01, 0.03]
    assert p.bad_lines == 2


def test_imu_reader_maps_into_the_camera_frame_and_reports_unplugging():
    R_cam_imu = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    dev = PtyDevice(None, "imu")
    imu = ImuReader.open(dev.path, "text", R_cam_imu=R_cam_imu, anchor="device", gyro_bias=[0.0, 0.01, 0.0])
    try:
        dev.write(b"0.005 1 0 0 0 0 9.81\n0.010 0 1 0 0 0 9.81\n")
        s = imu.take_until(0.01, wait_s=1.0)
        assert len(s) == 2
        np.testing.assert_allclose(s.gyro[0], [0, -0.01, 1])       # IMU x is the optic axis
        np.testing.assert_allclose(s.gyro[1], [-1, -0.01, 0])      # IMU y is the image's left
        np.testing.assert_allclose(s.accel[0], [0, -9.81, 0])      # IMU z is the image's up
        dev.unplug()
        with pytest.raises(DriverError, match="unplugged"):
            time.sleep(0.2)
            imu.take_until(1.0, wait_s=0.5)
    finally:
        imu.close()


def test_a_checksum_burst_is_a_fault():
    dev = PtyDevice(None, "imu")
    imu = ImuReader.open(dev.path, "bno085-rvc", checksum_burst=5)
    try:
        bad = bytearray(encode_rvc(1, 0, 0, 0, [0, 0, 1000]))
        bad[-1] ^= 1
        dev.write(bytes(bad) * 10)
        time.sleep(0.3)
        with pytest.raises(DriverError, match="corrupt frames"):
            imu.take_until(1.0, wait_s=0.2)
    finally:
        imu.close()
        dev.close()


# ------------------------------------------------------------------ cameras
def _frames(tmp_path, n=5):
    paths = []
    for k in range(n):
        img = np.full((48, 64, 3), 40 * k, np.uint8)
        p = tmp_path / f"f{k:03d}.png"
        cv2.imwrite(str(p), img)
        paths.append(p)
    return paths


def test_pattern_and_folder_sources(tmp_path):
    _frames(tmp_path)
    src = ReplaySource(str(tmp_path / "f*.png"), fps=10)
    got = [src.read() for _ in range(5)]
    assert [f.t for f in got] == pytest.approx([0, 0.1, 0.2, 0.3, 0.4])
    assert [int(f.image[0, 0, 0]) for f in got] == [0, 40, 80, 120, 160]
    with pytest.raises(SessionEnded):
        src.read()
    folder = tmp_path / "live"
    (folder / "rgb").mkdir(parents=True)
    fs = FolderSource(folder)
    with pytest.raises(CameraStalled):
        fs.read(timeout_s=0.05)                                   # nothing yet: the camera stalls
    cv2.imwrite(str(folder / "rgb" / "a.png"), np.zeros((8, 8, 3), np.uint8))
    (folder / "rgb.txt").write_text("# frames\n0.5 rgb/a.png\n# end\n")
    assert fs.read().t == 0.5
    with pytest.raises(SessionEnded):
        fs.read()


def test_live_capture_keeps_only_the_newest_frame():
    class FastCapture:                 # a camera that delivers faster than the consumer reads
        def __init__(self):
            self.k = 0

        def read(self):
            time.sleep(0.005)
            self.k += 1
            if self.k > 60:
                return False, None
            return True, np.full((4, 4, 3), self.k % 256, np.uint8)

        def release(self):
            pass

    cam = LiveCapture(FastCapture(), "fake")
    a = cam.read(1.0)
    time.sleep(0.1)
    b = cam.read(1.0)
    assert b.index - a.index > 5                                  # frames in between were dropped
    assert b.index == cam.grabbed - 1 or b.index >= cam.grabbed - 3
    with pytest.raises(CameraStalled, match="stopped delivering"):
        for _ in range(100):
            cam.read(0.5)
    cam.close()


# ------------------------------------------------------------------ rig.toml
RIG = """head = "reference"
[servo]
driver = "maestro"
port = "{port}"
channels = {{ elevation = 0, pan = 1, cyclotorsion = 2 }}
[servo.calibration.elevation]
neutral_us = 1500.0
us_per_deg = 10.2
sign = 1
min_us = 650.0
max_us = 2350.0
[servo.calibration.pan]
neutral_us = 1500.0
us_per_deg = 10.2
sign = -1
min_us = 650.0
max_us = 2350.0
[servo.calibration.cyclotorsion]
neutral_us = 1500.0
us_per_deg = 10.2
sign = 1
min_us = 650.0
max_us = 2350.0
[camera]
source = 0
camera_toml = "camera.toml"
[imu]
driver = "bno085-rvc"
port = "/dev/ttyUSB0"
"""


def write_rig(tmp_path, text=None, port="/dev/ttyACM0"):
    from kinematics.camera import default_camera, save_camera

    save_camera(default_camera(), tmp_path / "camera.toml")
    p = tmp_path / "rig.toml"
    p.write_text(text if text is not None else RIG.format(port=port))
    return p


def test_rig_toml_in_the_issues_exact_form_loads(tmp_path):
    cfg = load_rig(write_rig(tmp_path))
    assert cfg.channels == (0, 1, 2) and cfg.calibration[1].sign == -1 and cfg.imu_driver == "bno085-rvc"
    assert cfg.camera_source == 0 and cfg.device is None
    assert cfg.answer_timeout_s == 0.2
    p = write_rig(tmp_path, RIG.format(port="/dev/ttyACM0").replace('driver = "maestro"',
                                                                     'driver = "maestro"\nanswer_timeout_ms = 1500', 1))
    assert load_rig(p).answer_timeout_s == 1.5
    assert cfg.imu_clock_offset_s == 0.0
    p = write_rig(tmp_path, RIG.format(port="/dev/ttyACM0").replace('port = "/dev/ttyUSB0"',
                                                                     'port = "/dev/ttyUSB0"\nclock_offset_ms = -12.5', 1))
    assert load_rig(p).imu_clock_offset_s == -0.0125
    p = write_rig(tmp_path, RIG.format(port="/dev/ttyACM0").replace('port = "/dev/ttyUSB0"',
                                                                     'port = "/dev/ttyUSB0"\nclock_offset_ms = "late"', 1))
    with pytest.raises(RigFileError, match="imu.clock_offset_ms"):
        load_rig(p)


@pytest.mark.parametrize("change, message", [
    (("max_us = 2350.0", "max_us = 2100.0", 1), "elevation range"),
    (("sign = -1", "sign = 2", 1), "sign"),
    (('driver = "maestro"', 'driver = "ssc32"', 1), "servo.driver"),
    (("cyclotorsion = 2 }", "cyclotorsion = 1 }", 1), "own channel"),
    (("us_per_deg = 10.2", "us_per_dgr = 10.2", 1), "did you mean 'us_per_deg'"),
    (('driver = "bno085-rvc"', 'driver = "mpu"', 1), "imu.driver"),
    (('driver = "maestro"', 'driver = "maestro"\nanswer_timeout_ms = 0.0', 1), "servo.answer_timeout_ms"),
])
def test_rig_toml_errors_are_one_line_naming_the_key(tmp_path, change, message):
    old, new, count = change
    p = write_rig(tmp_path, RIG.format(port="/dev/ttyACM0").replace(old, new, count))
    with pytest.raises(RigFileError, match=message) as e:
        load_rig(p)
    assert "\n" not in str(e.value)


def test_start_up_sets_the_rig_limits_on_the_board(tmp_path, board):
    vm, wc = board
    cfg = load_rig(write_rig(tmp_path, port=wc.path))
    sb = ServoBoard(cfg, mp.Maestro.open(wc.path))
    try:
        sb.start()
        sb.maestro.get_position(0)                                  # a round trip: the board has read it all
        us_s = 10.0 * 180 / math.pi * 10.2                          # the HS-50's 10 rad/s
        assert [vm.ch[c].speed for c in range(3)] == [mp.speed_units(us_s)] * 3
        assert [vm.ch[c].accel for c in range(3)] == [mp.accel_units(5000 * 10.2)] * 3
        vm.errors = 1 << 5                                          # the board's serial time-out
        with pytest.raises(DriverError, match="serial timeout"):
            sb.start()
    finally:
        sb.maestro.close()


def test_the_rvc_streams_noise_reaches_the_slams_prediction():
    from kinematics import reference_head
    from kinematics.camera import default_camera
    from runtime.apps.closed_loop import slam_config
    from runtime.drivers.imu import RVC_GYRO_NOISE
    from runtime.robot import RobotInfo
    from runtime.slam.config import DEFAULT_CONFIG

    devs = [PtyDevice(None, "imu"), PtyDevice(None, "imu")]
    rvc, text = ImuReader.open(devs[0].path, "bno085-rvc"), ImuReader.open(devs[1].path, "text")
    try:
        # Rates differenced from 0.01-deg orientations are far noisier than a raw gyro's.
        assert rvc.noise.gyro == RVC_GYRO_NOISE > 2 * DEFAULT_CONFIG.imu.imu_gyro_noise and text.noise is None
        head = reference_head()
        info = RobotInfo(head, default_camera(), 30.0, head.max_speed, imu_noise=rvc.noise)
        cfg = slam_config(info)
        assert (cfg.imu.imu_gyro_noise, cfg.imu.imu_accel_noise) == (rvc.noise.gyro, rvc.noise.accel)
        assert slam_config(RobotInfo(head, default_camera(), 30.0, head.max_speed)) == DEFAULT_CONFIG
        # A measured IMU latency (rig.toml's [imu] clock_offset_ms) is where SLAM starts its clock offset.
        late = RobotInfo(head, default_camera(), 30.0, head.max_speed, imu_clock_offset_s=0.045)
        assert slam_config(late).imu.time_offset0 == 0.045
    finally:
        rvc.close()
        text.close()
        for d in devs:
            d.close()
