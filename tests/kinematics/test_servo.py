"""The servo command filter: hard limits under any command sequence (property tests)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from kinematics import ServoCommandError, ServoFilter, filter_sequence, reference_head

HEAD = reference_head()
angles = st.floats(min_value=-50.0, max_value=50.0, allow_nan=False)
commands = st.lists(st.tuples(angles, angles, angles), min_size=1, max_size=60)
dts = st.floats(min_value=1e-4, max_value=0.2)


@settings(max_examples=200, deadline=None)
@given(commands, dts, st.floats(min_value=0.05, max_value=10.0), st.tuples(angles, angles, angles))
def test_any_command_sequence_stays_within_range_and_speed(cmds, dt, speed, q0):
    f = ServoFilter(HEAD, q0, speed_limit=speed)
    prev = f.q.copy()
    assert np.all(prev >= HEAD.lower) and np.all(prev <= HEAD.upper)
    for c in cmds:
        q = f.step(c, dt)
        assert np.all(q >= HEAD.lower) and np.all(q <= HEAD.upper)
        assert np.all(np.abs(q - prev) <= speed * dt * (1 + 1e-12) + 1e-15)
        prev = q


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(angles, angles, angles), min_size=1, max_size=30), dts)
def test_rate_commands_obey_the_same_limits(rates, dt):
    f = ServoFilter(HEAD)
    prev = f.q.copy()
    for r in rates:
        q = f.step_rate(r, dt)
        assert np.all(q >= HEAD.lower) and np.all(q <= HEAD.upper)
        assert np.all(np.abs(q - prev) <= HEAD.max_speed * dt * (1 + 1e-12))
        prev = q


def test_reachable_target_is_reached_at_full_speed():
    f = ServoFilter(HEAD)
    out = [f.step([0.5, -0.3, 0.0], 0.01) for _ in range(10)]
    # 10 rad/s for 10 ms is 0.1 rad a step: 0.1, 0.2, ... then holds 0.5.
    np.testing.assert_allclose(out[0], [0.1, -0.1, 0.0])
    np.testing.assert_allclose(out[-1], [0.5, -0.3, 0.0])
    assert f.clamped_speed == 4


def test_out_of_range_target_clamped_and_counted():
    f = ServoFilter(HEAD, speed_limit=10.0)
    for _ in range(100):
        q = f.step([5.0, -5.0, 0.0], 0.01)
    np.testing.assert_allclose(q, [HEAD.upper[0], HEAD.lower[1], 0.0])
    assert f.clamped_position == 100


def test_refusals():
    f = ServoFilter(HEAD)
    with pytest.raises(ServoCommandError, match="NaN or Inf"):
        f.step([math.nan, 0, 0], 0.01)
    np.testing.assert_array_equal(f.q, 0.0)        # refused command leaves the servos holding
    with pytest.raises(ServoCommandError, match="dt"):
        f.step([0, 0, 0], 0.0)
    with pytest.raises(ServoCommandError, match="exceeds the servo"):
        ServoFilter(HEAD, speed_limit=11.0)
    with pytest.raises(ServoCommandError, match="3 angles"):
        f.step([0, 0], 0.01)


def test_controlled_motion_limit_30_deg_per_s():
    out = filter_sequence(HEAD, [[0, 1.0, 0]] * 50, 1 / 30, speed_limit=math.radians(30))
    rates = np.abs(np.diff(np.vstack([[0, 0, 0], out]), axis=0)) * 30
    assert rates.max() <= math.radians(30) * (1 + 1e-12)


def test_torque_estimate_holds_the_payload():
    f = ServoFilter(HEAD)
    tau = f.required_torque(np.zeros(3), np.zeros(3), np.zeros(3))
    assert tau[0] > 0 and np.all(f.torque_margin(tau) > 0)
    # A violent acceleration needs more than the HS-50 can give, and the margin says so.
    tau = f.required_torque(np.zeros(3), np.zeros(3), np.full(3, 5000.0))
    assert np.any(f.torque_margin(tau) < 0)
