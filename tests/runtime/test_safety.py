"""The safety chain: each layer on its own, the chain around any robot (SafeRobot) as it is
composed for the twin and the rig, and hostile command streams through the whole chain to the
serial bytes (hypothesis), decoded by the simulated board: no pulse leaves a channel's
calibrated range and no channel moves faster than its limit."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics import ServoCommandError, reference_head
from runtime.drivers.calibration import ServoCalibration
from runtime.drivers.maestro import Maestro, speed_us_per_s
from runtime.drivers.rig import RigConfig, ServoBoard
from runtime.robot import MOTION_LIMIT_RAD_S, JointCommand, Observation, RobotInfo
from runtime.safety import EStop, EStopLatched, JointLimiter, SafeRobot, SafetyChain, SafetySettings
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


def test_the_limiter_passes_a_command_inside_its_limits_to_the_bit_and_clamps_the_rest():
    lim = JointLimiter(HEAD.lower, HEAD.upper, MOTION_LIMIT_RAD_S, [0.1, -0.2, 0.3])
    rng = np.random.default_rng(0)
    q = lim.q.copy()
    for _ in range(200):
        # A controller's own rate limit: q + s with |s| <= the step, as the gaze controller makes it.
        s = rng.uniform(-1, 1, 3) * MOTION_LIMIT_RAD_S * DT
        s[rng.integers(3)] = np.sign(s[0]) * MOTION_LIMIT_RAD_S * DT       # one joint at the limit
        target = np.clip(q + s, HEAD.lower, HEAD.upper)
        out = lim.step(target, DT)
        np.testing.assert_array_equal(out, target)
        q = out
    assert lim.clamped_speed == 0 and lim.clamped_position == 0
    out = lim.step(q + [0.3, -0.3, 0.001], DT)                              # too fast on two joints
    np.testing.assert_allclose(out - q, [MOTION_LIMIT_RAD_S * DT, -MOTION_LIMIT_RAD_S * DT, 0.001], atol=1e-15)
    assert lim.clamped_speed == 1
    lim.reset(HEAD.upper - 1e-3)
    out = lim.step(HEAD.upper + 1.0, DT)                                     # beyond the range
    np.testing.assert_array_equal(out, HEAD.upper)
    assert lim.clamped_position == 1
    with pytest.raises(ServoCommandError):
        lim.step([np.nan, 0, 0], DT)


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


# ------------------------------------------------------------------ the chain around any robot
class LoggingRobot:
    """A robot whose joints go exactly where they are sent: it keeps every command it receives."""

    def __init__(self, q0=(0.0, 0.0, 0.0)):
        self.q0 = np.asarray(q0, float)
        self.sent: list[np.ndarray] = []
        self.closed = False

    @property
    def info(self) -> RobotInfo:
        return RobotInfo(head=HEAD, camera=default_camera(), frame_rate=1 / DT, speed_limit=HEAD.max_speed)

    def _obs(self, t, q):
        return Observation(t=t, image=np.zeros((2, 2, 3), np.uint8), imu=None, q=np.asarray(q, float))

    def reset(self):
        self.t = 0.0
        return self._obs(0.0, self.q0)

    def step(self, command):
        self.sent.append(command.q.copy())
        self.t += DT
        return self._obs(self.t, command.q)

    def close(self):
        self.closed = True


def check_safe_robot(robot: SafeRobot, sent, limit: float):
    """Through any SafeRobot: an over-speed command is clamped to the motion limit, one inside
    it passes to the bit, a stale basis is held, and a stop latches until reset (reset refused
    meanwhile). ``sent()`` : the commands the wrapped robot has received; ``limit`` rad/s."""
    obs = robot.reset()
    q0 = np.asarray(obs.q, float)
    n = len(sent())
    obs = robot.step(JointCommand(q0 + [1.0, -1.0, 0.5], basis_t=obs.t))     # far too fast
    q1 = sent()[n]
    np.testing.assert_allclose(np.abs(q1 - q0), limit * robot.dt, rtol=1e-12)
    inside = q1 + np.array([0.5, -0.25, 0.1]) * limit * robot.dt
    obs = robot.step(JointCommand(inside, basis_t=obs.t))
    np.testing.assert_array_equal(sent()[n + 1], inside)                    # unchanged, to the bit
    assert robot.report().motion_limit == 1
    # The pose stops coming: after the time-out the head holds, whatever is asked.
    basis = obs.t
    while obs.t - basis <= robot.chain.settings.pose_timeout_s + robot.dt:
        obs = robot.step(JointCommand(inside + 0.2, basis_t=basis))
    held = sent()[-1].copy()
    obs = robot.step(JointCommand(inside + 0.2, basis_t=basis))
    np.testing.assert_array_equal(sent()[-1], held)
    assert robot.chain.watchdog.state == "hold" and robot.report().watchdog_periods >= 1
    # A latched stop: held, however fresh the command, until an explicit reset.
    robot.estop.trip("test stop")
    for _ in range(5):
        obs = robot.step(JointCommand(held - 0.3, basis_t=obs.t))
        np.testing.assert_array_equal(sent()[-1], held)
    assert robot.report().estop_periods == 5
    with pytest.raises(EStopLatched, match="test stop"):
        robot.reset()
    robot.estop.reset()
    obs = robot.step(JointCommand(held - 0.3, basis_t=obs.t))
    assert np.all(sent()[-1] < held)


def test_the_safe_robot_limits_watches_and_latches_any_robot():
    inner = LoggingRobot([0.2, -0.1, 0.05])
    robot = SafeRobot(inner, SafetySettings())
    check_safe_robot(robot, lambda: inner.sent, MOTION_LIMIT_RAD_S)
    robot.close()
    assert inner.closed


def test_the_twin_assembled_for_a_run_is_behind_the_same_chain(monkeypatch):
    """wvr.assemble's twin (sim run, the station): an over-speed command clamped, a stale pose
    held, a stop latched, on the commands the twin's step received; and its physics held too."""
    from runtime.twin.twin import Twin
    from wvr.assemble import make_twin, safe_twin

    received = []
    step = Twin.step

    def recorded(self, command, profile=None):
        received.append(np.asarray(command.q, float).copy())
        return step(self, command, profile)

    monkeypatch.setattr(Twin, "step", recorded)
    twin = make_twin(ideal_camera=True)
    try:
        twin.configure("workbench-static", seed=0, seconds=4.0)
        robot = safe_twin(twin)
        assert robot.chain.settings.motion_limit_rad_s == MOTION_LIMIT_RAD_S
        check_safe_robot(robot, lambda: received, MOTION_LIMIT_RAD_S)
        robot.estop.trip("physics check")
        commanded = twin.ground_truth.command.copy()
        for _ in range(3):
            robot.step(JointCommand(commanded + 0.3, basis_t=twin.t))
            np.testing.assert_array_equal(twin.ground_truth.command, commanded)   # the servos' input held
    finally:
        twin.close()


def test_the_rig_assembled_for_a_run_is_behind_the_same_chain(tmp_path, monkeypatch):
    """wvr.assemble.make_rig: the rig (here a stand-in for its devices) behind the same chain,
    with rig.toml's [safety] limits and its latch file."""
    import runtime.drivers.rig as rig_module
    from test_drivers import RIG, write_rig  # the same directory (pytest prepends it)
    from wvr.assemble import make_rig

    class DevicesStandIn(LoggingRobot):
        def __init__(self, cfg):
            super().__init__()
            self.cfg = cfg

    monkeypatch.setattr(rig_module, "HardwareRig", DevicesStandIn)
    text = RIG.format(port="/dev/null") + "[safety]\nmotion_limit_deg_s = 20.0\nestop_file = \"stop.latch\"\n"
    rig = make_rig(write_rig(tmp_path, text))
    assert isinstance(rig.robot, DevicesStandIn)
    check_safe_robot(rig, lambda: rig.robot.sent, math.radians(20.0))
    rig.estop.trip("rig test stop")
    assert (tmp_path / "stop.latch").exists()                     # outlives the process
    with pytest.raises(EStopLatched, match="wvr head --rig .* reset"):
        rig.reset()
    rig.close()
    assert rig.robot.closed
