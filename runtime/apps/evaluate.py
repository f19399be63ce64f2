"""Scoring a closed-loop run against truth, where a robot offers it (the twin): fixation error,
attitude held, SLAM's ATE, the tracker's and the servo's pixel errors. Never on the control
path: it reads the loop's log and the truth logged beside it after the run."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from kinematics.camera import CameraIntrinsics, project, unproject

from ..sequence import Trajectory
from ..eval import trajectory_errors


def fixation_errors(T_world_cam: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    """(n,) radians between each optic axis and the direction from its centre to ``p_world`` (n, 3)."""
    d = p_world - T_world_cam[:, :3, 3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.arccos(np.clip(np.einsum("ij,ij->i", T_world_cam[:, :3, 2], d), -1.0, 1.0))


def pitch_roll(R_world_cam: np.ndarray) -> np.ndarray:
    """(n, 2) radians: the optic axis's elevation above the horizontal and the image's roll (the
    angle of optical x out of the horizontal plane), for (n, 3, 3) camera-to-world rotations."""
    z, x = R_world_cam[:, :, 2], R_world_cam[:, :, 0]
    return np.column_stack([np.arcsin(np.clip(z[:, 2], -1, 1)), np.arcsin(np.clip(x[:, 2], -1, 1))])


def region_on_plane(camera: CameraIntrinsics, T_world_cam: np.ndarray, uv: np.ndarray,
                    plane_points: np.ndarray) -> np.ndarray:
    """(4, 3) world points where the rays of pixels ``uv`` (4, 2) meet the plane through
    ``plane_points`` (>= 3, 3): the true place of a region selected in an image."""
    c = plane_points.mean(axis=0)
    n = np.cross(plane_points[1] - plane_points[0], plane_points[2] - plane_points[0])
    n /= np.linalg.norm(n)
    rays = unproject(camera, uv) @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    s = ((c - o) @ n) / (rays @ n)
    return o + s[:, None] * rays


def _diagonals_meet(quads: np.ndarray) -> np.ndarray:
    """(n, 2) where the diagonals of each quadrilateral (n, 4, 2) cross: the image of the centre
    of the planar rectangle it shows (a projective invariant, unlike the corners' mean)."""
    h = np.concatenate([quads, np.ones(quads.shape[:2] + (1,))], axis=2)
    p = np.cross(np.cross(h[:, 0], h[:, 2]), np.cross(h[:, 1], h[:, 3]))
    return p[:, :2] / p[:, 2:3]


def write_tracking(out: Path, log, truth_uv: np.ndarray | None) -> None:
    """tracking.csv: the tracker's polygon per period, lost flag, and (with truth) the true corners."""
    with open(out / "tracking.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        head = ["t", *[f"{a}{k}" for k in range(4) for a in ("x", "y")], "lost"]
        if truth_uv is not None:
            head += [f"true_{a}{k}" for k in range(4) for a in ("x", "y")]
        w.writerow(head)
        for j, r in enumerate(log.rows):
            row = [r.t, *r.polygon.ravel(), int(r.track_lost)]
            if truth_uv is not None:
                row += list(truth_uv[j].ravel())
            w.writerow(row)


def _track_scores(out: Path, log, T_true, landmarks, camera, region_uv) -> dict:
    """The tracker's corner error against where the selected region truly is, and the servo's
    error: the region's true centre against the image centre after the first second."""
    world = region_on_plane(camera, T_true[0], region_uv, landmarks["target_corners"])
    truth_uv = np.array([project(camera, (world - T[:3, 3]) @ T[:3, :3]) for T in T_true])
    write_tracking(out, log, truth_uv)
    times = log.times
    poly = np.array([r.polygon for r in log.rows])
    lost = np.array([r.track_lost for r in log.rows])
    after = times >= times[0] + 1.0
    centre_err = np.linalg.norm(_diagonals_meet(truth_uv) - [camera.cx, camera.cy], axis=1)
    ok = after & ~lost & np.isfinite(poly).all(axis=(1, 2))
    corner_err = np.linalg.norm(poly - truth_uv, axis=2)
    return {"track_lost_frames": int(lost.sum()),
            "servo_centre_rms_px": float(np.sqrt(np.mean(centre_err[after] ** 2))) if after.any() else float("nan"),
            "servo_centre_max_px": float(centre_err[after].max()) if after.any() else float("nan"),
            "tracker_corner_rms_px": float(np.sqrt(np.mean(corner_err[ok] ** 2))) if ok.any() else float("nan")}


def _landings(times, err_deg, events) -> list[dict]:
    """Per saccade: when it landed (the controller's own estimate said so) and the true error
    then and over the next 0.3 s."""
    out = []
    sacc = [e for e in events if e["event"] == "saccade"]
    lands = [e for e in events if e["event"] == "landed"]
    for k, s in enumerate(sacc):
        end = sacc[k + 1]["t"] if k + 1 < len(sacc) else times[-1] + 1
        land = next((e for e in lands if s["t"] <= e["t"] < end), None)
        rec = {"target": s["target"], "start_s": s["t"], "landed": land is not None}
        if land is not None:
            j = int(np.searchsorted(times, land["t"]))
            win = (times >= land["t"]) & (times < min(land["t"] + 0.3, end))
            rec.update(duration_s=land["t"] - s["t"], error_deg=float(err_deg[j]),
                       error_after_deg=float(np.max(err_deg[win])))
        out.append(rec)
    return out


def _glance_windows(times: np.ndarray, events: list[dict]) -> tuple[np.ndarray, dict]:
    """The periods (n,) a fixation task spent away on glances (from each ``glance`` event to its
    ``glance-end``, or the run's end), and the glances' figures: how many, the time between
    their starts (median, s) and the time away in all (s)."""
    away = np.zeros(len(times), bool)
    starts = {e["index"]: e["t"] for e in events if e["event"] == "glance"}
    ends = {e["index"]: e["t"] for e in events if e["event"] == "glance-end"}
    for k, t0 in starts.items():
        away |= (times >= t0) & (times <= ends.get(k, np.inf))
    t_starts = np.sort(np.array(list(starts.values()), float))
    gaps = np.diff(t_starts)
    dt = float(np.median(np.diff(times))) if len(times) > 1 else 0.0
    return away, {"glances": len(starts), "glance_interval_s": float(np.median(gaps)) if len(gaps) else None,
                  "glance_away_s": float(away.sum() * dt)}


def start_map_scale(start, depth: np.ndarray) -> dict:
    """The scale of a start's map against the true depth image (H, W) m along the optic axis at
    its frame: each point's depth along the start camera's optic axis over the true depth at its
    pixel (where the truth has one); the median less one is the scale's error."""
    T = np.asarray(start.T_world_cam, float)
    z_est = (np.asarray(start.xyz, float) - T[:3, 3]) @ T[:3, 2]
    uv = np.round(np.asarray(start.uv, float)).astype(int)
    h, w = depth.shape
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    z_true = np.full(len(uv), np.nan)
    z_true[ok] = depth[uv[ok, 1], uv[ok, 0]]
    ok &= np.isfinite(z_true) & (z_true > 0)
    if not ok.any():
        return {}
    ratio = z_est[ok] / z_true[ok]
    return {"start_map_scale_error": float(np.median(ratio) - 1.0), "start_map_points": int(ok.sum())}


def _head_motion_scores(times: np.ndarray, T_est: np.ndarray, T_true: np.ndarray) -> dict:
    """A head-motion start's scores over the frames SLAM gave poses (it starts after the motion):
    the ATE with the estimate put on the truth by the start frame's pose alone (no fitted
    alignment, so the scale and the levelling count), and the similarity's scale over the run
    (truth units per estimate unit: 1 is metric). ``T_true_est`` : (4, 4) that start-frame
    alignment, for mapping the task's targets."""
    ok = np.isfinite(T_est).all(axis=(1, 2))
    if ok.sum() < 2:
        return {"slam_started": bool(ok.any())}
    k = int(np.argmax(ok))
    A = T_true[k] @ np.linalg.inv(T_est[k])
    T_on = A[None] @ T_est[ok]
    err = np.linalg.norm(T_on[:, :3, 3] - T_true[ok, :3, 3], axis=1)
    e = trajectory_errors(Trajectory.from_T_world_cam(times[ok], T_est[ok]),
                          Trajectory.from_T_world_cam(times[ok], T_true[ok]))
    return {"slam_started": True, "slam_start_s": float(times[k] - times[0]),
            "ate_rmse_m": float(np.sqrt(np.mean(err**2))), "ate_max_m": float(err.max()),
            "ate_sim3_rmse_m": e.ate_sim3_rmse_m, "scale_error": float(e.sim3_scale - 1.0), "T_true_est": A.tolist()}


def evaluate(log, T_true: np.ndarray, landmarks: dict, task, camera: CameraIntrinsics,
             region_uv: np.ndarray | None, out: Path) -> dict:
    """The run's scores against the truth logged beside each period (T_true (n, 4, 4))."""
    s: dict = {}
    times = log.times
    after = times >= times[0] + 1.0
    targets = log.column("target") if task.kind in ("fixate", "saccade") else None
    T_est = np.array([r.T_est for r in log.rows])
    if task.start == "head-motion":
        s.update(_head_motion_scores(times, T_est, T_true))
        if log.task_t0 is not None:
            s["task_start_s"] = float(log.task_t0 - times[0])
        A = s.pop("T_true_est", None)
        if targets is not None and A is not None:
            # The targets are in the start's world: the truth's through the start-frame alignment.
            A = np.asarray(A)
            targets = targets @ A[:3, :3].T + A[:3, 3]
    elif np.isfinite(T_est).any():
        # Every task runs SLAM where it can start (observed only in stabilise, body and track).
        e = trajectory_errors(Trajectory.from_T_world_cam(times, T_est), Trajectory.from_T_world_cam(times, T_true))
        s.update(ate_rmse_m=e.ate_rmse_m, ate_max_m=e.ate_max_m)
    if task.kind in ("fixate", "saccade"):
        err = np.degrees(fixation_errors(T_true, targets))
        s["fixation_error_deg"] = err.tolist()
        if task.start == "head-motion":
            # A head-motion start: scored from a second after the task began (SLAM caught up).
            t0 = log.task_t0 if log.task_t0 is not None else np.inf
            after = after & (times >= t0 + 1.0) & np.isfinite(err)
        if getattr(task, "glances", False):
            # The fixation's error is scored outside the glances (from leaving to landing back).
            away, g = _glance_windows(times, log.events)
            after = after & ~away
            s.update(g)
        if task.kind == "fixate" and after.any():
            s.update(fixation_rms_deg=float(np.sqrt(np.mean(err[after] ** 2))), fixation_peak_deg=float(err[after].max()))
        if task.kind == "saccade":
            s["landings"] = _landings(times, err, log.events)
    if task.kind in ("stabilise", "body") and s.get("slam_started", True):
        # The attitude held is the one at the task's start (after a head-motion start's motion).
        k0 = int(np.searchsorted(times, log.task_t0 - 1e-9)) if log.task_t0 is not None else 0
        pr = np.degrees(pitch_roll(T_true[:, :3, :3]))
        dev = np.abs(pr[k0:] - pr[k0])
        s.update(pitch_max_dev_deg=float(dev[:, 0].max()), roll_max_dev_deg=float(dev[:, 1].max()),
                 pitch_rms_dev_deg=float(np.sqrt(np.mean(dev[:, 0] ** 2))),
                 roll_rms_dev_deg=float(np.sqrt(np.mean(dev[:, 1] ** 2))))
        s["pitch_roll_deg"] = pr.tolist()
    if task.kind == "track" and region_uv is not None:
        s.update(_track_scores(out, log, T_true, landmarks, camera, region_uv))
    return s
