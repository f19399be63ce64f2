"""The safety chain: each layer on its own, and hostile command streams through the whole chain
to the serial bytes (hypothesis), decoded by the simulated board: no pulse leaves a channel's
calibrated range and no channel moves faster than its limit."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics import reference_head
from runtime.drivers.calibration import ServoCalibration
from runtime.drivers.maestro import Maestro, speed_us_per_s
from runtime.drivers.rig import RigConfig, ServoBoard
from runtime.drivers.safety import EStop, SafetyChain, SafetySettings
from runtime.robot import JointCommand
from runtime.twin.hil import VirtualMaestro
from kinematics.camera import default_camera

HEAD = reference_head()
DT = 1 / 30
CAL = (ServoCalibration(1500.0, 10.2, 1, 650.0, 2350.0), ServoCalibration(1480.0, 10.0, -1, 650.0, 2350.0),
       ServoCalibration(1510.0, 10.4, 1, 650.0, 2350.0))


class LoopbackPort:
    """The bytes the driver writes go straight into a simulated board."""

    def __init__(self, board: VirtualMaestro):
        self.board = board
        self.answer = b""
        self.in_waiting = 0
        self.written = bytearray()

    def write(self, data):
        self.written += data
        self.answer += self.board.feed(bytes(data))

    def read(self, n):
        out, self.answer = self.answer[:n], self.answer[n:]
        return out

    def reset_input_buffer(self):
        self.answer = b""

    def close(self):
        pass


def make_board(limit_deg_s=573.0):
    cfg = RigConfig(path=None, head=HEAD, port="loop", channels=(0, 1, 2), calibration=CAL, camera=default_camera(),
                    camera_source=0, speed_limit_rad_s=np.full(3, math.radians(limit_deg_s)))
    vm = VirtualMaestro(channels=6, home_qus=[c.to_qus(0.0) for c in CAL] + [6000] * 3)
    return ServoBoard(cfg, Maestro(LoopbackPort(vm))), vm


def test_each_layer_range_rate_and_motion_limit():
    chain = SafetyChain(HEAD, np.zeros(3), SafetySettings(motion_limit_rad_s=math.radians(30)))
    q = chain.apply(JointCommand([5.0, -5.0, 0.0]), 0.0, DT)       # far out of range, far away
    np.testing.assert_allclose(np.abs(q[:2]), math.radians(30) * DT)
    assert chain.report().range_or_servo_speed == 1 and chain.report().motion_limit == 1
    q = chain.apply(JointCommand([np.nan, 0.0, 0.0]), DT, DT)      # refused: holds
    np.testing.assert_allclose(q, chain.q)
    assert chain.report().refused == 1
    for k in range(400):
        q = chain.apply(JointCommand([5.0, -5.0, 0.0]), k * DT, DT)
    np.testing.assert_allclose(q[:2], [HEAD.upper[0], HEAD.lower[1]])


def t_stale(states, t0=10 * DT):
    return t0 + states.index("hold") * DT


def test_the_watchdog_holds_then_goes_home_slowly():
    s = SafetySettings(pose_timeout_s=0.5, hold_s=1.0, home_rate_rad_s=math.radians(20))
    chain = SafetyChain(HEAD, [0.6, -0.4, 0.2], s)
    t = 0.0
    for _ in range(10):                                  # fresh poses: the command goes through
        q = chain.apply(JointCommand([0.65, -0.4, 0.2], basis_t=t), t, DT)
        t += DT
    assert chain.watchdog.state == "ok" and q[0] > 0.6
    states, qs = [], [q.copy()]
    while t < 4.0:                                       # the pose stops coming at t = 0.3
        q = chain.apply(JointCommand([1.2, 1.2, 1.2], basis_t=0.3), t, DT)
        states.append(chain.watchdog.state)
        qs.append(q)
        t += DT
    qs = np.array(qs)
    hold = np.flatnonzero(np.array(states) == "hold")
    assert len(hold) and (np.array(states) == "home").any()
    assert t_stale(states) == pytest.approx(0.3 + 0.5, abs=DT + 1e-9)       # the stated time-out
    held = qs[hold[0]]                                                        # where it was when it went stale
    np.testing.assert_allclose(qs[hold + 1], held[None].repeat(len(hold), 0))  # held exactly there
    assert len(hold) == pytest.approx(1.0 / DT, abs=1.5)                      # for hold_s
    home = np.flatnonzero(np.array(states) == "home")
    steps = np.abs(qs[home + 1] - qs[home]).max()
    assert steps <= math.radians(20) * DT + 1e-12                             # home at the slow rate
    assert np.abs(qs[-1]).max() < np.abs(held).max()                          # on its way home


def test_the_estop_latches_until_an_explicit_reset(tmp_path):
    latch = tmp_path / "estop.latch"
    chain = SafetyChain(HEAD, np.zeros(3), estop=EStop(latch))
    chain.apply(JointCommand([0.1, 0, 0]), 0.0, DT)
    q_stop = chain.q.copy()
    EStop(latch).trip("pressed")                          # another process (wvr head stop) trips it
    for k in range(30):
        q = chain.apply(JointCommand([1.0, 1.0, 1.0], basis_t=k * DT), k * DT, DT)
        np.testing.assert_allclose(q, q_stop)
    assert chain.estop.tripped and "pressed" in chain.report().estop_reason
    assert EStop(latch).tripped                           # the latch outlives this process
    chain.estop.reset()
    assert not latch.exists()
    q = chain.apply(JointCommand([1.0, 1.0, 1.0]), 2.0, DT)
    assert q[0] > q_stop[0]


hostile = st.one_of(st.floats(-1e6, 1e6, allow_nan=False), st.just(float("nan")), st.just(float("inf")),
                    st.just(-float("inf")), st.floats(-2.0, 2.0))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(hostile, hostile, hostile), min_size=1, max_size=60),
       st.floats(1.0, 60.0), st.booleans(), st.lists(st.floats(0.0, 3.0), min_size=1, max_size=60))
def test_no_pulse_leaves_the_calibrated_range_and_no_channel_moves_too_fast(cmds, limit_deg, stale, basis_ages):
    board, vm = make_board()
    chain = SafetyChain(HEAD, np.zeros(3), SafetySettings(motion_limit_rad_s=math.radians(limit_deg)))
    board.start()
    speed_us = [speed_us_per_s(vm.ch[c].speed) for c in range(3)]
    prev = np.array([c.to_us(0.0) for c in CAL])
    outputs_prev = vm.positions_qus([0, 1, 2]) / 4.0
    for k, c in enumerate(cmds):
        t = k * DT
        basis = t - basis_ages[k % len(basis_ages)] if stale else t
        q = chain.apply(JointCommand(np.array(c, float), basis_t=basis), t, DT)
        board.send(q)
        vm.advance(DT)
        # The targets the board decoded from the bytes, in us:
        target = np.array([vm.ch[ch].target for ch in range(3)]) / 4.0
        lo = np.array([cal.min_us for cal in CAL])
        hi = np.array([cal.max_us for cal in CAL])
        assert np.all(target >= lo) and np.all(target <= hi)
        # No target step faster than the motion limit (plus a quarter-us of rounding).
        us_per_rad = np.array([cal.us_per_rad for cal in CAL])
        assert np.all(np.abs(target - prev) <= us_per_rad * math.radians(limit_deg) * DT + 0.25 + 1e-9)
        prev = target
        # And the board's outputs never move faster than the speed set on it.
        out = vm.positions_qus([0, 1, 2]) / 4.0
        assert np.all(np.abs(out - outputs_prev) <= np.array(speed_us) * DT + 1e-6)
        outputs_prev = out
    assert board.maestro.get_errors() == 0                  # every byte was a valid command
