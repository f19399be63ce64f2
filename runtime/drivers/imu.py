"""IMU drivers: the BNO085's UART-RVC stream and a plain text line protocol, read in a thread,
delivered as :class:`runtime.robot.ImuSamples` in the camera frame.

**BNO085 UART-RVC** (BNO08x datasheet, "UART-RVC protocol"): 100 Hz, 19-byte frames::

    0xAA 0xAA | index | yaw pitch roll (int16 LE, 0.01 deg) | ax ay az (int16 LE, mg) | 3 reserved | checksum

The checksum is the sum of bytes 2..17 (index to the reserved bytes) mod 256. The orientation
is applied as yaw (about z), then pitch (about the new y), then roll (about the newest x):
``R_ref_imu = Rz(yaw) Ry(pitch) Rx(roll)``; the acceleration includes gravity (specific force).
The parser resynchronises on the header after garbage or a bad checksum and counts the reports
lost between indices.

The RVC stream has no angular rates. They are derived by differencing the orientation:
``w_n = log(R_{n-1}^T R_n) / dt`` over each 10 ms report interval, so that integrating the rates
gives back the sensor's own fused orientation exactly (the quantisation of 0.01 deg per report
becomes about 0.5 deg/s of rate noise per sample, which cancels in any integral). A sample holds
for the interval it was differenced over: it is stamped at the interval's start (report n's
sample at ``t0 + (n - 1) / 100``, dropped reports counted in n), since its consumers hold each
sample until the next (SLAM's inertial prediction); its acceleration is the mean of the
interval's two reports. Stamped at the interval's end, every rate came one report late: 0.3 deg
of rotation per frame at 30 deg/s, enough to throw SLAM's predictions off during a saccade. The
stream is anchored at the rig's clock when it starts.

**Text lines**, for other boards (and the hardware-in-the-loop IMU): ``t wx wy wz ax ay az`` per
line (s, rad/s, m/s^2, the IMU's frame; imu.txt's layout), ``#`` lines ignored; the board's own
time stamps are kept.

Both map into the camera frame by the rig's extrinsic rotation ``R_cam_imu`` and subtract the
still biases that ``wvr calibrate imu`` wrote (camera frame).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..robot import ImuNoise, ImuSamples
from . import DriverError

#: The RVC stream's noise as an inertial input (runtime.robot.ImuNoise): rates differenced from
#: 0.01-deg orientations at 100 Hz carry about 0.5 deg/s of noise a sample (0.0007 rad/s/sqrt(Hz)),
#: taken with a margin for the sensor fusion's own errors as 0.002; the specific force a raw
#: MEMS part's, doubled as SlamConfig's default is.
RVC_GYRO_NOISE = 0.002          # rad/s/sqrt(Hz)
RVC_ACCEL_NOISE = 0.004         # m/s^2/sqrt(Hz)

RVC_FRAME_BYTES = 19
RVC_HEADER = b"\xaa\xaa"
RVC_RATE_HZ = 100.0
G = 9.80665          # the datasheet's mg


@dataclass(frozen=True)
class RvcReport:
    """One RVC frame. index : 0..255. yaw, pitch, roll : rad. accel : (3,) m/s^2, IMU frame."""

    index: int
    yaw: float
    pitch: float
    roll: float
    accel: np.ndarray

    @property
    def R_ref_imu(self) -> np.ndarray:
        return Rotation.from_euler("ZYX", [self.yaw, self.pitch, self.roll]).as_matrix()


def rvc_checksum(frame: bytes) -> int:
    return sum(frame[2:18]) & 0xFF


def encode_rvc(index: int, yaw_deg: float, pitch_deg: float, roll_deg: float, accel_mg) -> bytes:
    """One RVC frame (for simulated devices and tests), values rounded to the protocol's units."""
    def i16(v):
        v = int(round(v))
        v = max(-32768, min(32767, v))
        return (v & 0xFFFF).to_bytes(2, "little")
    body = bytes([index & 0xFF]) + i16(yaw_deg * 100) + i16(pitch_deg * 100) + i16(roll_deg * 100) \
        + b"".join(i16(a) for a in accel_mg) + b"\x00\x00\x00"
    frame = RVC_HEADER + body
    return frame + bytes([rvc_checksum(frame + b"\x00")])


def _i16(b: bytes, k: int) -> int:
    return int.from_bytes(b[k:k + 2], "little", signed=True)


@dataclass
class RvcParser:
    """Bytes in, reports out. Counters: frames, checksum_errors, skipped_bytes (garbage passed
    over while resynchronising), dropped (reports missing between consecutive indices)."""

    frames: int = 0
    checksum_errors: int = 0
    skipped_bytes: int = 0
    dropped: int = 0
    _buf: bytearray = field(default_factory=bytearray)
    _last_index: int | None = None

    def feed(self, data: bytes) -> list[RvcReport]:
        self._buf += data
        out = []
        buf = self._buf
        while True:
            k = buf.find(RVC_HEADER)
            if k < 0:
                keep = 1 if buf[-1:] == b"\xaa" else 0
                self.skipped_bytes += len(buf) - keep
                del buf[:len(buf) - keep]
                break
            if k:
                self.skipped_bytes += k
                del buf[:k]
            if len(buf) < RVC_FRAME_BYTES:
                break
            frame = bytes(buf[:RVC_FRAME_BYTES])
            if rvc_checksum(frame) != frame[18]:
                # A false header inside garbage, or a corrupted frame: step past this header only.
                self.checksum_errors += 1
                self.skipped_bytes += 1
                del buf[:1]
                continue
            del buf[:RVC_FRAME_BYTES]
            idx = frame[2]
            if self._last_index is not None:
                self.dropped += (idx - self._last_index - 1) % 256
            self._last_index = idx
            self.frames += 1
            out.append(RvcReport(idx, math.radians(_i16(frame, 3) / 100), math.radians(_i16(frame, 5) / 100),
                                 math.radians(_i16(frame, 7) / 100),
                                 np.array([_i16(frame, 9), _i16(frame, 11), _i16(frame, 13)], float) * 1e-3 * G))
        return out


class RvcRates:
    """Reports to samples (IMU frame): rates by differencing consecutive orientations, stamped
    by index at ``t0 + n / rate`` (n counts dropped reports too)."""

    def __init__(self, rate_hz: float = RVC_RATE_HZ):
        self.period = 1.0 / rate_hz
        self.t0: float | None = None
        self._n = 0
        self._prev: RvcReport | None = None

    def push(self, r: RvcReport) -> tuple[float, np.ndarray, np.ndarray] | None:
        """The sample describing the interval that ends at report n: (its start, n - 1 periods after
        report 0 (more when reports were dropped: then their whole gap), its mean rate, its mean
        specific force), or None for report 0."""
        if self._prev is None:
            self.t0 = 0.0
            self._prev = r
            return None
        steps = (r.index - self._prev.index) % 256 or 256
        start = self.t0 + self._n * self.period          # the interval this sample describes starts here
        self._n += steps
        w = Rotation.from_matrix(self._prev.R_ref_imu.T @ r.R_ref_imu).as_rotvec() / (steps * self.period)
        a = 0.5 * (np.asarray(self._prev.accel, float) + np.asarray(r.accel, float))
        self._prev = r
        return start, w, a


@dataclass
class TextParser:
    """``t wx wy wz ax ay az`` lines in, (t, gyro, accel) out; bad lines counted."""

    lines: int = 0
    bad_lines: int = 0
    _buf: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes) -> list[tuple[float, np.ndarray, np.ndarray]]:
        self._buf += data
        out = []
        while True:
            k = self._buf.find(b"\n")
            if k < 0:
                if len(self._buf) > 4096:     # no line end in 4 kB: garbage, drop it
                    self.bad_lines += 1
                    self._buf.clear()
                break
            line = bytes(self._buf[:k]).decode("ascii", "replace").strip()
            del self._buf[:k + 1]
            if not line or line.startswith("#"):
                continue
            try:
                v = [float(x) for x in line.split()]
            except ValueError:
                v = []
            if len(v) != 7 or not all(math.isfinite(x) for x in v):
                self.bad_lines += 1
                continue
            self.lines += 1
            out.append((v[0], np.array(v[1:4]), np.array(v[4:7])))
        return out


class ImuReader:
    """An IMU on a serial port, read in its own thread; samples in the camera frame.

    protocol : "bno085-rvc" or "text". R_cam_imu : (3, 3) extrinsic rotation. gyro_bias,
    accel_bias : (3,) camera frame, subtracted. anchor : how the stream's times map to the
    rig's clock: "device" (as sent: a board sharing the camera's clock), "arrival" (the first
    sample at its arrival on ``clock``), "camera" (the stream's start at the camera's first
    frame: :meth:`anchor_at`). The RVC stream's own times are its index / 100 Hz from report 0.
    checksum_burst : this many checksum errors or bad lines
    within one second is a fault (a wrong baud rate, a broken cable).
    """

    def __init__(self, port, protocol: str, R_cam_imu=np.eye(3), gyro_bias=np.zeros(3), accel_bias=np.zeros(3),
                 clock=time.monotonic, name: str = "IMU", checksum_burst: int = 20, anchor: str = "arrival",
                 period_s: float | None = None):
        if anchor not in ("device", "arrival", "camera"):
            raise DriverError(f"IMU anchor {anchor!r} unknown; use device, arrival or camera")
        if protocol not in ("bno085-rvc", "text"):
            raise DriverError(f"IMU protocol {protocol!r} unknown; use bno085-rvc or text")
        self.port = port
        self.protocol = protocol
        self.R = np.asarray(R_cam_imu, float)
        self.gyro_bias = np.asarray(gyro_bias, float)
        self.accel_bias = np.asarray(accel_bias, float)
        self.clock = clock
        self.name = name
        self.checksum_burst = checksum_burst
        self.rvc = RvcParser()
        self.rates = RvcRates()
        self.text = TextParser()
        self._samples: deque = deque(maxlen=20000)
        self._cond = threading.Condition()
        self._error: str | None = None
        self._stop = threading.Event()
        self._bad_times: deque = deque(maxlen=1000)
        self.latest_t = -math.inf
        self.anchor = anchor
        self.period = period_s if period_s is not None else (1.0 / RVC_RATE_HZ if protocol == "bno085-rvc" else 0.005)
        self.offset: float | None = 0.0 if anchor == "device" else None
        self._t_first: float | None = None
        self._thread = threading.Thread(target=self._run, name=f"imu-{protocol}", daemon=True)
        self._thread.start()

    @property
    def noise(self) -> ImuNoise | None:
        """The stream's noise for the SLAM (None: a text board's raw rates, the SLAM's defaults)."""
        return ImuNoise(RVC_GYRO_NOISE, RVC_ACCEL_NOISE) if self.protocol == "bno085-rvc" else None

    @classmethod
    def open(cls, path: str, protocol: str, baud: int = 115200, **kw) -> "ImuReader":
        import serial

        try:
            port = serial.Serial(path, baudrate=baud, timeout=0.05, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as e:
            raise DriverError(f"IMU port {path}: cannot open it ({str(e).splitlines()[0][:160]}); check the cable and "
                              f"rig.toml [imu] port, or set driver = \"none\"") from None
        return cls(port, protocol, name=f"IMU on {path}", **kw)

    @property
    def counters(self) -> dict:
        if self.protocol == "bno085-rvc":
            return {"frames": self.rvc.frames, "checksum_errors": self.rvc.checksum_errors,
                    "skipped_bytes": self.rvc.skipped_bytes, "dropped": self.rvc.dropped}
        return {"lines": self.text.lines, "bad_lines": self.text.bad_lines}

    def _bad(self) -> int:
        return self.rvc.checksum_errors if self.protocol == "bno085-rvc" else self.text.bad_lines

    def _run(self) -> None:
        bad_before = 0
        while not self._stop.is_set():
            try:
                data = self.port.read(max(1, getattr(self.port, "in_waiting", 0) or 1))
            except Exception as e:  # noqa: BLE001 - any port failure ends the stream with a message
                if not self._stop.is_set():
                    self._fail(f"{self.name}: reading failed ({str(e).splitlines()[0][:120] if str(e) else type(e).__name__}); "
                               f"was it unplugged?")
                return
            if not data:
                continue
            now = self.clock()
            rows = []
            if self.protocol == "bno085-rvc":
                for r in self.rvc.feed(data):
                    if self._t_first is None:
                        self._t_first = 0.0           # report 0 is the stream's time zero
                        self._anchor_arrival(now)
                    s = self.rates.push(r)
                    if s is not None:
                        rows.append(s)
            else:
                rows = self.text.feed(data)
                if rows and self._t_first is None:
                    self._t_first = rows[0][0]
                    self._anchor_arrival(now)
            bad = self._bad()
            for _ in range(bad - bad_before):
                self._bad_times.append(time.monotonic())
            bad_before = bad
            recent = sum(1 for x in self._bad_times if x > time.monotonic() - 1.0)
            if recent >= self.checksum_burst:
                self._fail(f"{self.name}: {recent} corrupt frames within a second (checksum errors or bad lines); "
                           f"check the baud rate and the cable")
                return
            if rows:
                with self._cond:
                    for t, w, a in rows:
                        self._samples.append((t, self.R @ w - self.gyro_bias, self.R @ a - self.accel_bias))
                        self.latest_t = t
                    self._cond.notify_all()

    def _anchor_arrival(self, now: float) -> None:
        if self.anchor == "arrival":
            with self._cond:
                self.offset = now - self._t_first
                self._cond.notify_all()

    def anchor_at(self, t_camera_start: float, wait_s: float = 1.0) -> None:
        """Anchor "camera": the stream's start is at the camera's first frame (``t`` s)."""
        if self.anchor != "camera":
            return
        deadline = time.monotonic() + wait_s
        with self._cond:
            while self._t_first is None and self._error is None and time.monotonic() < deadline:
                self._cond.wait(0.01)
            self.offset = t_camera_start - (self._t_first or 0.0)

    def _fail(self, message: str) -> None:
        with self._cond:
            self._error = message
            self._cond.notify_all()

    def take_until(self, t: float, wait_s: float = 0.0) -> ImuSamples:
        """The samples stamped up to ``t`` (removed from the buffer), waiting up to ``wait_s``
        for the stream to reach ``t`` (within one sample period)."""
        deadline = time.monotonic() + wait_s
        period = self.period
        # An RVC sample is stamped at the start of the interval it describes: the one from the
        # last report due by t is stamped up to two periods before t.
        due = t - (2 * period if self.protocol == "bno085-rvc" else period)
        with self._cond:
            while self._error is None and (self.offset is None or self.latest_t + self.offset < due - 1e-9):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            if self._error is not None:
                raise DriverError(self._error)
            rows = []
            off = self.offset
            while off is not None and self._samples and self._samples[0][0] + off <= t + 1e-9:
                t_dev, w, a = self._samples.popleft()
                rows.append((t_dev + off, w, a))
        if not rows:
            return ImuSamples()
        return ImuSamples(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))

    def close(self) -> None:
        self._stop.set()
        try:
            self.port.close()
        except Exception:  # noqa: BLE001
            pass
        self._thread.join(timeout=1.0)
