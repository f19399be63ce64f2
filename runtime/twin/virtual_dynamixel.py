"""A virtual bus of Dynamixel X-series servos speaking Protocol 2.0 (instruction and status
packets with byte stuffing and CRC-16, as ROBOTIS's e-manual gives them), for testing the
Dynamixel driver without hardware: put it behind a :class:`runtime.twin.hil.PtyDevice`.

Each servo has the control table's addresses the driver uses (runtime/drivers/dynamixel.py).
Its present position moves towards the goal no faster than its Profile Velocity and
Acceleration (0 = unlimited), only with torque on; its Bus Watchdog stops it (goal := present,
watchdog := -1, goals read-only) after that many 20 ms without a packet addressed to it.
Supported instructions: Ping, Read, Write, Sync Read, Sync Write.
"""

from __future__ import annotations

import math
import threading
import time
from contextlib import contextmanager

from ..drivers.dynamixel import (ACCEL_UNIT_RAD_S2, ADDR_BUS_WATCHDOG, ADDR_GOAL_POSITION, ADDR_MAX_POSITION,
                                 ADDR_MIN_POSITION, ADDR_OPERATING_MODE, ADDR_PRESENT_POSITION,
                                 ADDR_PROFILE_ACCELERATION, ADDR_PROFILE_VELOCITY, ADDR_TORQUE_ENABLE, TICKS_PER_TURN,
                                 VELOCITY_UNIT_RAD_S, WATCHDOG_UNIT_S)

PING, READ, WRITE, STATUS, SYNC_READ, SYNC_WRITE = 0x01, 0x02, 0x03, 0x55, 0x82, 0x83
ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_ACCESS = 0x02, 0x03, 0x04, 0x07
MODEL_XL430 = 1060
TABLE_SIZE = 147
TICKS_PER_RAD = TICKS_PER_TURN / (2 * math.pi)


#: How long a host should wait for this bus's answer, s. Real servos answer within a millisecond
#: and ROBOTIS's SDK waits 2 x its 16 ms latency timer + 2 ms; the virtual bus answers from a
#: Python thread behind a pty, which a loaded 2-core machine can hold off for longer than that.
ANSWER_DEADLINE_S = 2.0


@contextmanager
def patient_host(deadline_s: float = ANSWER_DEADLINE_S):
    """Within the block, ROBOTIS's SDK waits about ``deadline_s`` for each status packet (its
    packet timeout is 2 x LATENCY_TIMER + 2 ms + the bytes' time): the virtual bus's answers
    then hold on a loaded machine. Restores the SDK's own timer after."""
    import dynamixel_sdk.port_handler as ph

    old = ph.LATENCY_TIMER
    ph.LATENCY_TIMER = (1000.0 * deadline_s - 2.0) / 2.0
    try:
        yield
    finally:
        ph.LATENCY_TIMER = old


def crc16(data) -> int:
    """Protocol 2.0's CRC-16 (polynomial 0x8005, as the e-manual's table)."""
    crc = 0
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Byte stuffing of a packet's instruction and parameters: FF FF FD -> FF FF FD FD."""
    out = bytearray()
    for b in body:
        out.append(b)
        if out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if out[-3:] == b"\xff\xff\xfd" and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1                                  # drop the stuffed FD
        i += 1
    return bytes(out)


def packet(dxl_id: int, instruction: int, params: bytes) -> bytes:
    body = stuff(bytes([instruction]) + bytes(params))
    n = len(body) + 2
    head = bytes([0xFF, 0xFF, 0xFD, 0x00, dxl_id, n & 0xFF, n >> 8])
    crc = crc16(head + body)
    return head + body + bytes([crc & 0xFF, crc >> 8])


class VirtualServo:
    def __init__(self, dxl_id: int, position: int = 2048, lo: int = 0, hi: int = 4095, mode: int = 3):
        self.id = dxl_id
        self.table = bytearray(TABLE_SIZE)
        self.set(ADDR_OPERATING_MODE, 1, mode)
        self.set(ADDR_MIN_POSITION, 4, lo)
        self.set(ADDR_MAX_POSITION, 4, hi)
        self.set(ADDR_PRESENT_POSITION, 4, position)
        self.set(ADDR_GOAL_POSITION, 4, position)
        self.position = float(position)
        self.velocity = 0.0                         # ticks/s
        self.last_packet = time.monotonic()
        self.max_speed_seen = 0.0                   # ticks/s, over every advance

    def get(self, addr: int, n: int) -> int:
        v = int.from_bytes(self.table[addr:addr + n], "little")
        return v - (1 << 32) if n == 4 and v >= 1 << 31 else v

    def set(self, addr: int, n: int, value: int) -> None:
        self.table[addr:addr + n] = (int(value) & ((1 << 8 * n) - 1)).to_bytes(n, "little")

    def write(self, addr: int, data: bytes) -> int:
        """A Write's effect; the status error (0 if accepted)."""
        if addr < 0 or addr + len(data) > TABLE_SIZE:
            return ERR_DATA_RANGE
        watchdog_tripped = self.table[ADDR_BUS_WATCHDOG] == 0xFF
        touches_goal = addr < ADDR_GOAL_POSITION + 4 and addr + len(data) > ADDR_GOAL_POSITION
        if watchdog_tripped and touches_goal:
            return ERR_ACCESS                       # goals are read-only until the watchdog is cleared
        if addr <= ADDR_BUS_WATCHDOG < addr + len(data) and data[ADDR_BUS_WATCHDOG - addr] not in range(0, 128):
            return ERR_DATA_RANGE
        if touches_goal:
            goal = int.from_bytes(bytes(data[ADDR_GOAL_POSITION - addr:ADDR_GOAL_POSITION - addr + 4]), "little",
                                  signed=True) if addr == ADDR_GOAL_POSITION and len(data) >= 4 else None
            if goal is not None and not self.get(ADDR_MIN_POSITION, 4) <= goal <= self.get(ADDR_MAX_POSITION, 4):
                return ERR_DATA_RANGE               # a position-mode goal outside the limits is refused
        self.table[addr:addr + len(data)] = data
        return 0

    def advance(self, dt: float, now: float) -> None:
        wd = self.table[ADDR_BUS_WATCHDOG]
        torque = self.table[ADDR_TORQUE_ENABLE] == 1
        if torque and 0 < wd < 128 and now - self.last_packet > wd * WATCHDOG_UNIT_S:
            self.set(ADDR_GOAL_POSITION, 4, int(round(self.position)))
            self.table[ADDR_BUS_WATCHDOG] = 0xFF
            self.velocity = 0.0
        if torque and dt > 0:
            goal = self.get(ADDR_GOAL_POSITION, 4)
            pv, pa = self.get(ADDR_PROFILE_VELOCITY, 4), self.get(ADDR_PROFILE_ACCELERATION, 4)
            vmax = pv * VELOCITY_UNIT_RAD_S * TICKS_PER_RAD if pv > 0 else math.inf
            amax = pa * ACCEL_UNIT_RAD_S2 * TICKS_PER_RAD if pa > 0 else math.inf
            err = goal - self.position
            v_stop = math.sqrt(2 * amax * abs(err)) if math.isfinite(amax) else math.inf
            v_want = math.copysign(min(vmax, v_stop), err) if err else 0.0
            dv = v_want - self.velocity
            if math.isfinite(amax):
                dv = max(-amax * dt, min(amax * dt, dv))
            self.velocity += dv
            step = self.velocity * dt
            if abs(step) >= abs(err) or not math.isfinite(step):
                self.position, self.velocity = float(goal), 0.0
            else:
                self.position += step
                self.max_speed_seen = max(self.max_speed_seen, abs(self.velocity))
        self.set(ADDR_PRESENT_POSITION, 4, int(round(self.position)))


class VirtualDynamixelBus:
    """Servos ``ids`` on one bus; :meth:`feed` takes the host's bytes and returns the answers.
    A thread advances the servos in real time (``run=True``) or the caller does (:meth:`advance`)."""

    def __init__(self, ids=(1, 2, 3), positions=None, limits=(0, 4095), run: bool = True):
        positions = positions or [2048] * len(ids)
        self.servos = {i: VirtualServo(i, p, *limits) for i, p in zip(ids, positions)}
        self.buffer = bytearray()
        self.crc_errors = 0
        self.packets = 0
        self.goal_writes: list[dict[int, int]] = []   # every goal the host set, per packet
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._t = time.monotonic()
        self._thread = None
        if run:
            self._thread = threading.Thread(target=self._run, name="virtual-dynamixel", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.002):
            self.advance()

    def advance(self, dt: float | None = None) -> None:
        with self._lock:
            now = time.monotonic()
            dt = now - self._t if dt is None else dt
            self._t = now
            for s in self.servos.values():
                s.advance(dt, now)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)

    def feed(self, data: bytes) -> bytes:
        with self._lock:
            self.buffer += data
            out = bytearray()
            while True:
                k = self.buffer.find(b"\xff\xff\xfd\x00")
                if k < 0:
                    del self.buffer[:max(0, len(self.buffer) - 3)]
                    break
                del self.buffer[:k]
                if len(self.buffer) < 7:
                    break
                n = self.buffer[5] | self.buffer[6] << 8
                if len(self.buffer) < 7 + n:
                    break
                raw = bytes(self.buffer[:7 + n])
                del self.buffer[:7 + n]
                if crc16(raw[:-2]) != (raw[-2] | raw[-1] << 8):
                    self.crc_errors += 1
                    continue
                self.packets += 1
                body = unstuff(raw[7:-2])
                out += self._handle(raw[4], body[0], body[1:])
            return bytes(out)

    def _status(self, dxl_id: int, error: int, params: bytes = b"") -> bytes:
        return packet(dxl_id, STATUS, bytes([error]) + bytes(params))

    def _handle(self, dxl_id: int, inst: int, p: bytes) -> bytes:
        now = time.monotonic()
        if dxl_id == 0xFE:
            for s in self.servos.values():
                s.last_packet = now
        elif dxl_id in self.servos:
            self.servos[dxl_id].last_packet = now
        else:
            return b""                               # nobody answers an absent ID
        if inst == SYNC_WRITE:
            addr, n = p[0] | p[1] << 8, p[2] | p[3] << 8
            goals = {}
            for k in range(4, len(p), n + 1):
                i, data = p[k], p[k + 1:k + 1 + n]
                if i in self.servos and len(data) == n and self.servos[i].write(addr, data) == 0 \
                        and addr == ADDR_GOAL_POSITION and n == 4:
                    goals[i] = int.from_bytes(data, "little", signed=True)
            if goals:
                self.goal_writes.append(goals)
            return b""
        if inst == SYNC_READ:
            addr, n = p[0] | p[1] << 8, p[2] | p[3] << 8
            return b"".join(self._status(i, 0, self.servos[i].table[addr:addr + n]) for i in p[4:] if i in self.servos)
        if dxl_id == 0xFE:
            return b""
        s = self.servos[dxl_id]
        if inst == PING:
            return self._status(dxl_id, 0, bytes([MODEL_XL430 & 0xFF, MODEL_XL430 >> 8, 52]))
        if inst == READ:
            addr, n = p[0] | p[1] << 8, p[2] | p[3] << 8
            if addr + n > TABLE_SIZE:
                return self._status(dxl_id, ERR_DATA_RANGE)
            return self._status(dxl_id, 0, s.table[addr:addr + n])
        if inst == WRITE:
            addr = p[0] | p[1] << 8
            err = s.write(addr, p[2:])
            if err == 0 and addr == ADDR_GOAL_POSITION and len(p) >= 6:
                self.goal_writes.append({dxl_id: int.from_bytes(p[2:6], "little", signed=True)})
            return self._status(dxl_id, err)
        return self._status(dxl_id, ERR_INSTRUCTION)
