"""--task explore: the next fixation's scoring on synthetic maps (runtime.apps.explore), and a short
closed-loop run on the twin."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics import forward_kinematics, reference_head
from kinematics.camera import DEFAULT_CAMERA
from runtime.apps.explore import (ExploreSettings, candidate_directions, choose_fixation, score_views,
                                  viewing_cone_sr)
from runtime.slam.state import State

import slam_testing as st

CAM = DEFAULT_CAMERA
HEAD = reference_head()


def _state(T_world_cam: np.ndarray, points_world: np.ndarray, sigma_pose: float = 0.01,
           sigma_point: float = 0.02) -> State:
    """A camera at ``T_world_cam`` with point features, independent Gaussian uncertainties."""
    return st.state_with_points(T_world_cam, points_world, sigma_pose, sigma_pose, sigma_point)


def _turn_y(deg: float) -> np.ndarray:
    """A camera turned about its own y (down) axis: positive looks to the image's right (+x)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0, math.radians(deg), 0]).as_matrix()
    return T


def _patch(centre: np.ndarray, n: int = 5, half: float = 0.3, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return centre + rng.uniform(-half, half, (n * n, 3))


def test_the_view_of_the_features_scores_highest_and_an_empty_view_scores_nothing():
    # Features only to the camera's right (world +x, the camera at the origin looking along +z).
    pts = _patch(np.array([2.0, 0.0, 2.0]))
    s = _state(np.eye(4), pts)
    T = np.stack([_turn_y(45.0), _turn_y(0.0), _turn_y(-45.0), _turn_y(180.0)])
    v = score_views(s, CAM, T, sigma_pixel=1.0)
    assert v.n_visible[0] == len(pts) and v.n_visible[2] == 0 and v.n_visible[3] == 0
    assert v.pose_info[0] > 1.0                       # nats: many features on a 1 cm, 0.6 deg pose
    assert v.pose_info[0] > v.pose_info[1] + 0.5      # straight ahead sees few of them, at the edge
    assert v.pose_info[2] == 0.0 and v.pose_info[3] == 0.0
    assert v.empty[2] == 1.0 and 0.0 <= v.empty[0] < 1.0


def test_pose_information_matches_a_dense_ekf_update():
    pts = _patch(np.array([0.0, 0.0, 2.0]), n=3)
    s = _state(np.eye(4), pts)
    v = score_views(s, CAM, np.eye(4)[None], sigma_pixel=2.0, margin_px=0.0)
    # The same update written out over the whole state, the pose's rotation as a world rotation vector.
    from runtime.slam.measurement import predict

    p = predict(s, np.arange(s.n_features), CAM)
    H = np.zeros((2 * s.n_features, s.n))
    for k in range(s.n_features):
        H[2 * k:2 * k + 2, :7] = p.H_c[k]
        H[2 * k:2 * k + 2, s.starts[k]:s.starts[k] + 3] = p.H_f[k][:, :3]
    S = H @ s.P @ H.T + 4.0 * np.eye(len(H))
    P_post = s.P - s.P @ H.T @ np.linalg.solve(S, H @ s.P)
    G = np.zeros((6, 7))
    G[:3, :3] = np.eye(3)
    G[3:, 4:7] = 2 * np.eye(3)                        # at q = identity, dtheta = 2 dq_vec
    want = 0.5 * (np.linalg.slogdet(G @ s.P[:7, :7] @ G.T)[1] - np.linalg.slogdet(G @ P_post[:7, :7] @ G.T)[1])
    assert v.pose_info[0] == pytest.approx(want, rel=1e-6)


def _mount_and_state(points_world: np.ndarray):
    T_world_mount = np.eye(4)
    q0 = np.zeros(3)
    T_world_cam = T_world_mount @ forward_kinematics(HEAD, q0).T_mount_cam
    return T_world_mount, q0, _state(T_world_cam, points_world)


def test_an_unreachable_candidate_is_never_chosen():
    settings = ExploreSettings(azimuth_deg=(-180.0, 160.0, 20.0), elevation_deg=(-20.0, 20.0, 20.0))
    T_wm, q0, _ = _mount_and_state(np.zeros((0, 3)))
    D = candidate_directions(HEAD, T_wm, settings)
    c = forward_kinematics(HEAD, q0).p_mount_cam
    # Features straight behind the head, out of its reach, and a few within it, off to one side.
    behind = _patch(c + 2.0 * D[1], n=6)          # D[1]: azimuth 180 deg, level
    side = _patch(c + 2.0 * D[len(D) // 2 + 6], n=2, half=0.2, seed=1)
    _, _, s = _mount_and_state(np.vstack([behind, side]))
    ch = choose_fixation(HEAD, CAM, s, T_wm, q0, 1.0, settings, map_points_world=np.vstack([behind, side]))
    assert (~ch.reachable).any() and ch.reachable.any()
    assert ch.best >= 0 and ch.reachable[ch.best]
    assert np.isneginf(ch.score[~ch.reachable]).all()
    # Scored as if reachable, the view behind would have won: the reach check is what refuses it.
    T_rel = np.stack([np.eye(4)])
    T_rel[0][:3, :3] = Rotation.from_rotvec([0, math.pi, 0]).as_matrix()
    assert score_views(s, CAM, T_rel, 1.0).pose_info[0] > ch.pose_info[ch.best]


def test_the_chosen_fixation_point_lies_at_the_maps_median_depth():
    T_wm, q0, _ = _mount_and_state(np.zeros((0, 3)))
    D = candidate_directions(HEAD, T_wm, ExploreSettings())
    c = (T_wm @ forward_kinematics(HEAD, q0).T_mount_cam)[:3, 3]
    pts = _patch(c + 1.5 * D[len(D) // 2 + 5], n=4, half=0.2)
    _, _, s = _mount_and_state(pts)
    ch = choose_fixation(HEAD, CAM, s, T_wm, q0, 1.0, map_points_world=pts)
    d = np.linalg.norm(ch.points_world - c, axis=1)
    assert np.allclose(d, np.median(np.linalg.norm(pts - c, axis=1)))
    assert ch.n_visible[ch.best] > 0 and ch.pose_info[ch.best] == ch.pose_info[ch.reachable].max()


def test_viewing_cone_of_a_known_cap():
    # Directions filling a cone of half-angle 30 deg: its solid angle 2 pi (1 - cos 30 deg).
    a = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    h = math.radians(30.0)
    ring = np.stack([np.sin(h) * np.cos(a), np.sin(h) * np.sin(a), np.full_like(a, math.cos(h))], axis=1)
    pts = np.vstack([ring * 3.0, [[0, 0, 2.0]]]) + np.array([1.0, 2.0, 3.0])
    assert viewing_cone_sr(pts, np.array([1.0, 2.0, 3.0])) == pytest.approx(2 * np.pi * (1 - math.cos(h)), rel=1e-3)
    assert viewing_cone_sr(pts[:2], np.zeros(3)) == 0.0


def test_bad_settings_are_refused_with_the_fix():
    with pytest.raises(ValueError, match="step > 0"):
        ExploreSettings(azimuth_deg=(-10.0, 10.0, 0.0))
    with pytest.raises(ValueError, match="sigma_pixel"):
        score_views(_state(np.eye(4), np.zeros((0, 3))), CAM, np.eye(4)[None], sigma_pixel=0.0)


@pytest.mark.slow
def test_explore_on_the_twin_saccades_within_the_limit_and_lands(tmp_path, monkeypatch):
    import csv
    import json
    import threading

    from runtime.apps import closed_loop
    from runtime.apps.evaluate import fixation_errors
    from runtime.sequence import read_trajectory
    from wvr.cli import main

    # The choice (about 0.7 s of CPU) is made beside the control loop, never on its thread.
    threads = []

    def choose(*a, **k):
        threads.append(threading.current_thread() is threading.main_thread())
        return choose_fixation(*a, **k)

    monkeypatch.setattr(closed_loop, "choose_fixation", choose)
    out = tmp_path / "run"
    code = main(["sim", "run", "--scenario", "office-far-target", "--task", "explore", "--seconds", "6", "--seed", "1",
                 "--out", str(out), "--no-session-log"])
    assert code == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["ended"] == "complete" and s["lost_frames"] == 0
    chosen = [e for e in s["events"] if e["event"] == "explore"]
    assert len(chosen) >= 2 and all(np.isfinite(e["score"]) for e in chosen)
    assert threads and not any(threads)
    # Acted on CHOICE_DELAY_S after the snapshot: the first choice waits that long after the start.
    assert chosen[0]["t"] >= closed_loop.CHOICE_DELAY_S - 1e-9
    assert len({tuple(np.round(e["target"], 3)) for e in chosen}) == len(chosen)     # each a new place
    assert sum(e["event"] == "landed" for e in s["events"]) >= 2
    with open(out / "joints.csv") as fh:
        rows = list(csv.DictReader(fh))
    rates = np.array([[float(r[f"cmd_rate_{n}"]) for n in ("elevation", "pan", "cyclotorsion")] for r in rows])
    assert np.abs(rates).max() <= math.radians(30) + 1e-9
    # The true optic axis reaches each chosen point: at each landing, within 3 degrees of it.
    gt = read_trajectory(out / "groundtruth.txt")
    targets = np.array([[float(r[f"target_{a}"]) for a in "xyz"] for r in rows])
    err = np.degrees(fixation_errors(gt.T_world_cam(), targets))
    landed = [int(np.argmin(np.abs(gt.t - e["t"]))) for e in s["events"] if e["event"] == "landed"]
    assert err[landed].max() < 3.0
    assert read_trajectory(out / "trajectory.tum").t.size > 150


def test_explore_task_needs_no_target_and_dwells_1_5_s_by_default():
    from runtime.apps.closed_loop import Task

    t = Task("explore")
    assert t.uses_slam and t.dwell_s == 1.5 and t.targets.shape == (0, 3)
    assert Task("saccade", np.eye(3), ).dwell_s == 2.0 and Task("explore", dwell_s=0.5).dwell_s == 0.5
    with pytest.raises(ValueError, match="dwell_s"):
        Task("explore", dwell_s=0.0)


def test_a_view_beyond_reach_comes_with_the_turn_that_brings_it_within():
    from runtime.apps.explore import choose_beyond_reach

    settings = ExploreSettings()
    T_wm, q0, _ = _mount_and_state(np.zeros((0, 3)))
    c = forward_kinematics(HEAD, q0).p_mount_cam
    D = candidate_directions(HEAD, T_wm, ExploreSettings(azimuth_deg=(-180.0, 160.0, 20.0),
                                                         elevation_deg=(0.0, 0.0, 20.0)))
    behind = _patch(c + 2.0 * D[0], n=5, half=0.2)        # azimuth -180 deg: straight behind
    _, _, s = _mount_and_state(behind)
    b = choose_beyond_reach(HEAD, CAM, s, T_wm, q0, 1.0, settings, map_points_world=behind)
    assert b is not None and b.prompt.kind == "turn" and abs(b.prompt.turn_rad) > math.radians(60)
    assert b.score > 1.0                                  # the turned view sees the features
    # Within reach the same map gives nothing: the request is what would find it.
    ch = choose_fixation(HEAD, CAM, s, T_wm, q0, 1.0, settings, map_points_world=behind)
    assert np.max(ch.pose_info) == 0.0
    # The point asked for is reachable from the turned mount, and not from this one.
    from runtime.gaze.estimate import ik_point

    from runtime.gaze.prompts import turned_mount

    T_turned = turned_mount(T_wm, b.prompt.turn_rad)
    assert ik_point(HEAD, b.point_world, T_turned, q0).reachable and not ik_point(HEAD, b.point_world, T_wm, q0).reachable
    # Features all within reach: nothing beyond it beats them (no turned view sees them).
    ahead = _patch(c + 2.0 * D[9], n=4, half=0.2)         # azimuth 0
    _, _, s2 = _mount_and_state(ahead)
    b2 = choose_beyond_reach(HEAD, CAM, s2, T_wm, q0, 1.0, settings, map_points_world=ahead)
    assert b2 is None or b2.score < 0.5


def test_explore_asks_the_wearer_to_turn_back_to_the_map_and_the_twin_obeys(tmp_path, monkeypatch):
    """turn-away-ask: the wearer turns 120 deg away from the mapped bench at 4 s; explore finds
    the best view beyond the head's reach, asks the wearer to turn, the twin's wearer obeys, and
    the map's uncertainty is noted at the request and after it (4 s after, not 6, to keep the
    run short: the turn takes about 3 s)."""
    import json

    from runtime.apps import closed_loop
    from runtime.apps.closed_loop import Task
    from wvr.assemble import make_twin, run_on_twin

    ASK_AFTER_S = 4.0
    monkeypatch.setattr(closed_loop, "ASK_AFTER_S", ASK_AFTER_S)
    twin = make_twin()
    try:
        s = run_on_twin(twin, "turn-away-ask", Task("explore"), tmp_path / "run", seconds=17, seed=1,
                        progress=False, session_log=False)
        turns = list(twin._turns)
    finally:
        twin.close()
    ev = s["events"]
    asks = [e for e in ev if e["event"] == "ask-turn"]
    assert asks, "no request to turn"
    a = asks[0]
    assert a["score"] > a["best_within_reach"] + ExploreSettings().ask_margin_nats
    assert a["turn_deg"] < 0                          # back towards the bench: the wearer turned left
    obeyed = [e for e in ev if e["event"] == "wearer-obeys" and e["text"] == a["text"]]
    assert obeyed and any(abs(math.degrees(psi) - a["turn_deg"]) < 1e-9 for _, _, psi, _ in turns)
    after = [e for e in ev if e["event"] == "after-turn"]
    assert after and after[0]["t"] - a["t"] >= ASK_AFTER_S - 1e-9
    for k in ("pose_sigma_m", "point_sigma_m", "map_cone_sr"):
        assert np.isfinite(a[k]) and np.isfinite(after[0][k])
    assert after[0]["pose_sigma_m"] < a["pose_sigma_m"] and after[0]["point_sigma_m"] < a["point_sigma_m"]
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["lost_frames"] == 0
