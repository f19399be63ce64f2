"""The Pololu Maestro servo controller over a serial port (pyserial), both of its protocols.

Commands (Pololu's "Maestro Servo Controller User's Guide", section 5.e)::

    Set Target            0x84 ch lo hi         target in quarter-microseconds (0 = pulses off)
    Set Multiple Targets  0x9F n first (lo hi)*n
    Set Speed             0x87 ch lo hi         units of (0.25 us)/(10 ms); 0 = unlimited
    Set Acceleration      0x89 ch lo hi         units of (0.25 us)/(10 ms)/(80 ms); 0 = unlimited
    Get Position          0x90 ch  -> lo8 hi8   the pulse being sent now (after speed and acceleration)
    Get Errors            0xA1     -> lo8 hi8   the error register (reading clears it)
    Go Home               0xA2

Values go as two 7-bit data bytes (low 7 bits, then bits 7-13). The compact protocol sends the
command byte as is; the Pololu protocol (for a daisy chain) sends ``0xAA, device number,
command & 0x7F, data...``. Answers come as two plain bytes, low first.

The board's own serial time-out (set with Pololu's Maestro Control Center, not over serial)
sends every servo home when the host stops talking: see the README's rig section.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from . import DriverError

SET_TARGET = 0x84
SET_MULTIPLE_TARGETS = 0x9F
SET_SPEED = 0x87
SET_ACCELERATION = 0x89
GET_POSITION = 0x90
GET_ERRORS = 0xA1
GO_HOME = 0xA2
POLOLU_START = 0xAA
DEFAULT_DEVICE = 12

#: The error register's bits (user's guide, section 4.e).
ERROR_BITS = ("serial signal error", "serial overrun error", "serial RX buffer full", "serial CRC error",
              "serial protocol error", "serial timeout", "script stack error", "script call stack error",
              "script program counter error")

#: Seconds per speed unit's time base, and the acceleration's second time base.
SPEED_PERIOD_S = 0.010
ACCEL_PERIOD_S = 0.080
MAX_SPEED_UNITS = 0x3FFF
MAX_ACCEL_UNITS = 255


def _data14(v: int) -> list[int]:
    v = int(v)
    if not 0 <= v <= 0x3FFF:
        raise DriverError(f"Maestro value {v} does not fit in 14 bits (0..16383)")
    return [v & 0x7F, (v >> 7) & 0x7F]


def packet(command: int, data: list[int], device: int | None = None) -> bytes:
    """One command's bytes: compact protocol when ``device`` is None, else the Pololu protocol."""
    if any(not 0 <= b <= 0x7F for b in data):
        raise DriverError(f"Maestro data bytes must be 7-bit, got {data}")
    if device is None:
        return bytes([command, *data])
    if not 0 <= device <= 0x7F:
        raise DriverError(f"Maestro device number {device} must be 0..127 (the default is {DEFAULT_DEVICE})")
    return bytes([POLOLU_START, device, command & 0x7F, *data])


def set_target_bytes(channel: int, target_qus: int, device: int | None = None) -> bytes:
    return packet(SET_TARGET, [channel, *_data14(target_qus)], device)


def set_multiple_targets_bytes(first: int, targets_qus, device: int | None = None) -> bytes:
    targets = [int(t) for t in targets_qus]
    data = [len(targets), first]
    for t in targets:
        data += _data14(t)
    return packet(SET_MULTIPLE_TARGETS, data, device)


def set_speed_bytes(channel: int, speed: int, device: int | None = None) -> bytes:
    return packet(SET_SPEED, [channel, *_data14(speed)], device)


def set_acceleration_bytes(channel: int, accel: int, device: int | None = None) -> bytes:
    return packet(SET_ACCELERATION, [channel, *_data14(accel)], device)


def speed_units(us_per_s: float) -> int:
    """The Maestro speed value that never exceeds ``us_per_s`` (pulse width change, us/s): units of
    0.25 us per 10 ms, rounded down, at least 1 (0 would mean unlimited)."""
    if not (math.isfinite(us_per_s) and us_per_s > 0):
        raise DriverError(f"servo speed limit {us_per_s!r} us/s must be positive and finite")
    return int(min(MAX_SPEED_UNITS, max(1, math.floor(us_per_s * SPEED_PERIOD_S / 0.25))))


def accel_units(us_per_s2: float) -> int:
    """The Maestro acceleration value that never exceeds ``us_per_s2``: units of 0.25 us per 10 ms
    per 80 ms, rounded down, 1..255 (0 would mean unlimited)."""
    if not (math.isfinite(us_per_s2) and us_per_s2 > 0):
        raise DriverError(f"servo acceleration limit {us_per_s2!r} us/s^2 must be positive and finite")
    return int(min(MAX_ACCEL_UNITS, max(1, math.floor(us_per_s2 * SPEED_PERIOD_S * ACCEL_PERIOD_S / 0.25))))


def speed_us_per_s(units: int) -> float:
    return units * 0.25 / SPEED_PERIOD_S


def accel_us_per_s2(units: int) -> float:
    return units * 0.25 / (SPEED_PERIOD_S * ACCEL_PERIOD_S)


def describe_errors(bits: int) -> str:
    names = [n for k, n in enumerate(ERROR_BITS) if bits >> k & 1]
    unknown = bits >> len(ERROR_BITS)
    if unknown:
        names.append(f"unknown bits 0x{bits & ~((1 << len(ERROR_BITS)) - 1):04x}")
    return ", ".join(names) or "none"


@dataclass
class MaestroStats:
    commands: int = 0
    queries: int = 0
    flushed_bytes: int = 0     # stray bytes found waiting before a query (garbage on the line)


class Maestro:
    """A Maestro on an open serial port (a ``serial.Serial`` or anything with read, write,
    reset_input_buffer and in_waiting).

    device : None for the compact protocol, or the board's device number for the Pololu
    protocol. answer_timeout_s : how long a query waits for its two bytes.
    """

    def __init__(self, port, device: int | None = None, answer_timeout_s: float = 0.2, name: str = "Maestro"):
        self.port = port
        self.device = device
        self.answer_timeout_s = float(answer_timeout_s)
        self.name = name
        self.stats = MaestroStats()

    @classmethod
    def open(cls, path: str, baud: int = 115200, device: int | None = None, answer_timeout_s: float = 0.2) -> "Maestro":
        """Open the board's serial port; a missing or busy port is a one-line DriverError."""
        import serial

        try:
            port = serial.Serial(path, baudrate=baud, timeout=answer_timeout_s, write_timeout=1.0, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as e:
            raise DriverError(f"servo port {path}: cannot open it ({_short(e)}); check the cable, the port name "
                              f"in rig.toml [servo] port, and that no other program (e.g. Maestro Control Center) "
                              f"holds it") from None
        return cls(port, device, answer_timeout_s, name=f"Maestro on {path}")

    def close(self) -> None:
        try:
            self.port.close()
        except Exception:  # noqa: BLE001 - closing a vanished port must not mask the fault being reported
            pass

    # -- commands
    def _send(self, data: bytes) -> None:
        try:
            self.port.write(data)
            flush = getattr(self.port, "flush", None)
            if flush is not None:
                flush()
        except Exception as e:  # noqa: BLE001 - pyserial raises SerialException, OSError or its timeouts
            raise DriverError(f"{self.name}: writing failed ({_short(e)}); was the board unplugged? "
                              f"Check the USB cable and restart") from None
        self.stats.commands += 1

    def set_target(self, channel: int, target_qus: int) -> None:
        self._send(set_target_bytes(channel, target_qus, self.device))

    def set_targets(self, first: int, targets_qus) -> None:
        self._send(set_multiple_targets_bytes(first, targets_qus, self.device))

    def set_speed(self, channel: int, speed: int) -> None:
        self._send(set_speed_bytes(channel, speed, self.device))

    def set_acceleration(self, channel: int, accel: int) -> None:
        self._send(set_acceleration_bytes(channel, accel, self.device))

    def go_home(self) -> None:
        self._send(packet(GO_HOME, [], self.device))

    # -- queries
    def _query(self, command: int, data: list[int]) -> int:
        try:
            stray = self.port.in_waiting
            if stray:
                self.port.reset_input_buffer()       # garbage on the line must not shift the answer
                self.stats.flushed_bytes += stray
        except Exception as e:  # noqa: BLE001
            raise DriverError(f"{self.name}: the port failed ({_short(e)}); was the board unplugged?") from None
        self._send(packet(command, data, self.device))
        self.stats.queries += 1
        got = b""
        deadline = time.monotonic() + self.answer_timeout_s
        while len(got) < 2:
            try:
                chunk = self.port.read(2 - len(got))
            except Exception as e:  # noqa: BLE001
                raise DriverError(f"{self.name}: reading failed ({_short(e)}); was the board unplugged?") from None
            got += chunk
            if len(got) < 2 and time.monotonic() > deadline:
                raise DriverError(f"{self.name}: no answer within {1000 * self.answer_timeout_s:.0f} ms; check that the "
                                  f"board is powered, its serial mode is 'USB Dual Port' or 'USB Chained', and the "
                                  f"protocol (device number) in rig.toml")
        return got[0] | got[1] << 8

    def get_position(self, channel: int) -> int:
        """The pulse being sent on ``channel`` now, quarter-microseconds."""
        return self._query(GET_POSITION, [channel])

    def get_errors(self) -> int:
        """The error register (reading it clears it on the board)."""
        bits = self._query(GET_ERRORS, [])
        if bits >> 15:
            raise DriverError(f"{self.name}: garbled answer to Get Errors (0x{bits:04x}); check the baud rate")
        return bits

    def check_errors(self) -> None:
        bits = self.get_errors()
        if bits:
            raise DriverError(f"{self.name} reports errors: {describe_errors(bits)} (0x{bits:04x}); the board has "
                              f"sent the servos home; fix the cause, then start again")


def _short(e: Exception) -> str:
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return text[:160]
