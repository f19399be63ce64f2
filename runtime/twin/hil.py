"""Hardware in the loop: the twin behind virtual devices on pseudo-terminals, so that the real
drivers (``runtime.drivers``) and ``wvr run --rig`` are exercised without hardware.

* :class:`VirtualMaestro`: a Pololu Maestro speaking the real protocol (compact and Pololu
  forms), whose outputs move at the speed and acceleration limits set on it, with its error
  register (protocol errors, the serial time-out) and its go-home-on-error behaviour.
* :class:`PtyDevice`: a device on a pseudo-terminal (``os.openpty``): bytes written to the
  slave's path reach the device, its answers come back; ``unplug()`` hangs the line up.
* :class:`HilSession`: the twin stepped in lock step with the controller. Each period it
  publishes a frame (a sequence folder whose rgb.txt grows: the rig's camera source) after
  streaming the IMU for the period (BNO085 UART-RVC frames on one pty, and ``t w a`` text lines
  on another), then waits for the controller's targets on the Maestro's pty, and advances the
  physics with the Maestro's ramped outputs driving the twin's joints (one per physics step).
  It writes the rig.toml for ``wvr run --rig``, the clicked target.toml, and, for scoring only,
  the true trajectory (groundtruth.txt).

Lock step (the simulated world waits for the controller, up to ``wait_s`` of wall time) keeps
the simulation faithful on a loaded machine, where rendering alone takes about a frame period.
"""

from __future__ import annotations

import math
import os
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import JOINT_NAMES, save_head
from kinematics.camera import save_camera

from ..drivers.imu import G, encode_rvc
from ..drivers.maestro import (ACCEL_PERIOD_S, GET_ERRORS, GET_POSITION, GO_HOME, POLOLU_START, SET_ACCELERATION,
                               SET_MULTIPLE_TARGETS, SET_SPEED, SET_TARGET, SPEED_PERIOD_S)
from ..sequence import save_target, write_trajectory
from .scene import TIMESTEP

GET_MOVING_STATE = 0x93
_LENGTHS = {SET_TARGET: 3, SET_SPEED: 3, SET_ACCELERATION: 3, GET_POSITION: 1, GET_ERRORS: 0, GO_HOME: 0,
            GET_MOVING_STATE: 0}


@dataclass
class _Channel:
    target: float = 0.0       # quarter-us; 0 = no pulses
    position: float = 0.0
    velocity: float = 0.0     # quarter-us per s
    speed: int = 0
    accel: int = 0
    home: float = 6000.0


class VirtualMaestro:
    """The Maestro's serial protocol and its outputs' motion, in a time the caller advances.

    channels : how many. device : its device number (Pololu protocol). home_qus : per channel,
    where an error sends the outputs (the board's "home" setting). serial_timeout_s : the board's
    serial time-out (None: off), in the caller's time.
    """

    def __init__(self, channels: int = 6, device: int = 12, home_qus=None, serial_timeout_s: float | None = None):
        self.ch = [_Channel() for _ in range(channels)]
        if home_qus is not None:
            for c, h in zip(self.ch, home_qus):
                c.home = c.target = c.position = float(h)
        self.device = device
        self.errors = 0
        self.serial_timeout_s = serial_timeout_s
        self.t = 0.0
        self._last_valid = 0.0
        self._buf = bytearray()
        self._lock = threading.RLock()
        self.targets_received = 0          # Set Target / Set Multiple Targets commands so far
        self.log: list[tuple[float, int, list[int]]] = []   # (t, channel, targets) of every target command
        self.wall_times: list[float] = []    # wall clock (monotonic) of every Set Multiple Targets
        self.commands = 0

    # -- the protocol
    def feed(self, data: bytes) -> bytes:
        """Bytes from the host; returns the answers."""
        out = bytearray()
        with self._lock:
            self._buf += data
            while self._buf:
                b = self._buf[0]
                if b < 0x80:                          # a data byte where a command should be
                    self._error(4)
                    del self._buf[0]
                    continue
                pololu = b == POLOLU_START
                start = 3 if pololu else 1
                if pololu:
                    if len(self._buf) < 3:
                        break
                    if self._buf[1] >= 0x80 or self._buf[2] >= 0x80:
                        self._error(4)
                        del self._buf[0]
                        continue
                    cmd = self._buf[2] | 0x80
                    mine = self._buf[1] == self.device
                else:
                    cmd, mine = b, True
                if cmd == SET_MULTIPLE_TARGETS:
                    if len(self._buf) < start + 1:
                        break
                    n = self._buf[start]
                    need = 2 + 2 * n
                elif cmd in _LENGTHS:
                    need = _LENGTHS[cmd]
                else:
                    self._error(4)
                    del self._buf[:start]
                    continue
                if len(self._buf) < start + need:
                    break
                data_bytes = bytes(self._buf[start:start + need])
                if any(x >= 0x80 for x in data_bytes):   # a command interrupted by another
                    self._error(4)
                    k = next(i for i, x in enumerate(data_bytes) if x >= 0x80)
                    del self._buf[:start + k]
                    continue
                del self._buf[:start + need]
                if mine:
                    out += self._execute(cmd, data_bytes)
        return bytes(out)

    def _error(self, bit: int) -> None:
        self.errors |= 1 << bit
        for c in self.ch:                            # an error sends every output home
            c.target = c.home

    def _execute(self, cmd: int, d: bytes) -> bytes:
        self.commands += 1
        self._last_valid = self.t
        v14 = lambda lo, hi: lo | hi << 7            # noqa: E731
        if cmd == SET_TARGET:
            if d[0] < len(self.ch):
                self.ch[d[0]].target = float(v14(d[1], d[2]))
                self.targets_received += 1
                self.log.append((self.t, d[0], [v14(d[1], d[2])]))
        elif cmd == SET_MULTIPLE_TARGETS:
            n, first = d[0], d[1]
            vals = [v14(d[2 + 2 * i], d[3 + 2 * i]) for i in range(n)]
            for i, v in enumerate(vals):
                if first + i < len(self.ch):
                    self.ch[first + i].target = float(v)
            self.targets_received += 1
            self.log.append((self.t, first, vals))
            self.wall_times.append(time.monotonic())
        elif cmd == SET_SPEED:
            if d[0] < len(self.ch):
                self.ch[d[0]].speed = v14(d[1], d[2])
        elif cmd == SET_ACCELERATION:
            if d[0] < len(self.ch):
                self.ch[d[0]].accel = min(255, v14(d[1], d[2]))
        elif cmd == GET_POSITION:
            p = int(round(self.ch[d[0]].position)) if d[0] < len(self.ch) else 0
            return bytes([p & 0xFF, p >> 8 & 0xFF])
        elif cmd == GET_ERRORS:
            e, self.errors = self.errors, 0
            return bytes([e & 0xFF, e >> 8 & 0xFF])
        elif cmd == GO_HOME:
            for c in self.ch:
                c.target = c.home
        elif cmd == GET_MOVING_STATE:
            return bytes([int(any(abs(c.position - c.target) > 0.5 for c in self.ch if c.target))])
        return b""

    # -- the outputs' motion
    def advance(self, dt: float) -> None:
        """Move every output towards its target for ``dt`` s at its speed and acceleration limits."""
        with self._lock:
            self.t += dt
            if self.serial_timeout_s is not None and self.t - self._last_valid > self.serial_timeout_s \
                    and not self.errors >> 5 & 1:
                self._error(5)
            for c in self.ch:
                if c.target == 0:                    # pulses off: the output holds no position
                    continue
                if c.position == 0 or c.speed == 0 and c.accel == 0:
                    c.position, c.velocity = c.target, 0.0
                    continue
                err = c.target - c.position
                vmax = c.speed * 1.0 / SPEED_PERIOD_S if c.speed else math.inf   # quarter-us/s
                if c.accel:
                    amax = c.accel * 1.0 / (SPEED_PERIOD_S * ACCEL_PERIOD_S)
                    # Brake in time to stop at the target; never beyond the speed limit.
                    v_stop = math.sqrt(2 * amax * abs(err))
                    v_want = math.copysign(min(vmax, v_stop), err)
                    dv = np.clip(v_want - c.velocity, -amax * dt, amax * dt)
                    c.velocity = float(c.velocity + dv)
                else:
                    c.velocity = math.copysign(vmax, err) if err else 0.0
                step = c.velocity * dt
                if abs(step) >= abs(err) or not math.isfinite(step):
                    c.position, c.velocity = c.target, 0.0
                else:
                    c.position += step

    def positions_qus(self, channels) -> np.ndarray:
        with self._lock:
            return np.array([self.ch[c].position for c in channels])


class PtyDevice:
    """A device on a pseudo-terminal: ``path`` is the slave's name (what rig.toml names as the
    port); a thread reads the host's bytes from the master and writes ``handler(bytes)``'s answers
    back. ``write`` sends unsolicited bytes (an IMU's stream); ``unplug`` hangs up."""

    def __init__(self, handler=None, name: str = "device"):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)                      # no echo, no line editing: bytes pass as they are
        tty.setraw(self.master)
        os.set_blocking(self.master, False)        # a stream nobody reads must not stall the world
        self.path = os.ttyname(self.slave)
        self.dropped_bytes = 0
        self.handler = handler
        self.name = name
        self._stop = threading.Event()
        self._wlock = threading.Lock()
        self.unplugged = False
        self._thread = None
        if handler is not None:
            self._thread = threading.Thread(target=self._run, name=f"pty-{name}", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self.master], [], [], 0.05)
                if not r:
                    continue
                data = os.read(self.master, 4096)
            except OSError:
                return
            if not data:
                continue
            answer = self.handler(data)
            if answer:
                self.write(answer)

    def write(self, data: bytes) -> None:
        if self.unplugged:
            return
        with self._wlock:
            while data:
                try:
                    n = os.write(self.master, data)
                except BlockingIOError:
                    self.dropped_bytes += len(data)   # the line's buffer is full: bytes lost, as on a UART
                    return
                except OSError:
                    return
                data = data[n:]

    def unplug(self) -> None:
        """Hang up: the host's next read or write fails, as when a USB cable is pulled."""
        self.unplugged = True
        self._stop.set()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def close(self) -> None:
        if not self.unplugged:
            self.unplug()
        if self._thread is not None:
            self._thread.join(timeout=1.0)


class WallClockMaestro:
    """A VirtualMaestro on a pty whose outputs move in wall-clock time (bring-up commands, tests)."""

    def __init__(self, maestro: VirtualMaestro, tick_s: float = 0.002):
        self.maestro = maestro
        self.pty = PtyDevice(maestro.feed, "maestro")
        self.path = self.pty.path
        self._stop = threading.Event()
        self._tick = tick_s
        self._thread = threading.Thread(target=self._run, name="maestro-clock", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t = time.monotonic()
        while not self._stop.is_set():
            time.sleep(self._tick)
            now = time.monotonic()
            self.maestro.advance(now - t)
            t = now

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.pty.close()


#: The HIL's IMU board is mounted with its x along the optic axis, y to the image's left and z
#: to the image's up: rig.toml's R_cam_imu (its columns: the IMU's axes in the camera frame).
R_CAM_IMU = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

#: The HIL Maestro's calibration (the issue's example numbers, pan and cyclotorsion mirrored to
#: exercise the sign).
HIL_CALIBRATION = {"elevation": (1500.0, 10.2, 1), "pan": (1480.0, 10.0, -1), "cyclotorsion": (1510.0, 10.4, 1)}
HIL_CHANNELS = {"elevation": 0, "pan": 1, "cyclotorsion": 2}


@dataclass
class HilStats:
    frames: int = 0
    waited_s: float = 0.0          # wall time spent waiting for the controller
    stalls: int = 0                # periods the controller did not answer within wait_s
    target_commands: int = 0
    maestro_errors_seen: int = 0
    notes: list = field(default_factory=list)


class HilSession:
    """The twin behind virtual devices; see the module docstring.

    twin : a configured Twin (``twin.configure(scenario, seed, seconds)``). out : the folder
    for rig.toml, camera/, target.toml and groundtruth.txt. imu : "bno085-rvc" or "text" (what
    rig.toml's [imu] uses; both streams run). wait_s : how long the world waits for each period's
    targets. start_target : the Target to write as target.toml (default: a simulated click).
    """

    def __init__(self, twin, out: str | Path, imu: str = "bno085-rvc", wait_s: float = 5.0, start_target=None,
                 linger_s: float = 8.0, click_seed: int = 0, click_error_px: float = 2.5):
        """wait_s : a period's targets not arriving within this (wall time) is a stall: the
        controller has stopped (Ctrl-C, a fault), so the simulated session ends there and the
        board stays on the line for ``linger_s`` with its outputs moving in wall time (the
        host's safe stop: hold, go home slowly)."""
        self.twin = twin
        self.out = Path(out)
        self.imu_protocol = imu
        self.wait_s = wait_s
        self.linger_s = linger_s
        self.start_target = start_target
        self.click_seed = click_seed
        self.click_error_px = float(click_error_px)
        self.stats = HilStats()
        self.cal = {n: HIL_CALIBRATION[n] for n in JOINT_NAMES}
        self.channels = [HIL_CHANNELS[n] for n in JOINT_NAMES]
        self.maestro = VirtualMaestro(channels=6)
        self.maestro_pty = PtyDevice(self._maestro_feed, "maestro")
        self.rvc_pty = PtyDevice(None, "imu-rvc")
        self.text_pty = PtyDevice(None, "imu-text")
        self._targets_event = threading.Event()
        self._rvc_index = 0
        self._truth_t, self._truth_T = [], []

    def _maestro_feed(self, data: bytes) -> bytes:
        n0 = self.maestro.targets_received
        answer = self.maestro.feed(data)
        if self.maestro.targets_received > n0:
            self._targets_event.set()
        return answer

    # -- calibration maps (the twin's joints <-> the board's pulses)
    def _to_qus(self, q) -> np.ndarray:
        return np.array([4.0 * (neu + sign * upd * math.degrees(v)) for (neu, upd, sign), v in zip(self.cal.values(), q)])

    def _to_rad(self, qus) -> np.ndarray:
        return np.array([math.radians((p / 4.0 - neu) / (sign * upd)) for (neu, upd, sign), p in zip(self.cal.values(), qus)])

    # -- files
    def write_rig(self, path: Path) -> None:
        imu = self.imu_protocol
        port = self.rvc_pty.path if imu == "bno085-rvc" else self.text_pty.path
        lines = ['# written by wvr sim hil: the twin behind virtual devices on pseudo-terminals', 'head = "head.toml"', "",
                 "[servo]", 'driver = "maestro"', f'port = "{self.maestro_pty.path}"',
                 "# the virtual board answers from a thread beside the renderer: allow it a loaded machine's pauses",
                 "answer_timeout_ms = 2000.0",
                 "channels = { " + ", ".join(f"{n} = {c}" for n, c in HIL_CHANNELS.items()) + " }", ""]
        for n, (neu, upd, sign) in self.cal.items():
            lines += [f"[servo.calibration.{n}]", f"neutral_us = {neu}", f"us_per_deg = {upd}", f"sign = {sign}",
                      "min_us = 650.0", "max_us = 2350.0", ""]
        lines += ["[camera]", 'source = "camera"', 'camera_toml = "camera.toml"', f"fps = {self.twin.frame_rate}",
                  "timeout_s = 10.0", "",
                  "[imu]", f'driver = "{imu}"', f'port = "{port}"',
                  "R_cam_imu = [" + ", ".join("[" + ", ".join(f"{v:.1f}" for v in r) + "]" for r in R_CAM_IMU) + "]",
                  f'anchor = "{"camera" if imu == "bno085-rvc" else "device"}"',
                  f"rate_hz = {100.0 if imu == 'bno085-rvc' else 1.0 / (self.twin.steps_per_imu * TIMESTEP)}", "",
                  "[safety]", "pose_timeout_s = 1.0", "", "[start]", 'target = "target.toml"', ""]
        path.write_text("\n".join(lines))

    # -- streams
    def _emit_imu(self, rows: np.ndarray) -> None:
        """Rows (k, 7) of the twin's IMU (camera frame): text lines at the twin's rate, and an RVC
        report for each 10 ms (the fused orientation of the IMU board, and its accelerometer)."""
        R_imu_cam = R_CAM_IMU.T
        text = []
        rvc = b""
        for t, *v in np.asarray(rows).reshape(-1, 7):
            w = R_imu_cam @ np.array(v[:3])
            f = R_imu_cam @ np.array(v[3:])
            text.append(f"{t:.6f} " + " ".join(f"{x:.9g}" for x in (*w, *f)))
            k = int(round(t / TIMESTEP))
            if k % 10 == 0:                                  # 100 Hz
                R_ref_imu = self.twin.cam_R[k] @ R_CAM_IMU
                yaw, pitch, roll = Rotation.from_matrix(R_ref_imu).as_euler("ZYX", degrees=True)
                rvc += encode_rvc(self._rvc_index, yaw, pitch, roll, f / G * 1000.0)
                self._rvc_index = (self._rvc_index + 1) % 256
        if text:
            self.text_pty.write(("\n".join(text) + "\n").encode())
        if rvc:
            self.rvc_pty.write(rvc)

    def _publish(self, obs, k: int) -> None:
        name = f"rgb/{k:06d}.png"
        cv2.imwrite(str(self.cam_dir / name), cv2.cvtColor(obs.image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        self._rgb.write(f"{obs.t:.6f} {name}\n")
        self._rgb.flush()
        self.stats.frames += 1

    def run(self, progress: bool = True) -> HilStats:
        """Serve one session: the scenario's duration, then ``linger_s`` of the board alone."""
        from kinematics.progress import progress_bar

        twin = self.twin
        self.out.mkdir(parents=True, exist_ok=True)
        self.cam_dir = self.out / "camera"
        (self.cam_dir / "rgb").mkdir(parents=True, exist_ok=True)
        obs = twin.reset()
        n_frames = int(round(twin.seconds * twin.frame_rate))
        save_head(twin.head, self.out / "head.toml")
        save_camera(twin.camera, self.out / "camera.toml")
        save_camera(twin.camera, self.cam_dir / "camera.toml")
        target = self.start_target
        if target is None:
            from .operator import clicked_target

            target = clicked_target(twin, self.click_error_px, np.random.default_rng(self.click_seed))
        save_target(target, self.out / "target.toml")
        for c, p in zip(self.channels, self._to_qus(twin.filter.q)):
            ch = self.maestro.ch[c]
            ch.target = ch.position = ch.home = float(p)
        self.write_rig(self.out / "rig.toml")
        self._rgb = open(self.cam_dir / "rgb.txt", "w", encoding="utf-8")
        self._rgb.write("# timestamp filename  (wvr sim hil: the rendered frames as they happen)\n")
        self.ready()
        self._emit_imu(obs.imu.rows())
        self._truth(twin)
        self._publish(obs, 0)
        bar = progress_bar(total=n_frames, desc="hil", unit="frame", disable=not progress)
        bar.update(1)
        try:
            for k in range(1, n_frames):
                t0 = time.monotonic()
                # The first command waits for the controller to start (imports, compilation).
                if not self._targets_event.wait(self.wait_s if k > 1 else max(self.wait_s, 120.0)):
                    self.stats.stalls += 1
                    self.stats.notes.append(f"the controller stopped answering at t = {obs.t:.3f} s; session ended")
                    break
                self.stats.waited_s += time.monotonic() - t0
                self._targets_event.clear()
                profile = np.empty((twin.steps_per_frame, 3))
                for i in range(twin.steps_per_frame):
                    self.maestro.advance(TIMESTEP)
                    profile[i] = self._to_rad(self.maestro.positions_qus(self.channels))
                obs = twin.step(None, profile=profile)
                self._emit_imu(obs.imu.rows())
                self._truth(twin)
                self._publish(obs, k)
                bar.update(1)
        finally:
            bar.close()
            self._rgb.write("# end\n")
            self._rgb.close()
            write_trajectory(self.out / "groundtruth.txt", np.array(self._truth_t), np.array(self._truth_T),
                             header="true camera-to-world poses of the HIL run (scoring only)")
        self.stats.target_commands = self.maestro.targets_received
        # The board stays on the line a little longer, in wall time, for the host's safe stop.
        t_end = time.monotonic() + self.linger_s
        t = time.monotonic()
        while time.monotonic() < t_end:
            time.sleep(0.005)
            now = time.monotonic()
            self.maestro.advance(now - t)
            t = now
        return self.stats

    def ready(self) -> None:
        """Called once the files are written and the devices are up (a hook for tests and the CLI)."""

    def _truth(self, twin) -> None:
        gt = twin.ground_truth
        self._truth_t.append(gt.t)
        self._truth_T.append(gt.T_world_cam)

    def close(self) -> None:
        for p in (self.maestro_pty, self.rvc_pty, self.text_pty):
            p.close()
