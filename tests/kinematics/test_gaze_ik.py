"""Gaze IK: round trips through FK, the image-vertical rule, analytic cases, refusals."""

import math

import numpy as np
import pytest

from kinematics import JOINT_NAMES, forward_kinematics, gaze_at_direction, gaze_at_point, reference_head
from kinematics.gaze_ik import ZENITH_CONE_RAD, paden_kahan_2
from kinematics.chain import axis_angle_matrix


def angle_between(a, b):
    a = a / np.linalg.norm(a); b = b / np.linalg.norm(b)
    return math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b))


def random_up(rng, tilt_deg=25.0):
    """World up seen from a mount tilted by up to tilt_deg (a leaning wearer)."""
    axis = rng.normal(size=3); axis[2] = 0; axis /= np.linalg.norm(axis)
    return axis_angle_matrix(axis, math.radians(rng.uniform(0, tilt_deg))) @ np.array([0.0, 0.0, 1.0])


def check_fixation(head, q, d, up, vertical_defined):
    pose = forward_kinematics(head, q)
    assert angle_between(pose.optic_axis, d) < 1e-9
    assert np.all(q >= head.lower - 1e-12) and np.all(q <= head.upper + 1e-12)
    if vertical_defined:
        assert abs(pose.R_mount_cam[:, 0] @ up) < 1e-9      # optical x horizontal
        assert pose.R_mount_cam[:, 1] @ up < 0                # optical y (down) points down: upright


def test_direction_round_trip_over_workspace():
    head = reference_head()
    rng = np.random.default_rng(0)
    reached = 0
    for _ in range(1000):
        q_true = rng.uniform(head.lower, head.upper)
        d = forward_kinematics(head, q_true).optic_axis
        up = random_up(rng)
        res = gaze_at_direction(head, d, up, q_current=rng.uniform(head.lower, head.upper))
        in_cone = angle_between(d, up) < ZENITH_CONE_RAD or angle_between(d, -up) < ZENITH_CONE_RAD
        assert res.vertical_defined == (not in_cone)
        if res.reachable:
            reached += 1
            for s in res.solutions:
                check_fixation(head, s.q, d, up, res.vertical_defined)
        else:
            # Elevation and pan are reachable by construction, so only the upright cyclotorsion
            # can be out of range, and the reason must say so.
            assert res.blocking_joint == "cyclotorsion", res.reason
            assert "cyclotorsion would need" in res.reason
    assert reached > 750


def test_point_round_trip_over_workspace():
    head = reference_head()
    rng = np.random.default_rng(1)
    reached = 0
    for _ in range(300):
        q_true = rng.uniform(head.lower * 0.9, head.upper * 0.9)
        pose = forward_kinematics(head, q_true)
        p = pose.p_mount_cam + rng.uniform(0.15, 3.0) * pose.optic_axis
        up = random_up(rng)
        res = gaze_at_point(head, p, up, q_current=np.zeros(3))
        if not res.reachable:
            assert res.blocking_joint in JOINT_NAMES
            continue
        reached += 1
        q = res.q
        sol = forward_kinematics(head, q)
        assert angle_between(sol.optic_axis, p - sol.p_mount_cam) < 1e-9
        assert (p - sol.p_mount_cam) @ sol.optic_axis > 0            # in front
        if res.vertical_defined:
            assert abs(sol.R_mount_cam[:, 0] @ up) < 1e-9
            assert sol.R_mount_cam[:, 1] @ up < 0
    assert reached > 200


def test_analytic_cases_reference_head():
    head = reference_head()
    np.testing.assert_allclose(gaze_at_direction(head, [1, 0, 0]).q, [0, 0, 0], atol=1e-12)
    t = math.radians(30)
    np.testing.assert_allclose(gaze_at_direction(head, [math.cos(t), math.sin(t), 0]).q, [0, t, 0], atol=1e-12)
    e = math.radians(20)
    np.testing.assert_allclose(gaze_at_direction(head, [math.cos(e), 0, math.sin(e)]).q, [e, 0, 0], atol=1e-12)
    # A mount rolled 10 degrees to its left: world up leans to the mount's right (-y), and the
    # cyclotorsion (about +x, forward) must turn by +10 degrees to level optical x.
    r = math.radians(10)
    up = np.array([0.0, -math.sin(r), math.cos(r)])   # world up as seen from the rolled mount
    q = gaze_at_direction(head, [1, 0, 0], up).q
    np.testing.assert_allclose(q, [0, 0, r], atol=1e-12)


def test_zenith_cone_holds_cyclotorsion_and_says_so():
    head = reference_head()
    d = [math.cos(math.radians(88)), 0, math.sin(math.radians(88))]   # 2 deg off the zenith
    head = head.with_joint_ranges(head.lower, [math.radians(89), head.upper[1], head.upper[2]])
    res = gaze_at_direction(head, d, q_current=[0, 0, 0.3])
    assert res.reachable and not res.vertical_defined
    assert res.q[2] == pytest.approx(0.3)
    assert angle_between(forward_kinematics(head, res.q).optic_axis, np.array(d)) < 1e-9


def test_unreachable_names_the_limit():
    head = reference_head()
    res = gaze_at_direction(head, [-1, 0.2, 0.0])   # behind the wearer's shoulder
    assert not res.reachable
    assert res.blocking_joint in ("pan", "elevation")
    assert "would need" in res.reason and "outside its range" in res.reason
    with pytest.raises(ValueError, match="unreachable"):
        res.q
    res = gaze_at_point(head, forward_kinematics(head, np.zeros(3)).p_mount_cam + [0.001, 0, 0.002])
    assert not res.reachable


def test_near_singular_posture_is_reported():
    head = reference_head()
    # Let pan reach 90 degrees, where the optic axis lies along the elevation axis.
    head = head.with_joint_ranges(head.lower, [head.upper[0], math.radians(100), head.upper[2]])
    res = gaze_at_direction(head, [0.0, 1.0, 0.0])
    assert res.reachable and res.near_singular
    assert res.best.sigma_min < 1e-6
    assert not gaze_at_direction(head, [1.0, 0.2, 0.1]).near_singular


def test_paden_kahan_against_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(200):
        w1, w2, p = (v / np.linalg.norm(v) for v in rng.normal(size=(3, 3)))
        t1, t2 = rng.uniform(-math.pi, math.pi, 2)
        q = axis_angle_matrix(w1, t1) @ axis_angle_matrix(w2, t2) @ p
        sols = paden_kahan_2(w1, w2, p, q)
        assert sols
        for s1, s2 in sols:
            np.testing.assert_allclose(axis_angle_matrix(w1, s1) @ axis_angle_matrix(w2, s2) @ p, q, atol=1e-9)
        assert any(abs(math.remainder(s1 - t1, 2 * math.pi)) < 1e-6 and abs(math.remainder(s2 - t2, 2 * math.pi)) < 1e-6
                   for s1, s2 in sols)


def test_best_solution_is_nearest_current():
    head = reference_head()
    wide = head.with_joint_ranges(np.radians([-80, -80, -80]), np.radians([80, 80, 80]))
    res = gaze_at_direction(wide, [0.9, 0.1, 0.3], q_current=[0.1, 0.1, 0.0])
    dists = [np.linalg.norm(s.q - [0.1, 0.1, 0.0]) for s in res.solutions]
    assert dists == sorted(dists)


def test_bad_target_is_refused_clearly():
    with pytest.raises(ValueError, match="zero or non-finite length"):
        gaze_at_direction(reference_head(), [0, 0, 0])


def test_a_far_point_out_of_range_is_refused_by_its_joint_not_as_too_close():
    """1e9 m along the elevation axis is a gimbal lock for Newton; the reason is the pan range."""
    h = reference_head()
    for p, sign in (((0.0, 1e9, 0.0), 1), ((0.0, -1e9, 0.0), -1), ((0.0, 10.0, 0.0), 1), ((0.0, -10.0, 0.0), -1)):
        r = gaze_at_point(h, np.array(p))
        assert not r.reachable and r.blocking_joint == "pan", r.reason
        need = float(r.reason.split("would need ")[1].split(" deg")[0])
        assert "too close" not in r.reason and 85 < sign * need < 95, r.reason
    # What 'wvr sim run --target 1e9,0,0' asked of the head: the point in the mount frame, the
    # mount's up and the joints at the time (it was refused as "too close to the head").
    r = gaze_at_point(h, np.array([0.0449236841, 1e9, -1.42063961]), np.array([0.0, 0.0, 1.0]),
                      q_current=np.array([-0.7769195, 0.16879482, -0.16369169]))
    assert not r.reachable and "too close" not in r.reason and r.blocking_joint in ("elevation", "pan"), r.reason
    # Far and reachable along any direction: the same answer as the direction itself.
    for d in ([1.0, 0.0, 0.0], [1.0, 0.8, 0.3], [0.6, -0.5, -0.4]):
        d = np.array(d) / np.linalg.norm(d)
        rp, rd = gaze_at_point(h, 1e9 * d), gaze_at_direction(h, d)
        assert rp.reachable and rd.reachable
        np.testing.assert_allclose(rp.q, rd.q, atol=1e-6)
    # Near the head it is still "too close".
    assert "too close" in gaze_at_point(h, np.array([0.0, 0.02, 0.0])).reason
