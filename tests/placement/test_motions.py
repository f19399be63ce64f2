"""The turn-round-room scenario's motion (placement.motions.turn_round through the composition
root): the wearer turns once round, in four steps, from the motion's own data (no simulator)."""

import math

import numpy as np

from runtime.twin.scenarios import get_scenario
from wvr.assemble import wearer_for


def _heading_deg(scenario_name: str, dt: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Times and the unwrapped heading, deg, of the chest (the shoulder mount's segment) over the
    scenario: where the body's forward (-y at rest) points in the world's x-y plane."""
    sc = get_scenario(scenario_name)
    w = wearer_for(sc, sc.seconds)
    t = np.arange(0.0, sc.seconds, dt)
    G = w.pose(w.index("chest"), t)
    fwd = -G[:, :3, 1]
    return t, np.degrees(np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0])))


def test_turn_round_room_turns_the_body_once_round_to_the_left_in_four_quarter_turns():
    t, yaw = _heading_deg("turn-round-room")
    turned = yaw - yaw[0]
    assert abs(turned[-1] - 360.0) < 3.0                      # once round, to the left (+z)
    rate = np.gradient(turned, t)
    moving = np.abs(rate) > 5.0                               # deg/s: turning, not swaying
    starts = np.flatnonzero(moving[1:] & ~moving[:-1])
    assert len(starts) == 4 and not moving[: int(4.5 / 0.05)].any()   # still for 5 s, then four turns
    assert rate.min() > -5.0                                  # never back to the right
    # In each pause the heading holds a quarter more: 90, 180, 270 and 360 deg.
    for k in range(4):
        pause = (t > 5.0 + 6.25 * k + 3.2) & (t < 5.0 + 6.25 * (k + 1) - 0.1)
        np.testing.assert_allclose(turned[pause], 90.0 * (k + 1), atol=3.0)


def test_turn_round_keeps_its_schedule_whatever_the_runs_length():
    from placement import motions
    from placement.body import make_body

    body = make_body()
    short = motions.turn_round(body, seconds=6.5)            # cut half-way through the first turn
    assert len(short.t) == 195
    s = (short.t[-1] - 5.0) / 3.0
    expected = 90.0 * (10 * s**3 - 15 * s**4 + 6 * s**5)
    assert abs(math.degrees(short.rotvec[-1, 0, 2]) - expected) < 0.01 and 30 < expected < 60
    long = motions.turn_round(body, seconds=40.0)             # ends standing, once round
    assert abs(math.degrees(long.rotvec[-1, 0, 2]) - 360.0) < 0.01
    np.testing.assert_array_equal(long.rotvec[:len(short.t)], short.rotvec)
