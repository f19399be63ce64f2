"""The gaze controller against analytic cases: the rate QP, the IMU attitude filter, fixation
IK reached and held, limits never exceeded (hypothesis), unreachable targets refused with a
wearer prompt."""

import math

import numpy as np
import pytest
import scipy.optimize
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kinematics import forward_kinematics, gaze_at_point, reference_head
from kinematics.camera import default_camera, project
from runtime.gaze import AttitudeFilter, ControllerSettings, GazeController, GazeRefused, RateQP, wearer_prompt

HEAD = reference_head()
CAM = default_camera()
DT = 1 / 30
G_UP = np.array([0.0, 0.0, 9.81])


# ------------------------------------------------------------------ the rate QP
def test_qp_follows_the_desired_rates_when_no_limit_binds():
    qp = RateQP()
    J = forward_kinematics(HEAD, [0.2, -0.3, 0.1]).R_mount_cam.T @ forward_kinematics(HEAD, [0.2, -0.3, 0.1]).axes_mount.T
    qd_des = np.array([0.1, -0.2, 0.05])
    qd = qp.solve(J, qd_des, qd_des, -np.ones(3), np.ones(3))
    np.testing.assert_allclose(qd, qd_des, atol=1e-4)


@pytest.mark.parametrize("seed", range(5))
def test_qp_matches_an_independent_bounded_least_squares(seed):
    rng = np.random.default_rng(seed)
    qp = RateQP()
    J = Rotation.random(random_state=seed).as_matrix() @ np.diag(rng.uniform(0.3, 1.5, 3))
    qd_des, qd_prev = rng.normal(0, 2, 3), rng.normal(0, 0.3, 3)
    lo, hi = -np.full(3, 0.5), np.full(3, 0.5)
    qd = qp.solve(J, qd_des, qd_prev, lo, hi)
    W = np.diag([1, 1, qp.settings.roll_weight])
    s = qp.settings
    A = np.vstack([W @ J, math.sqrt(s.smooth) * np.eye(3), math.sqrt(s.reg) * np.eye(3)])
    b = np.concatenate([W @ J @ qd_des, math.sqrt(s.smooth) * qd_prev, np.zeros(3)])
    ref = scipy.optimize.lsq_linear(A, b, bounds=(lo, hi), tol=1e-12).x
    assert np.all(qd >= lo) and np.all(qd <= hi)
    np.testing.assert_allclose(qd, ref, atol=2e-4)


def test_qp_bounds_stop_at_the_joint_range_within_one_period():
    lo, hi = RateQP.bounds([1.39, 0.0, -1.39], HEAD.lower, HEAD.upper, 0.5, DT)
    assert hi[0] == pytest.approx((HEAD.upper[0] - 1.39) / DT)
    assert lo[2] == pytest.approx((HEAD.lower[2] + 1.39) / DT)
    assert lo[1] == -0.5 and hi[1] == 0.5


# ------------------------------------------------------------------ the attitude filter
def imu_rows(R_world_cam_seq, t, accel_world=None):
    """IMU rows [t, w, f] for a camera orientation sequence, by finite differences."""
    rows = []
    for k in range(len(t) - 1):
        w = Rotation.from_matrix(R_world_cam_seq[k].T @ R_world_cam_seq[k + 1]).as_rotvec() / (t[k + 1] - t[k])
        a = np.zeros(3) if accel_world is None else accel_world[k]
        rows.append([t[k + 1], *w, *(R_world_cam_seq[k + 1].T @ (a + G_UP))])
    return np.array(rows)


def test_attitude_integrates_a_constant_rotation():
    t = np.arange(0, 2.0, 0.005)
    w_cam = np.array([0.3, -0.2, 0.5])
    R0 = Rotation.from_euler("xyz", [-100, 5, 30], degrees=True).as_matrix()
    Rs = np.array([R0 @ Rotation.from_rotvec(w_cam * ti).as_matrix() for ti in t])
    f = AttitudeFilter(R0, gain=0.0)
    f.t = 0.0
    R = f.update(imu_rows(Rs, t))
    assert Rotation.from_matrix(R.T @ Rs[-1]).magnitude() < 1e-6


def test_attitude_levels_itself_from_gravity():
    R_true = Rotation.from_euler("xyz", [-95, 8, 40], degrees=True).as_matrix()
    tilt = Rotation.from_rotvec([0.1, -0.05, 0.0]).as_matrix()
    f = AttitudeFilter(R_true @ tilt, gain=1.0)
    f.t = 0.0
    t = np.arange(0, 10.0, 0.005)
    R = f.update(imu_rows(np.repeat(R_true[None], len(t), 0), t))
    # Gravity fixes pitch and roll, not yaw: compare where world up lies in the camera frame.
    assert np.degrees(np.arccos(np.clip(R[2] @ R_true[2], -1, 1))) < 0.05


# ------------------------------------------------------------------ the controller, static body
def run_static(ctl: GazeController, T_world_mount, q0, steps: int):
    """Step the controller with a perfect servo and a still body; returns the commands (n, 3)."""
    q = np.asarray(q0, float)
    R_prev = (T_world_mount @ forward_kinematics(HEAD, q).T_mount_cam)[:3, :3]
    out = []
    for k in range(steps):
        T_wc = T_world_mount @ forward_kinematics(HEAD, q).T_mount_cam
        rows = imu_rows(np.array([R_prev, T_wc[:3, :3]]), np.array([k * DT, (k + 1) * DT])) if k else np.zeros((0, 7))
        cmd = ctl.step((k + 1) * DT, rows, q, T_world_cam=T_wc, v_world=np.zeros(3))
        R_prev = T_wc[:3, :3]
        q = cmd.q
        out.append(cmd)
    return out


def fixating_posture(p_mount):
    return gaze_at_point(HEAD, p_mount).q


def test_a_point_straight_ahead_of_a_still_body_needs_no_motion():
    p_mount = np.array([0.6, -0.4, -0.3])
    q0 = fixating_posture(p_mount)
    ctl = GazeController(HEAD, CAM, q0, DT)
    cmds = run_static(ctl, np.eye(4), q0, 1)
    ctl.fixate(p_mount)
    cmds = run_static(ctl, np.eye(4), q0, 10)
    assert max(np.abs(c.qd).max() for c in cmds) < 1e-6
    assert cmds[-1].error_rad < 1e-6


def test_a_point_at_a_known_angle_is_reached_at_the_ik_angles_within_the_limit():
    T_world_mount = np.eye(4)
    T_world_mount[:3, 3] = [0.2, -0.1, 1.4]
    p_mount0 = np.array([0.6, -0.4, -0.3])
    q0 = fixating_posture(p_mount0)
    p_world = T_world_mount[:3, 3] + np.array([0.5, 0.3, -0.5])
    expected = gaze_at_point(HEAD, p_world - T_world_mount[:3, 3], q_current=q0).q
    limit = math.radians(30)
    ctl = GazeController(HEAD, CAM, q0, DT, ControllerSettings(motion_limit_rad_s=limit))
    run_static(ctl, T_world_mount, q0, 1)
    ctl.saccade(p_world)
    cmds = run_static(ctl, T_world_mount, q0, 120)
    np.testing.assert_allclose(cmds[-1].q, expected, atol=1e-4)
    assert max(np.abs(c.qd).max() for c in cmds) <= limit + 1e-9
    assert any(c.landed for c in cmds)
    # And the point is then at the image centre.
    T_wc = T_world_mount @ forward_kinematics(HEAD, cmds[-1].q).T_mount_cam
    uv = project(CAM, ((p_world - T_wc[:3, 3]) @ T_wc[:3, :3])[None])[0]
    np.testing.assert_allclose(uv, [CAM.cx, CAM.cy], atol=0.05)


@settings(max_examples=25, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-1.2, 1.2), st.floats(0.3, 3.0),
       st.lists(st.floats(-1.3, 1.3), min_size=3, max_size=3), st.floats(5.0, 60.0))
def test_limits_are_never_exceeded_and_unreachable_targets_are_refused(az, el, dist, q0, limit_deg):
    p = dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    limit = math.radians(limit_deg)
    ctl = GazeController(HEAD, CAM, q0, DT, ControllerSettings(motion_limit_rad_s=limit))
    run_static(ctl, np.eye(4), q0, 1)
    q_prev = ctl.filter.q.copy()
    reachable = gaze_at_point(HEAD, p, q_current=q_prev).reachable
    try:
        ctl.fixate(p)
    except GazeRefused as e:
        assert not reachable
        assert e.prompt is not None and e.prompt.kind in ("turn", "step", "none")
        assert ctl.mode == "hold"
        return
    assert reachable
    for c in run_static(ctl, np.eye(4), q_prev, 15):
        assert np.all(c.q >= HEAD.lower - 1e-12) and np.all(c.q <= HEAD.upper + 1e-12)
        assert np.all(np.abs(c.q - q_prev) <= limit * DT + 1e-12)
        q_prev = c.q


def test_an_unreachable_target_is_refused_with_a_prompt_to_turn_the_right_way():
    q0 = fixating_posture(np.array([0.6, -0.4, -0.3]))
    for side, way in ((1.0, "left"), (-1.0, "right")):
        ctl = GazeController(HEAD, CAM, q0, DT)
        run_static(ctl, np.eye(4), q0, 1)
        # Behind the wearer and to one side (mount frame: x forward, y left, z up).
        p = np.array([-1.0, side * 0.4, -0.2])
        assert not gaze_at_point(HEAD, p, q_current=q0).reachable
        with pytest.raises(GazeRefused) as e:
            ctl.fixate(p)
        prompt = e.value.prompt
        assert prompt.kind == "turn" and way in prompt.text
        # Turning as asked makes it reachable.
        psi = prompt.turn_rad
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0, 0, psi]).as_matrix()
        assert wearer_prompt(HEAD, T, p, q0).kind == "ok"
        assert ctl.prompts and ctl.prompts[-1][1] is prompt


def test_a_held_target_that_becomes_unreachable_is_prompted_about_once_a_period_of_prompts(monkeypatch):
    """The prompt's search (up to 80 IK solves) runs when a prompt is due, not every control
    period: the loop keeps its rate while the wearer faces away."""
    import runtime.gaze.modes as modes

    searches = []
    monkeypatch.setattr(modes, "wearer_prompt", lambda *a, **k: searches.append(1) or wearer_prompt(*a, **k))
    p = np.array([0.6, -0.4, -0.3])
    q0 = fixating_posture(p)
    ctl = GazeController(HEAD, CAM, q0, DT)
    run_static(ctl, np.eye(4), q0, 1)
    ctl.fixate(p)
    T_turned = np.eye(4)
    T_turned[:3, :3] = Rotation.from_rotvec([0.0, 0.0, math.pi]).as_matrix()   # the wearer turned round
    seconds = 3.0
    cmds = run_static(ctl, T_turned, q0, int(seconds / DT))
    assert not any(c.reachable for c in cmds[2:])
    every = ctl.settings.prompt_every_s
    assert 1 <= len(searches) <= seconds / every + 1
    standing = [pr for _, pr in ctl.prompts]
    assert len(standing) == len(searches) and all(pr.kind == "turn" for pr in standing)


def _estimate(T_world_mount, q, prompt_due=False, w_mount=(0.0, 0.0, 0.0)):
    from runtime.gaze import GazeEstimate

    return GazeEstimate(t=0.0, q_enc=q, q=q, T_mount_cam=forward_kinematics(HEAD, q).T_mount_cam, T_world_cam=None,
                        T_world_mount=T_world_mount, v_mount=np.zeros(3), w_mount=np.asarray(w_mount, float),
                        R_world_cam=None, lead=DT, prompt_due=prompt_due)


def test_a_mode_reads_a_frozen_estimate_built_without_a_controller():
    """Modes take (estimate, head, camera): a hand-made estimate gives the IK's angles from the
    mount pose it states, and the estimate cannot be changed by a mode."""
    import dataclasses

    from runtime.gaze import Fixate, Slave

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.4]).as_matrix()
    T[:3, 3] = [0.2, -0.1, 1.4]
    q0 = fixating_posture(np.array([0.6, -0.4, -0.3]))
    p_world = T[:3, 3] + T[:3, :3] @ np.array([0.7, 0.2, -0.4])
    est = _estimate(T, q0)
    goal = Fixate(p_world).desired(est, HEAD, CAM)
    np.testing.assert_allclose(goal.q, gaze_at_point(HEAD, np.array([0.7, 0.2, -0.4]), T[:3, :3].T @ [0, 0, 1],
                                                     q_current=q0).q, atol=1e-12)
    T_wc = T @ forward_kinematics(HEAD, q0).T_mount_cam
    d = p_world - T_wc[:3, 3]
    assert goal.error_rad == pytest.approx(math.acos(T_wc[:3, 2] @ d / np.linalg.norm(d)), abs=1e-12)
    # The wearer turning: the goal is taken from where the mount will be a lead ahead.
    turned = Fixate(p_world).desired(_estimate(T, q0, w_mount=(0.0, 0.0, 1.0)), HEAD, CAM)
    T_ahead = T.copy()
    T_ahead[:3, :3] = Rotation.from_rotvec([0.0, 0.0, DT]).as_matrix() @ T[:3, :3]
    p_ahead = T_ahead[:3, :3].T @ (p_world - T[:3, 3])
    np.testing.assert_allclose(turned.q, gaze_at_point(HEAD, p_ahead, T_ahead[:3, :3].T @ [0, 0, 1], q_current=q0).q,
                               atol=1e-12)
    assert Slave(q0 + 0.1).desired(est, HEAD, CAM).error_rad == pytest.approx(math.sqrt(3) * 0.1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        est.q = np.zeros(3)
    with pytest.raises(ValueError):
        est.T_world_mount[0, 3] = 5.0


def test_the_controller_hands_its_modes_the_periods_estimate():
    p = np.array([0.6, -0.4, -0.3])
    q0 = fixating_posture(p)
    ctl = GazeController(HEAD, CAM, q0, DT)
    seen = []

    class Spy:
        name = "spy"

        def desired(self, est, head, camera):
            seen.append((est, head, camera))
            from runtime.gaze import Desired
            return Desired(None)

    ctl.set_mode(Spy())
    T_world_mount = np.eye(4)
    T_world_mount[:3, 3] = [0.1, 0.2, 1.3]
    T_wc = T_world_mount @ forward_kinematics(HEAD, q0).T_mount_cam
    ctl.step(0.5, np.zeros((0, 7)), q0, T_world_cam=T_wc)
    est, head, camera = seen[-1]
    assert head is HEAD and camera is CAM and est.t == 0.5 and est.lead == ctl.lead
    np.testing.assert_allclose(est.T_world_mount, T_world_mount, atol=1e-12)
    np.testing.assert_array_equal(est.T_world_cam, T_wc)
    np.testing.assert_array_equal(est.q_enc, q0)
    assert est.R_world_cam is None and est.prompt_due


def test_a_mode_builds_a_prompt_only_when_the_controller_says_one_is_due():
    from runtime.gaze import Fixate

    q0 = fixating_posture(np.array([0.6, -0.4, -0.3]))
    behind = np.array([-1.0, 0.4, -0.2])
    assert Fixate(behind).desired(_estimate(np.eye(4), q0, prompt_due=False), HEAD, CAM).prompt is None
    goal = Fixate(behind).desired(_estimate(np.eye(4), q0, prompt_due=True), HEAD, CAM)
    assert not goal.reachable and goal.q is None and goal.prompt.kind == "turn" and "left" in goal.prompt.text


def test_the_prompts_coarse_to_fine_search_finds_the_smallest_turn_a_step_by_step_search_finds():
    from runtime.gaze.prompts import _reachable

    def step_by_step(T, p, q, step=math.radians(5.0)):
        for i in range(1, 37):
            for sign in (1.0, -1.0):
                Tn = T.copy()
                Tn[:3, :3] = Rotation.from_rotvec([0.0, 0.0, sign * i * step]).as_matrix() @ T[:3, :3]
                if _reachable(HEAD, Tn, p, q):
                    return sign * i * step
        return None

    rng = np.random.default_rng(4)
    q0 = fixating_posture(np.array([0.6, -0.4, -0.3]))
    turns = []
    for _ in range(16):
        az, el = rng.uniform(-math.pi, math.pi), rng.uniform(-0.5, 0.3)
        p = rng.uniform(0.5, 2.0) * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        pr = wearer_prompt(HEAD, np.eye(4), p, q0)
        ref = step_by_step(np.eye(4), p, q0)
        if pr.kind == "ok":
            continue
        assert (pr.kind == "turn") == (ref is not None)
        if ref is not None:
            assert pr.turn_rad == pytest.approx(ref)
            turns.append(abs(ref))
    assert len(turns) >= 5 and max(turns) > math.radians(60)      # far turns were among them


def test_a_limit_above_the_servos_is_refused():
    with pytest.raises(ValueError, match="exceeds the servos"):
        GazeController(HEAD, CAM, np.zeros(3), DT, ControllerSettings(motion_limit_rad_s=12.0))


def test_track_mode_centres_an_image_point():
    q0 = fixating_posture(np.array([0.6, -0.4, -0.3]))
    ctl = GazeController(HEAD, CAM, q0, DT)
    run_static(ctl, np.eye(4), q0, 1)
    p_world = np.array([0.7, -0.2, -0.35])
    q = ctl.filter.q.copy()
    for _ in range(60):
        T_wc = forward_kinematics(HEAD, q).T_mount_cam
        uv = project(CAM, ((p_world - T_wc[:3, 3]) @ T_wc[:3, :3])[None])[0]
        ctl.track(uv)
        q = run_static(ctl, np.eye(4), q, 1)[0].q
    T_wc = forward_kinematics(HEAD, q).T_mount_cam
    uv = project(CAM, ((p_world - T_wc[:3, 3]) @ T_wc[:3, :3])[None])[0]
    # Track turns the optic axis onto the point's ray; the centre's offset from the axes moves
    # the point a little as the head turns, and the loop closes that on later images.
    np.testing.assert_allclose(uv, [CAM.cx, CAM.cy], atol=0.5)


def test_slaving_to_a_tracked_head_follows_the_mapped_angles_within_the_limits():
    from runtime.gaze.slaving import head_to_joint_targets

    q0 = np.zeros(3)
    limit = math.radians(30)
    ctl = GazeController(HEAD, CAM, q0, DT, ControllerSettings(motion_limit_rad_s=limit))
    run_static(ctl, np.eye(4), q0, 1)
    q, prev = ctl.filter.q.copy(), ctl.filter.q.copy()
    # A person turning their head left and up over 2 s, then holding.
    t = np.arange(90) * DT
    ypr = np.column_stack([np.radians(40) * np.minimum(t / 2, 1), np.radians(15) * np.minimum(t / 2, 1), 0 * t])
    for k in range(len(t)):
        ctl.slave(head_to_joint_targets(ypr[k], limits=HEAD))
        q = run_static(ctl, np.eye(4), q, 1)[0].q
        assert np.all(np.abs(q - prev) <= limit * DT + 1e-12)
        prev = q
    np.testing.assert_allclose(q, head_to_joint_targets(ypr[-1], limits=HEAD), atol=1e-3)
    with pytest.raises(GazeRefused, match="outside the joint ranges"):
        ctl.slave([0.0, 3.0, 0.0])


def test_the_wearers_rotation_is_the_gyro_less_the_joints_over_the_same_period():
    """A speed-limited board moves the joints early in the period and then holds: the gyro's
    last samples show the wearer alone, its first ones the wearer and the head. Over the period
    the difference of the gyro's mean and the encoders' change is the wearer's rotation; the
    latest sample less the commanded rate is not."""
    q0 = np.radians([-10.0, 5.0, 0.0])
    dq = np.radians([1.5, -2.0, 0.8])
    w_wearer = np.array([0.0, 0.0, 0.4])                      # the mount turning about world up, rad/s
    R0 = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    ctl = GazeController(HEAD, CAM, q0, DT)

    def T_world_mount(t):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(w_wearer * t).as_matrix() @ R0
        return T
    # The period [0, DT]: the joints go from q0 to q0 + dq within its first quarter, then hold.
    t = np.linspace(0.0, DT, 41)
    q_t = q0 + dq * np.clip(t / (DT / 4), 0.0, 1.0)[:, None]
    Rs = np.array([(T_world_mount(ti) @ forward_kinematics(HEAD, qi).T_mount_cam)[:3, :3] for ti, qi in zip(t, q_t)])
    rows = imu_rows(Rs, t)
    ctl.step(0.0, np.zeros((0, 7)), q0, T_world_cam=T_world_mount(0.0) @ forward_kinematics(HEAD, q0).T_mount_cam)
    ctl.qd_prev = dq / DT                                       # what was commanded for the period
    q1 = q0 + dq
    ctl.step(DT, rows, q1, T_world_cam=T_world_mount(DT) @ forward_kinematics(HEAD, q1).T_mount_cam)
    assert np.linalg.norm(ctl.w_mount - w_wearer) < 0.005 * np.linalg.norm(w_wearer)
