"""The head-motion start: the map's metric scale from the head's own known motion.

Checked against an independent ground truth: a textured plane rendered by its exact homography
at every pose of the head's motion (reference head, forward kinematics), with the mount drifting
as a still wearer's does; the start's points must lie on the plane at its true distance.
"""

import math
import threading
import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics import forward_kinematics
from kinematics.camera import default_camera
from kinematics.geometry import reference_head
from runtime.apps.head_motion import (CORNERS, MAX_BACKLOG, SOLVE_DELAY_S, HeadMotionPhase, HeadMotionPlan,
                                      level_attitude, waypoints)
from runtime.slam.head_motion_start import (GyroTurns, HeadMotionSettings, HeadMotionStart, calibrate_to_encoders,
                                             point_at_pixel)
from runtime.slam.natural_start import NaturalStart, StartWait
from runtime.slam.state import BG_SLICE
from runtime.slam.system import MonoSLAM

CAM = default_camera()
K = np.array([[CAM.fx, 0, CAM.cx], [0, CAM.fy, CAM.cy], [0, 0, 1.0]])
RATE = math.radians(30.0)
#: The synthetic gyro's errors: 0.5% scale and cross-axis terms, a bias (rad/s), a 3 ms late clock.
GYRO_AXES = np.array([[0.005, 0.003, 0.0], [-0.002, -0.004, 0.003], [0.0, 0.002, 0.005]])
GYRO_BIAS = np.array([0.004, -0.006, 0.003])
GYRO_LATE_S = 0.003


def _texture(seed: int = 0, size: int = 1400) -> np.ndarray:
    """A blotchy texture with corners at several scales, 1 px = 1 mm."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.float32)
    for s, a in ((9, 60), (25, 50), (70, 40)):
        n = cv2.resize(rng.uniform(-1, 1, (size // s + 2, size // s + 2)).astype(np.float32), (size, size),
                       interpolation=cv2.INTER_NEAREST if s == 9 else cv2.INTER_LINEAR)
        img += a * n
    return np.clip(128 + img, 0, 255).astype(np.uint8)


def _joint_path(q0: np.ndarray, amplitude: float, dt: float) -> np.ndarray:
    """(F, 3) joint angles at the controlled-motion limit through the corners, then 0.4 s held."""
    qs, q = [q0.copy()], q0.copy()
    for e, p in CORNERS:
        w = q0 + amplitude * np.array([e, p, 0.0])
        while np.abs(w - q).max() > 1e-9:
            q = q + np.clip(w - q, -RATE * dt, RATE * dt)
            qs.append(q.copy())
    qs += [q.copy()] * int(0.4 / dt)
    return np.array(qs)


def _plane_frame(tex, n, point, R, c) -> tuple[np.ndarray, np.ndarray]:
    """The plane through ``point`` with unit normal n textured by ``tex`` (1 px = 1 mm, its
    centre at ``point``) seen by a camera at R, c (first camera's frame): the image (H, W) and
    each pixel's distance along its ray (inf where the plane is behind)."""
    e1 = np.cross(n, [0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    h = tex.shape[0] / 2000.0
    A = np.column_stack([e1 / 1000, e2 / 1000, point - h * (e1 + e2)])
    H = K @ R.T @ (A - np.outer(c, [0, 0, 1]))
    img = cv2.warpPerspective(tex, H, (CAM.width, CAM.height), flags=cv2.INTER_LINEAR).astype(np.float32)
    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u, float)], -1) @ R.T
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    s = ((point - c) @ n) / (rays @ n)
    return img, np.where(s > 0, s, np.inf)


#: The scene, first camera's frame: a desk tilted up towards 1.3 m ahead, a wall 1.9 m away.
PLANES = ((np.array([0.0, -0.35, -1.0]) / np.linalg.norm([0.0, -0.35, -1.0]), np.array([0.0, 0.0, 1.3])),
          (np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.9])))


def _depth_true(X: np.ndarray) -> np.ndarray:
    """(n,) the true distance to the scene along each point's ray from the first camera."""
    u = X / np.linalg.norm(X, axis=1, keepdims=True)
    d = np.array([(p @ n) / (u @ n) for n, p in PLANES])
    d[d <= 0] = np.inf
    return d.min(axis=0)


def _scene(drift: bool, seed: int = 0):
    """Frames of the motion (two textured planes, each pixel the nearer), their times, the
    head-model poses, the true camera poses (first camera's frame) and gyro rows.

    The joints move as a servo does: rate-limited, and with its reversals rounded over 60 ms (a
    finite acceleration); the gyro samples the same motion every 5 ms, so it agrees with the
    frames' poses at the corners too."""
    head = reference_head()
    q0 = np.array([0.0, 0.0, 0.0])
    h = 0.001
    q_fine = _joint_path(q0, math.radians(10.0), h)
    kernel = np.ones(60) / 60
    q_fine = np.column_stack([np.convolve(np.pad(q, (30, 29), mode="edge"), kernel, mode="valid") for q in q_fine.T])
    t_fine = np.arange(len(q_fine)) * h
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * np.pi, 2)

    def poses(t):
        """(n, 4, 4) head-model poses and true T_cam0_cam at times t (n,) s."""
        q = np.column_stack([np.interp(t, t_fine, qj) for qj in q_fine.T])
        M = forward_kinematics(head, q).T_mount_cam
        # A still wearer: breathing turns the mount ~0.6 deg, sway moves it a few mm, slowly.
        D = np.tile(np.eye(4), (len(t), 1, 1))
        if drift:
            D[:, :3, :3] = Rotation.from_rotvec(np.outer(np.sin(2 * np.pi * 0.25 * t + ph[0]) - np.sin(ph[0]),
                                                         [0.0, 0.01, 0.004])).as_matrix()
            D[:, :3, 3] = np.outer(np.sin(2 * np.pi * 0.2 * t + ph[1]) - np.sin(ph[1]), [0.004, 0.003, 0.002])
        M0 = forward_kinematics(head, q_fine[:1]).T_mount_cam[0]
        return M, np.linalg.inv(M0)[None] @ D @ M

    t = np.arange(0.0, t_fine[-1], 1 / 30)
    M, T_c0 = poses(t)
    texs = (_texture(seed, 1600), _texture(seed + 10, 3000))
    frames = []
    for T in T_c0:
        views = [_plane_frame(tex, n, p, T[:3, :3], T[:3, 3]) for tex, (n, p) in zip(texs, PLANES)]
        near = views[0][1] <= views[1][1]
        frames.append(np.where(near, views[0][0], views[1][0]))
    gyro_t = np.arange(0, t_fine[-1], 0.005)
    R_g = Rotation.from_matrix(poses(gyro_t)[1][:, :3, :3])
    w = (R_g[:-1].inv() * R_g[1:]).as_rotvec() / 0.005          # the camera's rates, camera frame
    w = w @ (np.eye(3) + GYRO_AXES).T + GYRO_BIAS                  # a MEMS gyro's errors
    rows = np.column_stack([gyro_t[:-1] + GYRO_LATE_S, w, np.zeros((len(w), 3))])
    return frames, t, M, T_c0, rows


@pytest.fixture(scope="module")
def drifting():
    return _scene(drift=True, seed=1)


def _start(frames, t, M, rows=None):
    est = HeadMotionStart(CAM)
    for g, ti, Mi in zip(frames, t, M):
        est.add(g, ti, Mi)
    return est.solve(np.eye(3), rows)


def test_points_land_on_the_plane_at_its_true_distance(drifting):
    frames, t, M, T_c0, rows = drifting
    r = _start(frames, t, M, rows)
    assert not isinstance(r, StartWait), r
    X = r.start.xyz                                   # world = first camera's frame here
    depth_true = _depth_true(X)
    ratio = np.linalg.norm(X, axis=1) / depth_true
    assert len(X) >= 30
    # The map's unit is the metre: its median within 3%, and the points on the plane.
    assert abs(np.median(ratio) - 1) < 0.03, np.median(ratio)
    assert np.percentile(np.abs(ratio - np.median(ratio)), 90) < 0.12
    # Seen from the start's camera (the last frame, where SLAM begins) the map is metric too.
    T_end = r.start.T_world_cam
    rng_est = np.linalg.norm(X - T_end[:3, 3], axis=1)
    X_true = X / np.linalg.norm(X, axis=1, keepdims=True) * depth_true[:, None]
    rng_true = np.linalg.norm(X_true - T_c0[-1, :3, 3], axis=1)
    assert abs(np.median(rng_est / rng_true) - 1) < 0.03
    # Covariances say how far each point may be: most within 3 sigma along the ray.
    u = X / np.linalg.norm(X, axis=1, keepdims=True)
    sd = np.sqrt(np.einsum("ni,nij,nj->n", u, r.start.xyz_cov, u))
    err = np.linalg.norm(X, axis=1) - depth_true
    assert np.mean(np.abs(err) < 3 * sd) > 0.8
    # SLAM is handed the gyro's bias the calibration found.
    assert np.abs(r.start.gyro_bias - GYRO_BIAS).max() < 1e-3 and r.start.gyro_bias_sigma > 0


def test_slam_takes_the_starts_gyro_bias_over_a_still_stretchs_mean_rate(drifting):
    """A still wearer's sway turns the camera by a degree a second: the mean rate of the still
    stretch before the start takes that in as bias; a start that found the bias gives its own."""
    frames, t, M, T_c0, rows = drifting
    sway = np.array([0.02, 0.0, -0.01])
    ts = np.arange(0.0, 0.6, 0.005)
    imu = np.column_stack([ts, np.tile(GYRO_BIAS + sway, (len(ts), 1)), np.tile([0.0, -9.81, 0.0], (len(ts), 1))])
    uv = np.array([[u, v] for u in range(80, 600, 60) for v in range(80, 420, 60)], float)
    xy = np.column_stack([(uv[:, 0] - CAM.cx) / CAM.fx, (uv[:, 1] - CAM.cy) / CAM.fy])
    xyz = np.column_stack([xy, np.ones(len(xy))])
    cov = np.tile(np.eye(3) * 1e-4, (len(uv), 1, 1))
    image = frames[-1]
    for given, want in ((None, GYRO_BIAS + sway), (GYRO_BIAS, GYRO_BIAS)):
        slam = MonoSLAM(CAM, imu=True)
        slam.add_imu(imu)
        ns = NaturalStart(0, uv, xyz, cov, "head-motion", gyro_bias=given, gyro_bias_sigma=0.002)
        slam.start_natural(image, 0.6, ns)
        state = slam.state
        np.testing.assert_allclose(state.b_g, want, atol=1e-9)
    np.testing.assert_allclose(np.diag(state.P)[BG_SLICE], 0.002**2)


def test_the_gyro_is_calibrated_against_the_encoders(drifting):
    """The gyro's axes (for the axes the head turns about), bias and clock come from comparing its
    turn with the encoders' through a breathing wearer's slow turn."""
    frames, t, M, T_c0, rows = drifting
    E, delta_s, bias, rms = calibrate_to_encoders(GyroTurns(rows, t[0]), t, M)
    want = np.linalg.inv(np.eye(3) + GYRO_AXES) - np.eye(3)        # the correction undoes the error
    assert abs(delta_s - GYRO_LATE_S) < 5e-4, delta_s
    assert np.abs(E[:, :2] - want[:, :2]).max() < 1e-3, E
    assert np.abs(bias - GYRO_BIAS).max() < 1e-3, bias
    assert rms < 5e-4


def test_ignoring_the_drift_gets_the_scale_wrong(drifting):
    """The drift model is what the scale rests on: without the gyro's turn and the drift terms the
    same frames give a different, wrong map (so the first test is not passed by accident)."""
    frames, t, M, T_c0, rows = drifting
    est = HeadMotionStart(CAM, HeadMotionSettings(rotation_order=1, drift_sigma_m=1e-6, drift_sigma_rad=1e-6))
    for g, ti, Mi in zip(frames, t, M):
        est.add(g, ti, Mi)
    r = est.solve()
    if isinstance(r, StartWait):
        return                                         # refused: the frames disagree with a still mount
    X = r.start.xyz
    assert abs(np.median(np.linalg.norm(X, axis=1) / _depth_true(X)) - 1) > 0.05


def test_a_still_mount_needs_no_gyro():
    frames, t, M, T_c0, rows = _scene(drift=False, seed=2)
    r = _start(frames, t, M)
    assert not isinstance(r, StartWait), r
    X = r.start.xyz
    assert abs(np.median(np.linalg.norm(X, axis=1) / _depth_true(X)) - 1) < 0.03
    # The clicked pixel's point: the image centre's ray meets the desk at 1.3 m.
    p = point_at_pixel(CAM, r, np.array([CAM.cx, CAM.cy]))
    assert np.linalg.norm(p - [0, 0, 1.3]) < 0.05


def test_a_blank_view_waits_and_says_why():
    est = HeadMotionStart(CAM)
    M = forward_kinematics(reference_head(), _joint_path(np.zeros(3), math.radians(12.0), 1 / 30)).T_mount_cam
    for i, Mi in enumerate(M[:60]):
        est.add(np.full((CAM.height, CAM.width), 90.0, np.float32), i / 30, Mi)
    r = est.solve()
    assert isinstance(r, StartWait) and "textured" in r.reason


def test_gyro_turns_integrate_a_known_rate():
    t = np.arange(0, 2, 0.005)
    rows = np.column_stack([t, np.tile([0.1, -0.2, 0.3], (len(t), 1)), np.zeros((len(t), 3))])
    tf = np.array([0.2, 0.7, 1.5])
    R = GyroTurns(rows, tf[0]).at(tf)
    want = Rotation.from_rotvec(np.outer(tf - tf[0], [0.1, -0.2, 0.3])).as_matrix()
    assert np.allclose(R, want, atol=1e-9)


# ------------------------------------------------------------------ the phase that drives the head

class _Imu:
    def __init__(self, rows):
        self._rows = rows

    def rows(self):
        return self._rows


class _Obs:
    def __init__(self, t, q, rows, image=None):
        self.t, self.q, self.imu, self.image, self.fresh_image = t, q, _Imu(rows), image, image is not None


class _Ctl:
    """The controller as the phase sees it: modes set, and the command filter's angles."""

    class _Filter:
        q = np.zeros(3)

    def __init__(self):
        self.modes = []
        self.filter = self._Filter()

    def hold(self):
        self.modes.append("hold")

    def slave(self, q):
        self.modes.append(("slave", np.asarray(q).copy()))


def test_a_head_whose_camera_is_on_its_axes_is_refused():
    from dataclasses import replace

    from kinematics.chain import radii_of_rotation
    head = reference_head()
    on_axes = replace(head, joints=tuple(replace(j, origin_m=(0.0, 0.0, 0.0)) for j in head.joints),
                      camera=replace(head.camera, origin_m=(0.0, 0.0, 0.0)))
    assert radii_of_rotation(on_axes).max() < 1e-9
    with pytest.raises(ValueError, match="no baseline"):
        HeadMotionPhase(on_axes, CAM, np.zeros(3))
    HeadMotionPhase(head, CAM, np.zeros(3))           # the reference head's camera is off its axes


def test_a_moving_wearer_is_waited_for_and_told():
    phase = HeadMotionPhase(reference_head(), CAM, np.zeros(3))
    ctl = _Ctl()
    img = np.full((CAM.height, CAM.width, 3), 100, np.uint8)
    # Turning at 20 deg/s about the camera's y axis for 3 s: the start waits, holding the head.
    for k in range(90):
        t = k / 30
        ts = t - 1 / 30 + np.arange(1, 7) / 200
        rows = np.column_stack([ts, np.tile([0.0, math.radians(20), 0.0], (6, 1)), np.tile([0, -9.81, 0], (6, 1))])
        assert phase.step(_Obs(t, np.zeros(3), rows, img), ctl) is None
    assert phase.state == "waiting" and set(ctl.modes) == {"hold"}
    assert "keep still" in phase.said[-1][1] and "20.0 deg/s" in phase.said[-1][1]
    # Still: the motion begins, towards the first corner.
    for k in range(90, 120):
        t = k / 30
        ts = t - 1 / 30 + np.arange(1, 7) / 200
        rows = np.column_stack([ts, np.zeros((6, 3)), np.tile([0, -9.81, 0], (6, 1))])
        phase.step(_Obs(t, np.zeros(3), rows, img), ctl)
    assert phase.state == "moving"
    assert np.allclose(ctl.modes[-1][1], waypoints(reference_head(), np.zeros(3), HeadMotionPlan().amplitude_rad)[0])


def _to_solving(phase, ctl, img, t0=0.0):
    """Periods of a still wearer, the head reaching each waypoint a period after it is commanded,
    until the phase asks for its solve; the next period's time."""
    for k in range(400):
        t = t0 + k / 30
        ts = t - 1 / 30 + np.arange(1, 7) / 200
        rows = np.column_stack([ts, np.zeros((6, 3)), np.tile([0, -9.81, 0], (6, 1))])
        assert phase.step(_Obs(t, np.zeros(3), rows, img), ctl) is None
        if ctl.modes and ctl.modes[-1] != "hold":
            ctl.filter.q = ctl.modes[-1][1]
        if phase.state == "solving":
            return t + 1 / 30
    raise AssertionError(f"the phase never asked for its solve (state {phase.state})")


def _fake_result():
    return SimpleNamespace(start=SimpleNamespace(xyz=np.zeros((30, 3))), baseline_m=0.012, drift_m=0.004, rms_px=0.5)


def test_the_solve_runs_beside_the_loop(monkeypatch):
    """On hardware the loop keeps its period while the start is solved, the head holding (a
    stalled loop trips the servos' bus watchdog); the start comes at the first period after the
    solve is done, made at the frame it was asked at."""
    release, blocked = threading.Event(), []

    def slow_solve(self, R_world_cam0=None, gyro_rows=None):
        if not release.wait(20):
            blocked.append(True)            # the loop waited for the solve instead of going on
        return _fake_result()

    monkeypatch.setattr(HeadMotionStart, "solve", slow_solve)
    phase, ctl = HeadMotionPhase(reference_head(), CAM, np.zeros(3), clock_waits=False), _Ctl()
    img = np.full((CAM.height, CAM.width, 3), 100, np.uint8)
    t = _to_solving(phase, ctl, img)
    t_asked = phase.solving_at
    for k in range(60):                     # two seconds of periods while the solve is out
        assert phase.step(_Obs(t + k / 30, np.zeros(3), np.zeros((0, 7)), img), ctl) is None
    assert not blocked and phase.state == "solving" and ctl.modes[-1] == "hold"
    release.set()
    r, k, give_up = None, 60, time.monotonic() + 30.0
    while r is None and time.monotonic() < give_up:        # the worker's own pace, not the loop's
        r = phase.step(_Obs(t + k / 30, np.zeros(3), np.zeros((0, 7)), img), ctl)
        k += 1
        time.sleep(0.005)
    assert r is not None and not blocked
    assert phase.frame[1] == t_asked and phase.state == "done" and phase.solving_at is None
    # The frames seen while it was solved are kept for SLAM to go through, grey, in order, and
    # at most MAX_BACKLOG of them however long the solve took.
    times = np.array([t_b for _, t_b in phase.backlog])
    assert 0 < len(times) <= MAX_BACKLOG and times[0] > t_asked and np.all(np.diff(times) > 0)
    assert phase.backlog[0][0].shape == (CAM.height, CAM.width) and phase.backlog[0][0].dtype == np.uint8


def test_on_the_twin_the_solve_is_taken_a_fixed_loop_time_later(monkeypatch):
    monkeypatch.setattr(HeadMotionStart, "solve", lambda self, R=None, rows=None: _fake_result())
    phase, ctl = HeadMotionPhase(reference_head(), CAM, np.zeros(3), clock_waits=True), _Ctl()
    img = np.full((CAM.height, CAM.width, 3), 100, np.uint8)
    t = _to_solving(phase, ctl, img)
    t_asked = phase.solving_at
    for k in range(100):
        r = phase.step(_Obs(t + k / 30, np.zeros(3), np.zeros((0, 7)), img), ctl)
        if r is not None:
            break
    assert r is not None
    assert SOLVE_DELAY_S <= t + k / 30 - t_asked < SOLVE_DELAY_S + 1 / 30 + 1e-9


def test_level_attitude_puts_gravity_down():
    R_true = Rotation.from_euler("xyz", [100, 5, -30], degrees=True).as_matrix()     # camera to world
    f_cam = R_true.T @ np.array([0, 0, 9.81])
    R = level_attitude(f_cam)
    assert np.allclose(R @ f_cam / 9.81, [0, 0, 1], atol=1e-9)
    # Heading: the optic axis's horizontal part is world x.
    z_world = R @ np.array([0, 0, 1.0])
    assert abs(z_world[1]) < 1e-9 and z_world[0] > 0
