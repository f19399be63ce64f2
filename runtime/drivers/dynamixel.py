"""ROBOTIS Dynamixel X-series smart servos (XL330, XL430, XM430, ...) on one Protocol 2.0 bus,
through ROBOTIS's dynamixel-sdk (pyserial underneath): for a head rebuilt with smart servos.

The servos' control table (X-series e-manual; all values little-endian)::

    addr  name                   bytes  used as
      10  Drive Mode             1      bit 2 must be 0: a velocity-based profile
      11  Operating Mode         1      3 (position) or 4 (extended position)
      48  Max Position Limit     4      ticks; the calibration must lie inside the servo's limits
      52  Min Position Limit     4
      64  Torque Enable          1
      70  Hardware Error Status  1      bits: input voltage, -, overheating, motor encoder,
                                        electrical shock, overload
      98  Bus Watchdog           1      1..127: stop after this many 20 ms without a packet;
                                        reads -1 once tripped (goals are then read-only until 0
                                        is written)
     108  Profile Acceleration   4      x 214.577 rev/min^2
     112  Profile Velocity       4      x 0.229 rev/min; 0 would mean unlimited
     116  Goal Position          4      ticks, 4096 a turn
     132  Present Position       4      ticks (signed)

At start-up the driver checks each servo's modes and limits, sets its profile velocity and
acceleration to the rig's limits (so even a wrong goal moves no faster), arms the bus watchdog,
and turns the torque on. Goals go out as one Sync Write, positions come back by one Sync Read.
The servos have encoders: the rig observes the joints they report.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from . import DriverError

PROTOCOL = 2.0
ADDR_DRIVE_MODE = 10
ADDR_OPERATING_MODE = 11
ADDR_MAX_POSITION = 48
ADDR_MIN_POSITION = 52
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR = 70
ADDR_BUS_WATCHDOG = 98
ADDR_PROFILE_ACCELERATION = 108
ADDR_PROFILE_VELOCITY = 112
ADDR_GOAL_POSITION = 116
ADDR_PRESENT_POSITION = 132

POSITION_MODES = (3, 4)
DRIVE_MODE_TIME_BASED = 0x04
TICKS_PER_TURN = 4096
VELOCITY_UNIT_RAD_S = 0.229 * 2 * math.pi / 60.0          # one Profile Velocity unit
ACCEL_UNIT_RAD_S2 = 214.577 * 2 * math.pi / 3600.0        # one Profile Acceleration unit
WATCHDOG_UNIT_S = 0.020
MAX_PROFILE_UNITS = 32767

HARDWARE_ERROR_BITS = ("input voltage error", "bit 1", "overheating", "motor encoder error", "electrical shock",
                       "overload")


def velocity_units(rate_rad_s: float) -> int:
    """The Profile Velocity that never exceeds ``rate_rad_s``: rounded down, at least 1 (0 would
    mean unlimited)."""
    if not (math.isfinite(rate_rad_s) and rate_rad_s > 0):
        raise DriverError(f"servo speed limit {rate_rad_s!r} rad/s must be positive and finite")
    return int(min(MAX_PROFILE_UNITS, max(1, math.floor(rate_rad_s / VELOCITY_UNIT_RAD_S))))


def accel_units(accel_rad_s2: float) -> int:
    """The Profile Acceleration that never exceeds ``accel_rad_s2``: rounded down, at least 1."""
    if not (math.isfinite(accel_rad_s2) and accel_rad_s2 > 0):
        raise DriverError(f"servo acceleration limit {accel_rad_s2!r} rad/s^2 must be positive and finite")
    return int(min(MAX_PROFILE_UNITS, max(1, math.floor(accel_rad_s2 / ACCEL_UNIT_RAD_S2))))


def watchdog_units(timeout_s: float) -> int:
    """The Bus Watchdog value for a time-out: 20 ms units, 1..127."""
    if not (math.isfinite(timeout_s) and WATCHDOG_UNIT_S <= timeout_s <= 127 * WATCHDOG_UNIT_S):
        raise DriverError(f"Dynamixel bus watchdog {timeout_s!r} s must lie in 0.02..2.54 s")
    return int(round(timeout_s / WATCHDOG_UNIT_S))


def describe_hardware_errors(bits: int) -> str:
    return ", ".join(n for k, n in enumerate(HARDWARE_ERROR_BITS) if bits >> k & 1) or f"0x{bits:02x}"


@dataclass(frozen=True)
class TickCalibration:
    """ticks = zero_ticks + sign * ticks_per_deg * degrees(q), within min_ticks..max_ticks
    (rig.toml [servo.calibration.<joint>] for a Dynamixel head)."""

    zero_ticks: float
    ticks_per_deg: float
    sign: int
    min_ticks: float
    max_ticks: float

    def __post_init__(self):
        if self.sign not in (1, -1):
            raise DriverError(f"sign = {self.sign!r} must be +1 or -1 (which way a positive angle turns)")
        if not (math.isfinite(self.ticks_per_deg) and self.ticks_per_deg > 0):
            raise DriverError(f"ticks_per_deg = {self.ticks_per_deg!r} must be positive (X-series: 4096 / 360)")
        if not (self.min_ticks < self.zero_ticks < self.max_ticks):
            raise DriverError(f"min_ticks < zero_ticks < max_ticks must hold (got {self.min_ticks}, {self.zero_ticks}, "
                              f"{self.max_ticks})")

    @property
    def ticks_per_rad(self) -> float:
        return self.ticks_per_deg * 180.0 / math.pi

    def to_rad(self, ticks) -> np.ndarray:
        return (np.asarray(ticks, float) - self.zero_ticks) / (self.sign * self.ticks_per_rad)

    def to_ticks(self, q_rad) -> int:
        """The goal for an angle, clipped to min_ticks..max_ticks (the last software guard)."""
        t = self.zero_ticks + self.sign * self.ticks_per_rad * float(q_rad)
        return int(np.clip(round(t), math.ceil(self.min_ticks), math.floor(self.max_ticks)))

    def angle_range(self) -> tuple[float, float]:
        a, b = float(self.to_rad(self.min_ticks)), float(self.to_rad(self.max_ticks))
        return (min(a, b), max(a, b))


def _signed32(v: int) -> int:
    return v - (1 << 32) if v >= 1 << 31 else v


class DynamixelBus:
    """The servos ``ids`` on one port, by the SDK's PortHandler and Protocol 2.0 PacketHandler.
    Every failed exchange raises :class:`DriverError` naming the servo and the SDK's reason."""

    def __init__(self, port_name: str, baud: int, ids):
        try:
            import dynamixel_sdk as sdk
        except ImportError:
            raise DriverError("the Dynamixel driver needs ROBOTIS's SDK: pip install dynamixel-sdk") from None
        self.sdk = sdk
        self.ids = [int(i) for i in ids]
        self.port_name = port_name
        self.port = sdk.PortHandler(port_name)
        self.packet = sdk.PacketHandler(PROTOCOL)
        try:
            opened = self.port.openPort()
        except Exception as e:  # noqa: BLE001 - pyserial's SerialException and OSError alike
            raise DriverError(f"Dynamixel bus {port_name}: cannot open ({e}); check the port in rig.toml") from None
        if not opened or not self.port.setBaudRate(int(baud)):
            raise DriverError(f"Dynamixel bus {port_name}: cannot open at {baud} baud; check the port and servo.baud")
        self._writer = sdk.GroupSyncWrite(self.port, self.packet, ADDR_GOAL_POSITION, 4)
        self._reader = sdk.GroupSyncRead(self.port, self.packet, ADDR_PRESENT_POSITION, 4)
        # Hardware Error Status through Bus Watchdog in one block: every servo's faults in one exchange.
        self._status = sdk.GroupSyncRead(self.port, self.packet, ADDR_HARDWARE_ERROR,
                                         ADDR_BUS_WATCHDOG - ADDR_HARDWARE_ERROR + 1)
        for i in self.ids:
            self._reader.addParam(i)
            self._status.addParam(i)
        self.closed = False

    def _check(self, dxl_id, what, result, error) -> None:
        if result != self.sdk.COMM_SUCCESS:
            raise DriverError(f"Dynamixel {dxl_id} on {self.port_name}: {what} failed "
                              f"({self.packet.getTxRxResult(result)}); check the wiring, baud and servo.ids")
        if error & 0x80:
            raise DriverError(f"Dynamixel {dxl_id}: hardware alert during {what} "
                              f"({self.hardware_error_text(dxl_id)}); fix it, then reboot the servo")
        if error & 0x7F:
            raise DriverError(f"Dynamixel {dxl_id}: {what} refused ({self.packet.getRxPacketError(error)})")

    def hardware_error_text(self, dxl_id) -> str:
        v, result, _ = self.packet.read1ByteTxRx(self.port, dxl_id, ADDR_HARDWARE_ERROR)
        return describe_hardware_errors(v) if result == self.sdk.COMM_SUCCESS else "unreadable"

    def ping(self, dxl_id) -> int:
        model, result, error = self.packet.ping(self.port, dxl_id)
        self._check(dxl_id, "ping", result, error)
        return int(model)

    def read1(self, dxl_id, addr) -> int:
        v, result, error = self.packet.read1ByteTxRx(self.port, dxl_id, addr)
        self._check(dxl_id, f"read of address {addr}", result, error)
        return int(v)

    def read4(self, dxl_id, addr) -> int:
        v, result, error = self.packet.read4ByteTxRx(self.port, dxl_id, addr)
        self._check(dxl_id, f"read of address {addr}", result, error)
        return _signed32(int(v))

    def write1(self, dxl_id, addr, value) -> None:
        result, error = self.packet.write1ByteTxRx(self.port, dxl_id, addr, int(value) & 0xFF)
        self._check(dxl_id, f"write of address {addr}", result, error)

    def write4(self, dxl_id, addr, value) -> None:
        result, error = self.packet.write4ByteTxRx(self.port, dxl_id, addr, int(value) & 0xFFFFFFFF)
        self._check(dxl_id, f"write of address {addr}", result, error)

    def sync_goals(self, ticks) -> None:
        """Every servo's Goal Position in one Sync Write (no answer)."""
        self._writer.clearParam()
        for i, t in zip(self.ids, ticks):
            v = int(t) & 0xFFFFFFFF
            self._writer.addParam(i, [v & 0xFF, (v >> 8) & 0xFF, (v >> 16) & 0xFF, (v >> 24) & 0xFF])
        result = self._writer.txPacket()
        if result != self.sdk.COMM_SUCCESS:
            raise DriverError(f"Dynamixel bus {self.port_name}: goal sync write failed ({self.packet.getTxRxResult(result)})")

    def sync_positions(self) -> list[int]:
        """Every servo's Present Position (ticks) by one Sync Read."""
        result = self._reader.txRxPacket()
        if result != self.sdk.COMM_SUCCESS:
            raise DriverError(f"Dynamixel bus {self.port_name}: position sync read failed "
                              f"({self.packet.getTxRxResult(result)}); check the wiring and servo.ids")
        out = []
        for i in self.ids:
            if not self._reader.isAvailable(i, ADDR_PRESENT_POSITION, 4):
                raise DriverError(f"Dynamixel {i}: no position in the sync read's answer; check servo.ids")
            out.append(_signed32(int(self._reader.getData(i, ADDR_PRESENT_POSITION, 4))))
        return out

    def sync_status(self) -> list[tuple[int, int]]:
        """Every servo's (Hardware Error Status, Bus Watchdog) by one Sync Read."""
        n = ADDR_BUS_WATCHDOG - ADDR_HARDWARE_ERROR + 1
        result = self._status.txRxPacket()
        if result != self.sdk.COMM_SUCCESS:
            raise DriverError(f"Dynamixel bus {self.port_name}: status sync read failed "
                              f"({self.packet.getTxRxResult(result)}); check the wiring and servo.ids")
        out = []
        for i in self.ids:
            if not self._status.isAvailable(i, ADDR_HARDWARE_ERROR, n):
                raise DriverError(f"Dynamixel {i}: no status in the sync read's answer; check servo.ids")
            out.append((int(self._status.getData(i, ADDR_HARDWARE_ERROR, 1)),
                        int(self._status.getData(i, ADDR_BUS_WATCHDOG, 1))))
        return out

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.port.closePort()


class DynamixelBoard:
    """The rig's three servos as the rig's board: angles in, ticks out, limits on the servos.

    cfg : the rig (``channels`` are the servo IDs, ``calibration`` :class:`TickCalibration`\\ s,
    ``speed_limit_rad_s``, ``accel_limit_rad_s2``, ``watchdog_s``)."""

    def __init__(self, cfg, bus: DynamixelBus):
        self.cfg = cfg
        self.bus = bus

    def start(self, speed_rad_s=None) -> None:
        """Check each servo (present, position mode, velocity-based profile, limits covering the
        calibration, no hardware error), set its profile limits and watchdog, torque on."""
        b = self.bus
        speeds = np.broadcast_to(np.asarray(self.cfg.speed_limit_rad_s if speed_rad_s is None else speed_rad_s,
                                            float), (3,))
        for i, cal, sp in zip(b.ids, self.cfg.calibration, speeds):
            b.ping(i)
            mode = b.read1(i, ADDR_OPERATING_MODE)
            if mode not in POSITION_MODES:
                raise DriverError(f"Dynamixel {i}: operating mode {mode}; set position control (3) with "
                                  "Dynamixel Wizard before running the head")
            if b.read1(i, ADDR_DRIVE_MODE) & DRIVE_MODE_TIME_BASED:
                raise DriverError(f"Dynamixel {i}: its profile is time-based (Drive Mode bit 2); set it velocity-based "
                                  "with Dynamixel Wizard, so that the profile velocity limits the speed")
            lo, hi = b.read4(i, ADDR_MIN_POSITION), b.read4(i, ADDR_MAX_POSITION)
            if mode == 3 and (cal.min_ticks < lo or cal.max_ticks > hi):
                raise DriverError(f"Dynamixel {i}: the calibration's {cal.min_ticks:g}..{cal.max_ticks:g} ticks exceed the "
                                  f"servo's position limits {lo}..{hi}; narrow min_ticks/max_ticks in rig.toml")
            hw = b.read1(i, ADDR_HARDWARE_ERROR)
            if hw:
                raise DriverError(f"Dynamixel {i}: hardware error ({describe_hardware_errors(hw)}); fix it and reboot the servo")
            if b.read1(i, ADDR_BUS_WATCHDOG) != 0:
                b.write1(i, ADDR_BUS_WATCHDOG, 0)                  # clears a tripped watchdog
            b.write4(i, ADDR_PROFILE_VELOCITY, velocity_units(float(sp)))
            b.write4(i, ADDR_PROFILE_ACCELERATION, accel_units(self.cfg.accel_limit_rad_s2))
        # Torque on holding where each servo is, then the watchdog (it counts only with torque on).
        here = b.sync_positions()
        for i, t in zip(b.ids, here):
            b.write4(i, ADDR_GOAL_POSITION, t)
            b.write1(i, ADDR_TORQUE_ENABLE, 1)
            b.write1(i, ADDR_BUS_WATCHDOG, watchdog_units(self.cfg.watchdog_s))

    def _set_speed(self, rate_rad_s) -> None:
        rate = np.broadcast_to(np.asarray(rate_rad_s, float), (3,))
        for i, r in zip(self.bus.ids, rate):
            self.bus.write4(i, ADDR_PROFILE_VELOCITY, velocity_units(float(r)))

    def ticks(self, q) -> list[int]:
        return [c.to_ticks(v) for c, v in zip(self.cfg.calibration, np.asarray(q, float))]

    def send(self, q) -> list[int]:
        t = self.ticks(q)
        self.bus.sync_goals(t)
        return t

    def positions(self) -> np.ndarray:
        """(3,) rad: where the servos' encoders say they are."""
        return np.array([float(c.to_rad(t)) for c, t in zip(self.cfg.calibration, self.bus.sync_positions())])

    def move_slowly(self, q_goal, rate_rad_s: float, timeout_s: float = 30.0, on_progress=None) -> np.ndarray:
        """Go to ``q_goal`` with the servos' profile velocity at ``rate_rad_s`` and wait until
        they arrive (within 2 ticks) or the time-out; restores the rig's speed limits."""
        self._set_speed(rate_rad_s)
        target = self.send(q_goal)
        t_end = time.monotonic() + timeout_s
        q = self.positions()
        try:
            while time.monotonic() < t_end:
                ticks = self.bus.sync_positions()
                q = np.array([float(c.to_rad(t)) for c, t in zip(self.cfg.calibration, ticks)])
                if on_progress is not None:
                    on_progress(q)
                if all(abs(p - t) <= 2 for p, t in zip(ticks, target)):
                    break
                self.bus.sync_goals(target)                  # keeps the bus watchdog fed
                time.sleep(0.02)
        finally:
            self._set_speed(self.cfg.speed_limit_rad_s)
        return q

    def check_errors(self) -> None:
        """Raise :class:`DriverError` if a servo reports a hardware error or a tripped watchdog."""
        for i, (hw, watchdog) in zip(self.bus.ids, self.bus.sync_status()):
            if hw:
                raise DriverError(f"Dynamixel {i}: hardware error ({describe_hardware_errors(hw)}); the head stopped")
            if watchdog == 0xFF:
                raise DriverError(f"Dynamixel {i}: its bus watchdog tripped (the host went silent); the servo stopped")

    def close(self) -> None:
        """Close the port; the servos keep their torque and hold, and their watchdog stops them
        if anything still moves."""
        self.bus.close()
