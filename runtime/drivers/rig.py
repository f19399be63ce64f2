"""The hardware rig: ``rig.toml`` read and checked, and :class:`HardwareRig`, a
:class:`runtime.robot.Robot` over the servos (a Pololu Maestro with hobby servos, or Dynamixel
X-series smart servos), the camera and the IMU. It sends what it is given: ``wvr.assemble.make_rig``
wraps it in the safety chain (``runtime.safety.SafeRobot``: limits, watchdog, latched stop),
the same chain the twin is driven through; the rig adds the pulses' clipping and the board's
own speed and acceleration limits.

rig.toml (the contract; the keys marked optional may be left out)::

    head = "reference"            # or a head.toml path (relative to rig.toml)
    [servo]
    driver = "maestro"
    port = "/dev/ttyACM0"
    channels = { elevation = 0, pan = 1, cyclotorsion = 2 }
    baud = 115200                 # optional
    device = 12                   # optional: the Pololu protocol with this device number (else compact)
    speed_limit_deg_s = 573.0     # optional: the board's speed limit (default: the servos' own)
    accel_limit_deg_s2 = 5000.0   # optional: the board's acceleration limit
    home_deg = [0.0, 0.0, 0.0]    # optional
    [servo.calibration.elevation]
    neutral_us = 1500.0           # pulse at 0 deg
    us_per_deg = 10.2
    sign = 1                      # +1 or -1: which way a positive angle turns
    min_us = 650.0                # the board's limits for this channel
    max_us = 2350.0
    # [servo.calibration.pan], [servo.calibration.cyclotorsion] alike
    [camera]
    source = 0                    # a V4L2 device index, a device path, a video file or an image pattern
    camera_toml = "camera.toml"
    fps = 30.0                    # optional
    timeout_s = 1.0               # optional: longer without a frame is a fault
    [imu]
    driver = "bno085-rvc"         # or "text", or "none"
    port = "/dev/ttyUSB0"
    baud = 115200                 # optional
    R_cam_imu = [[1,0,0],[0,1,0],[0,0,1]]   # optional: IMU axes into the camera frame
    anchor = "arrival"            # optional: "arrival", "camera" or "device" (runtime.drivers.imu)
    rate_hz = 100.0               # optional: the stream's sample rate (default 100 RVC, 200 text)
    gyro_bias = [0, 0, 0]         # optional, rad/s, camera frame (wvr calibrate imu writes it)
    accel_bias = [0, 0, 0]        # optional, m/s^2, camera frame
    clock_offset_ms = 0.0         # optional: the IMU's stamps' measured lag behind the camera's,
                                  # where SLAM starts learning it (it learns up to ~20 ms alone)
    [safety]                      # optional table: runtime.safety.SafetySettings
    motion_limit_deg_s = 30.0     # default runtime.robot.MOTION_LIMIT_DEG_S
    pose_timeout_s = 0.5
    hold_s = 1.0
    home_rate_deg_s = 20.0
    estop_file = "estop.latch"
    [start]                       # optional
    target = "target.toml"        # the known target and its clicked pixels in the first image

A head with Dynamixel X-series servos (runtime.drivers.dynamixel) has instead::

    [servo]
    driver = "dynamixel"
    port = "/dev/ttyUSB0"         # the U2D2 (or any Protocol 2.0 adapter)
    ids = { elevation = 1, pan = 2, cyclotorsion = 3 }
    baud = 57600                  # optional: the servos' baud rate
    watchdog_ms = 100             # optional: each servo's bus watchdog (20..2540 ms)
    speed_limit_deg_s, accel_limit_deg_s2, home_deg as above
    [servo.calibration.elevation]
    zero_ticks = 2048.0           # position at 0 deg
    ticks_per_deg = 11.3778       # 4096 / 360 on X-series
    sign = 1
    min_ticks = 1024.0            # inside the servo's own position limits
    max_ticks = 3072.0

Every error is one line naming the key and the fix; a joint range of the head that the
calibration cannot reach inside ``min_us..max_us`` is refused with the joint named.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kinematics import JOINT_NAMES, HeadGeometry, load_head, reference_head
from kinematics.camera import CameraIntrinsics, load_camera
from kinematics.tomlfile import read_toml

from ..robot import JOINTS_COMMANDED, JOINTS_MEASURED, MOTION_LIMIT_DEG_S, ImuSamples, JointCommand, Observation, RobotInfo
from ..safety import SafetySettings
from . import DriverError
from .calibration import ServoCalibration
from .dynamixel import DynamixelBoard, DynamixelBus, TickCalibration
from .maestro import Maestro, accel_units, speed_units


class RigFileError(ValueError):
    """rig.toml is wrong: one line naming the key and the fix."""


_KEYS = {
    "": {"head", "servo", "camera", "imu", "safety", "start"},
    "servo": {"driver", "port", "channels", "baud", "device", "speed_limit_deg_s", "accel_limit_deg_s2", "home_deg",
              "calibration", "answer_timeout_ms"},
    "servo-dynamixel": {"driver", "port", "ids", "baud", "watchdog_ms", "speed_limit_deg_s", "accel_limit_deg_s2",
                        "home_deg", "calibration"},
    "calibration": {"neutral_us", "us_per_deg", "sign", "min_us", "max_us"},
    "calibration-dynamixel": {"zero_ticks", "ticks_per_deg", "sign", "min_ticks", "max_ticks"},
    "camera": {"source", "camera_toml", "fps", "timeout_s"},
    "imu": {"driver", "port", "baud", "R_cam_imu", "anchor", "gyro_bias", "accel_bias", "rate_hz", "clock_offset_ms"},
    "safety": {"motion_limit_deg_s", "pose_timeout_s", "hold_s", "home_rate_deg_s", "estop_file", "heartbeat_timeout_s"},
    "start": {"target"},
}


@dataclass(frozen=True)
class RigConfig:
    path: Path
    head: HeadGeometry
    port: str
    channels: tuple[int, int, int]                  # Maestro channels, or Dynamixel IDs
    calibration: tuple                              # ServoCalibration (Maestro) or TickCalibration (Dynamixel) x 3
    camera: CameraIntrinsics | None                 # None when loaded without the camera (bring-up)
    camera_source: object
    baud: int = 115200
    device: int | None = None
    speed_limit_rad_s: np.ndarray = field(default_factory=lambda: np.full(3, 10.0))
    accel_limit_rad_s2: float = math.radians(5000.0)
    home: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fps: float = 30.0
    camera_timeout_s: float = 1.0
    imu_driver: str = "none"
    imu_port: str | None = None
    imu_baud: int = 115200
    R_cam_imu: np.ndarray = field(default_factory=lambda: np.eye(3))
    imu_anchor: str = "arrival"
    imu_rate_hz: float = 100.0
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    imu_clock_offset_s: float = 0.0
    safety: SafetySettings = field(default_factory=SafetySettings)
    estop_file: Path | None = None
    start_target: Path | None = None
    servo_driver: str = "maestro"
    watchdog_s: float = 0.1                         # Dynamixel: each servo's bus watchdog
    answer_timeout_s: float = 0.2                   # Maestro: how long a query waits for its answer

    @property
    def base(self) -> Path:
        return self.path.parent


def _fail(path, key, why):
    raise RigFileError(f"{path}: {key}: {why}")


def _number(path, d, key, where, default=None, positive=True):
    if key not in d:
        if default is None:
            _fail(path, f"{where}.{key}" if where else key, "missing; add it")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        _fail(path, f"{where}.{key}" if where else key, f"{v!r} must be a {'positive ' if positive else ''}number")
    return float(v)


def _check_keys(path, d, table, where):
    allowed = _KEYS[table]
    for k in d:
        if k not in allowed:
            import difflib

            close = difflib.get_close_matches(k, sorted(allowed), n=1)
            _fail(path, f"{where}.{k}" if where else k,
                  "unknown key" + (f"; did you mean {close[0]!r}?" if close else f"; [{where or 'top'}] takes {', '.join(sorted(allowed))}"))


def _vector(path, d, key, where, n=3, default=None):
    if key not in d:
        return default
    v = d[key]
    try:
        a = np.asarray(v, float)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != (n,) or not np.isfinite(a).all():
        _fail(path, f"{where}.{key}", f"{v!r} must be {n} finite numbers")
    return a


def load_rig(path: str | Path, with_camera: bool = True) -> RigConfig:
    """Read and check rig.toml (see the module docstring). with_camera=False reads the servos
    and the safety settings only (the head's bring-up): no [camera] table is needed, and the
    config's camera is None."""
    path = Path(path)
    d = read_toml(path, RigFileError, "a rig.toml (see the README's rig section)")
    _check_keys(path, d, "", "")
    base = path.parent
    head_ref = d.get("head", "reference")
    if not isinstance(head_ref, str):
        _fail(path, "head", f"{head_ref!r} must be \"reference\" or a head.toml path")
    head = reference_head() if head_ref == "reference" else load_head(base / head_ref)
    for t in ("servo", "camera") if with_camera else ("servo",):
        if t not in d or not isinstance(d[t], dict):
            _fail(path, f"[{t}]", "missing table; add it (see the README's rig section)")
    sv = d["servo"]
    driver = sv.get("driver")
    if driver not in ("maestro", "dynamixel"):
        _fail(path, "servo.driver", f"{driver!r}: use \"maestro\" (hobby servos) or \"dynamixel\" (X-series)")
    dxl = driver == "dynamixel"
    _check_keys(path, sv, "servo-dynamixel" if dxl else "servo", "servo")
    if not isinstance(sv.get("port"), str) or not sv["port"]:
        _fail(path, "servo.port", "missing; give the " + ("Dynamixel bus's port, e.g. \"/dev/ttyUSB0\"" if dxl
                                                          else "Maestro's command port, e.g. \"/dev/ttyACM0\""))
    key, what, top = ("ids", "servo ID", 252) if dxl else ("channels", "channel number", 23)
    ch = sv.get(key)
    if not isinstance(ch, dict) or set(ch) != set(JOINT_NAMES):
        _fail(path, f"servo.{key}", f"must map each of {', '.join(JOINT_NAMES)} to a {what}, e.g. "
                                    + ("{ elevation = 1, pan = 2, cyclotorsion = 3 }" if dxl
                                       else "{ elevation = 0, pan = 1, cyclotorsion = 2 }"))
    channels = []
    for n in JOINT_NAMES:
        c = ch[n]
        if isinstance(c, bool) or not isinstance(c, int) or not int(dxl) <= c <= top:
            _fail(path, f"servo.{key}.{n}", f"{c!r} must be a {what} {int(dxl)}..{top}")
        channels.append(c)
    if len(set(channels)) != 3:
        _fail(path, f"servo.{key}", f"{channels}: each joint needs its own {what}")
    cal_d = sv.get("calibration")
    if not isinstance(cal_d, dict):
        _fail(path, "[servo.calibration.<joint>]", f"missing; add a table for each of {', '.join(JOINT_NAMES)}")
    cals = []
    for j, n in enumerate(JOINT_NAMES):
        c = cal_d.get(n)
        where = f"servo.calibration.{n}"
        keys = ("zero_ticks", "ticks_per_deg", "min_ticks", "max_ticks") if dxl else \
            ("neutral_us", "us_per_deg", "min_us", "max_us")
        if not isinstance(c, dict):
            _fail(path, f"[{where}]", f"missing table; add {', '.join(keys[:2])}, sign, {', '.join(keys[2:])}")
        _check_keys(path, c, "calibration-dynamixel" if dxl else "calibration", where)
        sign = c.get("sign")
        if sign not in (1, -1) or isinstance(sign, bool):
            _fail(path, f"{where}.sign", f"{sign!r} must be 1 or -1 (which way a positive angle turns)")
        zero, per, lo_v, hi_v = (_number(path, c, k, where, positive=not (dxl and k != "ticks_per_deg")) for k in keys)
        try:
            cal = TickCalibration(zero, per, int(sign), lo_v, hi_v) if dxl else \
                ServoCalibration(zero, per, int(sign), lo_v, hi_v)
        except DriverError as e:
            _fail(path, f"[{where}]", str(e))
        lo, hi = cal.angle_range()
        if head.lower[j] < lo - 1e-9 or head.upper[j] > hi + 1e-9:
            unit = "ticks outside min_ticks..max_ticks" if dxl else "pulses outside min_us..max_us"
            _fail(path, f"[{where}]", f"the head's {n} range {math.degrees(head.lower[j]):.1f}..{math.degrees(head.upper[j]):.1f} "
                                      f"deg needs {unit} (reachable {math.degrees(lo):.1f}.."
                                      f"{math.degrees(hi):.1f} deg); widen {keys[2]}/{keys[3]} if the servo allows, or "
                                      f"narrow the joint's range in head.toml")
        cals.append(cal)
    baud = int(_number(path, sv, "baud", "servo", 57600 if dxl else 115200))
    watchdog_s = _number(path, sv, "watchdog_ms", "servo", 100.0) / 1000.0
    if not 0.02 <= watchdog_s <= 2.54:
        _fail(path, "servo.watchdog_ms", f"{1000 * watchdog_s:g} must lie in 20..2540 ms (the servos' 20 ms units)")
    answer_timeout_s = _number(path, sv, "answer_timeout_ms", "servo", 200.0) / 1000.0
    if not 0.01 <= answer_timeout_s <= 5.0:
        _fail(path, "servo.answer_timeout_ms", f"{1000 * answer_timeout_s:g} must lie in 10..5000 ms (a Maestro answers "
                                               "within a millisecond; 200 is the default)")
    device = sv.get("device")
    if device is not None and (isinstance(device, bool) or not isinstance(device, int) or not 0 <= device <= 127):
        _fail(path, "servo.device", f"{device!r} must be the board's device number 0..127 (default 12)")
    vmax = head.max_speed
    speed = _number(path, sv, "speed_limit_deg_s", "servo", float(np.degrees(vmax.min())))
    if math.radians(speed) > float(vmax.min()) + 1e-9:
        _fail(path, "servo.speed_limit_deg_s", f"{speed:g} deg/s exceeds the servos' {math.degrees(vmax.min()):.0f} deg/s; "
                                               f"use at most that")
    accel = _number(path, sv, "accel_limit_deg_s2", "servo", 5000.0)
    home = _vector(path, sv, "home_deg", "servo", default=np.zeros(3))
    home = np.radians(home)
    if np.any(home < head.lower) or np.any(home > head.upper):
        _fail(path, "servo.home_deg", f"{np.degrees(home).round(1).tolist()} lies outside the head's joint ranges")

    camera, cd, fps, cam_timeout = None, {"source": None}, 30.0, 1.0
    if with_camera:
        cd = d["camera"]
        _check_keys(path, cd, "camera", "camera")
        if "source" not in cd:
            _fail(path, "camera.source", "missing; give a V4L2 device index, a device path, a video file or an image pattern")
        if "camera_toml" not in cd or not isinstance(cd["camera_toml"], str):
            _fail(path, "camera.camera_toml", "missing; give the camera.toml with the intrinsics (wvr calibrate camera writes one)")
        camera = load_camera(base / cd["camera_toml"])
        fps = _number(path, cd, "fps", "camera", 30.0)
        cam_timeout = _number(path, cd, "timeout_s", "camera", 1.0)

    im = d.get("imu", {"driver": "none"})
    _check_keys(path, im, "imu", "imu")
    drv = im.get("driver", "none")
    if drv not in ("bno085-rvc", "text", "none"):
        _fail(path, "imu.driver", f"{drv!r}: use \"bno085-rvc\", \"text\" or \"none\"")
    imu_port = im.get("port")
    if drv != "none" and (not isinstance(imu_port, str) or not imu_port):
        _fail(path, "imu.port", "missing; give the IMU's serial port, e.g. \"/dev/ttyUSB0\", or set driver = \"none\"")
    R = np.eye(3)
    if "R_cam_imu" in im:
        try:
            R = np.asarray(im["R_cam_imu"], float)
        except (TypeError, ValueError):
            R = np.zeros(0)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or abs(np.linalg.det(R) - 1) > 1e-6:
            _fail(path, "imu.R_cam_imu", "must be a 3x3 rotation matrix (rows of numbers, orthonormal, det +1)")
    anchor = im.get("anchor", "arrival")
    if anchor not in ("arrival", "camera", "device"):
        _fail(path, "imu.anchor", f"{anchor!r}: use \"arrival\", \"camera\" or \"device\"")

    sf = d.get("safety", {})
    _check_keys(path, sf, "safety", "safety")
    limit = _number(path, sf, "motion_limit_deg_s", "safety", MOTION_LIMIT_DEG_S)
    if math.radians(limit) > math.radians(speed) + 1e-9:
        _fail(path, "safety.motion_limit_deg_s", f"{limit:g} deg/s exceeds the board's speed limit {speed:g} deg/s")
    hb = sf.get("heartbeat_timeout_s")
    safety = SafetySettings(motion_limit_rad_s=math.radians(limit),
                            pose_timeout_s=_number(path, sf, "pose_timeout_s", "safety", 0.5),
                            heartbeat_timeout_s=None if hb is None else _number(path, sf, "heartbeat_timeout_s", "safety"),
                            hold_s=_number(path, sf, "hold_s", "safety", 1.0),
                            home_rate_rad_s=math.radians(_number(path, sf, "home_rate_deg_s", "safety", 20.0)),
                            home=tuple(home))
    estop = base / sf.get("estop_file", "estop.latch")
    st = d.get("start", {})
    _check_keys(path, st, "start", "start")
    start = base / st["target"] if "target" in st else None
    return RigConfig(path=path, head=head, port=sv["port"], channels=tuple(channels), calibration=tuple(cals),
                     camera=camera, camera_source=cd["source"], baud=baud, device=device,
                     speed_limit_rad_s=np.full(3, math.radians(speed)), accel_limit_rad_s2=math.radians(accel),
                     home=home, fps=fps, camera_timeout_s=cam_timeout, imu_driver=drv, imu_port=imu_port,
                     imu_baud=int(_number(path, im, "baud", "imu", 115200)), R_cam_imu=R, imu_anchor=anchor,
                     imu_rate_hz=_number(path, im, "rate_hz", "imu", 100.0 if drv == "bno085-rvc" else 200.0),
                     gyro_bias=_vector(path, im, "gyro_bias", "imu", default=np.zeros(3)),
                     accel_bias=_vector(path, im, "accel_bias", "imu", default=np.zeros(3)),
                     imu_clock_offset_s=_number(path, im, "clock_offset_ms", "imu", 0.0, positive=False) / 1000.0,
                     safety=safety, estop_file=estop, start_target=start, servo_driver=driver, watchdog_s=watchdog_s,
                     answer_timeout_s=answer_timeout_s)


class ServoBoard:
    """The Maestro with the rig's channels and calibration: angles in, pulses out, limits on the board."""

    def __init__(self, cfg: RigConfig, maestro: Maestro):
        self.cfg = cfg
        self.maestro = maestro

    def speed_units(self, rate_rad_s) -> list[int]:
        rate = np.broadcast_to(np.asarray(rate_rad_s, float), (3,))
        return [speed_units(c.us_per_rad * r) for c, r in zip(self.cfg.calibration, rate)]

    def accel_units(self) -> list[int]:
        return [accel_units(c.us_per_rad * self.cfg.accel_limit_rad_s2) for c in self.cfg.calibration]

    def start(self, speed_rad_s=None) -> None:
        """Clear and check the error register, then set every channel's speed and acceleration
        limits on the board (so even a wrong target moves no faster than the rig's limits)."""
        m = self.maestro
        m.check_errors()
        speeds = self.speed_units(self.cfg.speed_limit_rad_s if speed_rad_s is None else speed_rad_s)
        for ch, sp, ac in zip(self.cfg.channels, speeds, self.accel_units()):
            m.set_speed(ch, sp)
            m.set_acceleration(ch, ac)

    def pulses_qus(self, q) -> list[int]:
        return [c.to_qus(v) for c, v in zip(self.cfg.calibration, np.asarray(q, float))]

    def send(self, q) -> list[int]:
        """Targets for angles (3,) rad; one Set Multiple Targets when the channels are adjacent."""
        qus = self.pulses_qus(q)
        chs = list(self.cfg.channels)
        order = np.argsort(chs)
        sorted_ch = [chs[i] for i in order]
        if sorted_ch == list(range(sorted_ch[0], sorted_ch[0] + 3)):
            self.maestro.set_targets(sorted_ch[0], [qus[i] for i in order])
        else:
            for ch, v in zip(chs, qus):
                self.maestro.set_target(ch, v)
        return qus

    def positions(self) -> np.ndarray:
        """(3,) rad: the pulses the board sends now, as angles."""
        return np.array([float(c.to_rad(self.maestro.get_position(ch) / 4.0))
                         for c, ch in zip(self.cfg.calibration, self.cfg.channels)])

    def check_errors(self) -> None:
        self.maestro.check_errors()

    def close(self) -> None:
        self.maestro.close()

    def move_slowly(self, q_goal, rate_rad_s: float, timeout_s: float = 30.0, on_progress=None) -> np.ndarray:
        """Go to ``q_goal`` with the board's speed limit at ``rate_rad_s`` (the board ramps), and
        wait until the outputs arrive (or the time-out); restores the rig's speed limits."""
        m = self.maestro
        for ch, sp in zip(self.cfg.channels, self.speed_units(rate_rad_s)):
            m.set_speed(ch, sp)
        target = self.pulses_qus(q_goal)
        self.send(q_goal)
        t_end = time.monotonic() + timeout_s
        q = self.positions()
        while time.monotonic() < t_end:
            pos = [m.get_position(ch) for ch in self.cfg.channels]
            q = np.array([float(c.to_rad(p / 4.0)) for c, p in zip(self.cfg.calibration, pos)])
            if on_progress is not None:
                on_progress(q)
            if all(abs(p - t) <= 1 for p, t in zip(pos, target)):
                break
            time.sleep(0.02)
        for ch, sp in zip(self.cfg.channels, self.speed_units(self.cfg.speed_limit_rad_s)):
            m.set_speed(ch, sp)
        return q


def open_servo_board(cfg: RigConfig):
    """The rig's servo board: a :class:`ServoBoard` over the Maestro, or a
    :class:`runtime.drivers.dynamixel.DynamixelBoard` (both: ``start``, ``send``, ``positions``,
    ``move_slowly``, ``check_errors``, ``close``)."""
    if cfg.servo_driver == "dynamixel":
        return DynamixelBoard(cfg, DynamixelBus(cfg.port, cfg.baud, cfg.channels))
    return ServoBoard(cfg, Maestro.open(cfg.port, cfg.baud, cfg.device, cfg.answer_timeout_s))


class HardwareRig:
    """The real head as a :class:`runtime.robot.Robot`: ``reset`` starts the board and reads the
    first frame, ``step`` sends the command and waits for the next frame; the joint angles
    observed are the board's ramped outputs (hobby servos have no encoders: ``q_source =
    "commanded"``) or a Dynamixel's encoders (``"measured"``). Drive it through
    ``wvr.assemble.make_rig``, which puts the safety chain (``runtime.safety.SafeRobot``, with
    ``cfg.safety`` and the latch in ``cfg.estop_file``) in front of it."""

    def __init__(self, cfg: RigConfig):
        from .camera import open_camera
        from .imu import ImuReader

        self.cfg = cfg
        self.board = open_servo_board(cfg)
        self.maestro = getattr(self.board, "maestro", None)
        self.q_source = JOINTS_MEASURED if cfg.servo_driver == "dynamixel" else JOINTS_COMMANDED
        self.camera = None
        self.imu = None
        try:
            self.camera = open_camera(cfg.camera_source, cfg.base, cfg.fps)
            if cfg.imu_driver != "none":
                self.imu = ImuReader.open(cfg.imu_port, cfg.imu_driver, cfg.imu_baud, R_cam_imu=cfg.R_cam_imu,
                                          gyro_bias=cfg.gyro_bias, accel_bias=cfg.accel_bias, anchor=cfg.imu_anchor,
                                          period_s=1.0 / cfg.imu_rate_hz)
        except Exception:
            self.close()
            raise
        self.t = None
        self.sent_qus: list[list[int]] = []
        self.closed = False

    @property
    def info(self) -> RobotInfo:
        return RobotInfo(head=self.cfg.head, camera=self.cfg.camera, frame_rate=self.cfg.fps,
                         speed_limit=np.minimum(self.cfg.head.max_speed, self.cfg.speed_limit_rad_s), name="rig",
                         imu_noise=self.imu.noise if self.imu is not None else None,
                         imu_clock_offset_s=self.cfg.imu_clock_offset_s)

    def _imu_until(self, t: float) -> ImuSamples:
        if self.imu is None:
            return ImuSamples()
        return self.imu.take_until(t, wait_s=0.1)

    def reset(self) -> Observation:
        self.board.start()
        q0 = self.board.positions()
        if np.any(q0 < self.cfg.head.lower - 0.02) or np.any(q0 > self.cfg.head.upper + 0.02):
            raise DriverError(f"the board's outputs {np.degrees(q0).round(1).tolist()} deg lie outside the head's ranges; "
                              f"home it first (wvr head --rig {self.cfg.path} home)")
        frame = self.camera.read(max(self.cfg.camera_timeout_s, 5.0))
        if self.imu is not None:
            self.imu.anchor_at(frame.t)
        self._imu_until(frame.t)            # drop what came before the first frame
        self.t = frame.t
        return Observation(frame.t, frame.image, ImuSamples(), q0, self.q_source)

    def step(self, command: JointCommand) -> Observation:
        if self.t is None:
            raise RuntimeError("call reset() first")
        self.sent_qus.append(self.board.send(command.q))
        self.board.check_errors()
        frame = self.camera.read(self.cfg.camera_timeout_s)
        # The board's outputs when the frame has come (read before it, they were the period's
        # start: the controller then saw its joints a period late, and a walk's fixation rang).
        q_board = self.board.positions()
        imu = self._imu_until(frame.t)
        self.t = frame.t
        return Observation(frame.t, frame.image, imu, q_board, self.q_source)

    def safe_stop(self, reason: str = "", home: bool = True) -> str:
        """Hold, then (``home``) go home slowly, never raising: returns what happened (for the
        session's notes). The safety chain asks for no homing while its stop is latched."""
        notes = []
        try:
            q_now = self.board.positions()
            self.board.send(q_now)                                 # hold
            notes.append("held")
            if home:
                self.board.move_slowly(self.cfg.home, self.cfg.safety.home_rate_rad_s, timeout_s=15.0)
                notes.append("homed")
        except DriverError as e:
            notes.append(f"could not finish ({e})")
        return ", ".join(notes)

    def close(self) -> None:
        if getattr(self, "closed", False):
            return
        self.closed = True
        for dev in (self.imu, self.camera):
            if dev is not None:
                try:
                    dev.close()
                except Exception:  # noqa: BLE001 - closing must not hide the fault being reported
                    pass
        self.board.close()
