"""Glances during a fixation (runtime.apps.glances): the weak direction, the view that observes it
best on synthetic maps, and the schedule's phases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics import forward_kinematics, reference_head
from kinematics.camera import DEFAULT_CAMERA
from runtime.apps.explore import ExploreSettings, candidate_directions, score_views
from runtime.apps.glances import GlanceSchedule, GlanceSettings, choose_glance, weakest_direction

import slam_testing as st

CAM = DEFAULT_CAMERA
HEAD = reference_head()


def _state(T_world_cam: np.ndarray, points_world: np.ndarray, sigma_xyz=(0.01, 0.01, 0.01),
           sigma_rot: float = 0.002, sigma_point: float = 0.005):
    return st.state_with_points(T_world_cam, points_world, sigma_xyz, sigma_rot, sigma_point)


def _turn_y(deg: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0, math.radians(deg), 0]).as_matrix()
    return T


def _patch(centre, n=5, half=0.3, seed=0) -> np.ndarray:
    return np.asarray(centre, float) + np.random.default_rng(seed).uniform(-half, half, (n * n, 3))


def test_weakest_direction_is_the_largest_eigenvector():
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    P = R @ np.diag([0.002**2, 0.03**2, 0.001**2]) @ R.T
    sigma, v = weakest_direction(P)
    assert sigma == pytest.approx(0.03)
    assert abs(v @ R[:, 1]) == pytest.approx(1.0)


def test_information_along_a_direction_matches_a_dense_ekf_update():
    pts = _patch([0.0, 0.0, 2.0], n=3)
    s = _state(np.eye(4), pts, sigma_xyz=(0.03, 0.01, 0.02))
    w = np.array([0.6, 0.0, 0.8, 0.0, 0.0, 0.0])
    v = score_views(s, CAM, np.eye(4)[None], sigma_pixel=1.5, margin_px=0.0, direction=w)
    from runtime.slam.measurement import predict

    p = predict(s, np.arange(s.n_features), CAM)
    H = np.zeros((2 * s.n_features, s.n))
    for k in range(s.n_features):
        H[2 * k:2 * k + 2, :7] = p.H_c[k]
        H[2 * k:2 * k + 2, s.starts[k]:s.starts[k] + 3] = p.H_f[k][:, :3]
    S = H @ s.P @ H.T + 1.5**2 * np.eye(len(H))
    P_post = s.P - s.P @ H.T @ np.linalg.solve(S, H @ s.P)
    u = w[:3]                                          # position only: the rotation's part of w is 0
    want = 0.5 * math.log((u @ s.P[:3, :3] @ u) / (u @ P_post[:3, :3] @ u))
    assert v.along[0] == pytest.approx(want, rel=1e-6)
    assert want > 0.1
    # No direction asked: zeros, and the other scores unchanged.
    v0 = score_views(s, CAM, np.eye(4)[None], sigma_pixel=1.5, margin_px=0.0)
    assert v0.along[0] == 0.0 and v0.pose_info[0] == v.pose_info[0]


def test_a_lateral_uncertainty_is_best_observed_looking_across_it():
    # Features ahead (+z) and to the right (+x). The camera's x is observed by the features ahead
    # (a sideways shift moves them across the image), barely by those along x (it changes their
    # depth, seen through a small patch's small spread of depths); and the other way round for z.
    pts = np.vstack([_patch([0.0, 0.0, 2.0], n=4, half=0.1, seed=1), _patch([2.0, 0.0, 0.0], n=4, half=0.1, seed=2)])
    s = _state(np.eye(4), pts, sigma_xyz=(0.03, 0.03, 0.03))
    T = np.stack([_turn_y(0.0), _turn_y(90.0)])        # looking along +z, along +x
    ex = np.array([1.0, 0, 0, 0, 0, 0])
    ez = np.array([0, 0, 1.0, 0, 0, 0])
    along_x = score_views(s, CAM, T, 1.0, direction=ex).along
    along_z = score_views(s, CAM, T, 1.0, direction=ez).along
    assert along_x[0] > 2 * along_x[1]
    assert along_z[1] > 2 * along_z[0]


def test_the_glance_goes_where_the_weak_direction_is_observed_and_nowhere_without_gain():
    T_wm, q0 = np.eye(4), np.zeros(3)
    settings = GlanceSettings(views=ExploreSettings(azimuth_deg=(-80.0, 80.0, 20.0), elevation_deg=(0.0, 0.0, 20.0)))
    T_world_cam = T_wm @ forward_kinematics(HEAD, q0).T_mount_cam
    c = T_world_cam[:3, 3]
    D = candidate_directions(HEAD, T_wm, settings.views)
    left, right = D[0], D[-1]                          # azimuth -80 and +80 deg, level
    pts = np.vstack([_patch(c + 2.0 * left, n=4, half=0.2, seed=3), _patch(c + 2.0 * right, n=4, half=0.2, seed=4)])
    s = _state(T_world_cam, pts, sigma_xyz=(0.02, 0.02, 0.02))
    # Weak along the left view's line of sight (nearly the right view's too: 160 deg apart): the
    # glance is a reachable view that sees features and brings the most information along it.
    ch = choose_glance(HEAD, CAM, s, T_wm, q0, 1.0, left, settings, map_points_world=pts)
    assert ch.best >= 0 and ch.reachable[ch.best] and ch.score[ch.best] >= settings.min_gain_nats
    assert ch.n_visible[ch.best] > 0
    assert ch.score[ch.best] == pytest.approx(np.max(ch.score[np.isfinite(ch.score)]))
    # Up, across both lines of sight, is observed better than along them (features shift across
    # the image rather than change depth).
    up = np.cross(left, right)
    up /= np.linalg.norm(up)
    ch_up = choose_glance(HEAD, CAM, s, T_wm, q0, 1.0, up, settings, map_points_world=pts)
    assert ch_up.score[ch_up.best] > ch.score[ch.best]
    # A map with nothing to see brings no gain: no glance.
    empty = _state(T_world_cam, np.zeros((0, 3)))
    assert choose_glance(HEAD, CAM, empty, T_wm, q0, 1.0, left, settings).best == -1


def test_the_schedule_goes_out_dwells_comes_back_and_waits():
    g = GlanceSchedule(GlanceSettings(bound_m=0.01, min_interval_s=4.0, dwell_s=0.5, give_up_s=1.5))
    assert not g.due(0.0, 0.005) and g.due(0.0, 0.02)
    g.begin(0.0, np.array([1.0, 0, 0]))
    assert g.phase == "out" and g.away and not g.due(0.1, 0.05)
    assert g.step(0.4) is None
    g.landed(0.4)
    assert g.phase == "at" and g.step(0.8) is None
    assert g.step(0.9) == "return" and g.phase == "back"
    assert g.step(1.0) is None
    g.landed(1.2)
    assert g.phase == "fixating" and not g.away and g.point is None
    assert not g.due(5.1, 0.05) and g.due(5.2, 0.05)    # min_interval_s after it ended at 1.2 s
    # A saccade out that never lands comes back after give_up_s, and one back that never lands
    # gives the target to the task's fixation after give_up_s again.
    g.begin(6.0, np.zeros(3))
    assert g.step(7.4) is None and g.step(7.5) == "return"
    assert g.step(8.9) is None and g.step(9.0) == "resume" and g.phase == "fixating"
    assert g.count == 2


def test_bad_glance_settings_are_refused_with_the_bound():
    with pytest.raises(ValueError, match="bound_m"):
        GlanceSettings(bound_m=0.0)
    with pytest.raises(ValueError, match="min_interval_s"):
        GlanceSettings(min_interval_s=float("nan"))


def test_glances_on_the_twin_leave_the_target_land_come_back_and_are_scored_apart(tmp_path, monkeypatch):
    import csv
    import json

    import runtime.apps.closed_loop as closed_loop
    from runtime.apps.evaluate import fixation_errors
    from runtime.sequence import read_trajectory
    from wvr.cli import main

    # A bound every pose passes and no floor on the gain: the glances' path runs whatever the map.
    monkeypatch.setattr(closed_loop, "GlanceSettings",
                        lambda: GlanceSettings(bound_m=1e-4, min_gain_nats=0.0, min_interval_s=1.0))
    out = tmp_path / "run"
    code = main(["sim", "run", "--scenario", "office-static", "--task", "fixate", "--glances", "--seconds", "7",
                 "--seed", "1", "--out", str(out), "--no-session-log"])
    assert code == 0
    s = json.loads((out / "summary.json").read_text())
    ev = s["events"]
    out_ev = [e for e in ev if e["event"] == "glance"]
    end_ev = [e for e in ev if e["event"] == "glance-end"]
    assert len(out_ev) >= 2 and len(end_ev) >= 1 and s["glances"] == len(out_ev)
    assert all(e["gain_nats"] > 0 and e["sigma_m"] > 1e-4 for e in out_ev)
    assert s["glance_interval_s"] >= 1.0 and s["glance_away_s"] > 0.5
    with open(out / "joints.csv") as fh:
        rows = list(csv.DictReader(fh))
    targets = np.array([[float(r[f"target_{a}"]) for a in "xyz"] for r in rows])
    gt = read_trajectory(out / "groundtruth.txt")
    err = np.degrees(fixation_errors(gt.T_world_cam(), targets))
    # The head reached each glance's view: landed within 3 deg of it, far from the task's target.
    task_target = targets[0]
    for e in out_ev[:-1]:
        k = [int(np.argmin(np.abs(gt.t - x["t"]))) for x in ev if x["event"] == "landed" and x["t"] > e["t"]][0]
        assert err[k] < 3.0
        assert np.degrees(fixation_errors(gt.T_world_cam()[k:k + 1], task_target[None]))[0] > 5.0
    # Outside the glances the fixation is held as without them.
    assert s["fixation_rms_deg"] < 1.0
