"""The closed loop: twin, SLAM and gaze controller together (``wvr sim run``).

The controller sees only what a real wearable gives it: the image (through SLAM), the IMU
samples and the encoder angles. Ground truth is read only to write ``groundtruth.txt`` and to
score the run (fixation error, attitude held, ATE).

Tasks
-----
``fixate``   hold the optic axis on the first target for the whole run.
``saccade``  saccade through the targets in turn, ``dwell_s`` on each (cycling), fixating in between.
``stabilise`` Path A: hold the camera's starting attitude from the IMU alone (no vision).
``body``     Path B: hold the starting gaze direction relative to the wearer's body.
``track``    keep a 2D tracker's target centred (the known rectangle by default), the tracker
             (hyperplane or mean shift, runtime.vision2d) seeing only the images.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from kinematics import JOINT_NAMES
from kinematics.tomlfile import read_toml

from ..gaze import ControllerSettings, GazeController, GazeRefused
from ..sequence import Trajectory, write_trajectory
from ..slam.eval import trajectory_errors
from ..slam.system import MonoSLAM
from ..vision2d.track import METHODS as TRACK_METHODS
from ..vision2d.track import make_tracker
from .recorder import target_in_first_frame
from .scenarios import TASKS
from .twin import Twin


@dataclass(frozen=True)
class Task:
    """kind : one of :data:`TASKS`. targets : (n, 3) world points, m (fixate, saccade).
    dwell_s : time on each saccade target before the next."""

    kind: str
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    dwell_s: float = 2.0
    region: tuple | None = None       # track: (x, y, w, h) pixels in the first frame (default: the rectangle)
    method: str = "hyperplane"        # track: "hyperplane" or "meanshift"

    def __post_init__(self):
        if self.kind not in TASKS:
            raise ValueError(f"task {self.kind!r} unknown; choose one of {', '.join(TASKS)}")
        t = np.asarray(self.targets, float).reshape(-1, 3)
        if not np.isfinite(t).all():
            raise ValueError("task targets must be finite world points (x, y, z) m")
        if self.kind in ("fixate", "saccade") and len(t) == 0:
            raise ValueError(f"task {self.kind} needs a target: give --target X,Y,Z or --targets FILE")
        if self.kind == "saccade" and len(t) < 2:
            raise ValueError("task saccade needs at least two targets (--targets FILE)")
        if self.method not in TRACK_METHODS:
            raise ValueError(f"track method {self.method!r}: use one of {', '.join(TRACK_METHODS)}")
        if not self.dwell_s > 0:
            raise ValueError(f"dwell_s = {self.dwell_s} must be positive")
        object.__setattr__(self, "targets", t)


def load_targets(path: str | Path) -> tuple[np.ndarray, float | None]:
    """A targets file: TOML with ``targets = [[x, y, z], ...]`` (world, m) and optional ``dwell_s``."""
    d = read_toml(path, ValueError, "a targets TOML file (targets = [[x, y, z], ...])")
    if "targets" not in d:
        raise ValueError(f"{path}: no 'targets' list; write targets = [[x, y, z], ...] in metres, world frame")
    t = np.asarray(d["targets"], float)
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"{path}: 'targets' must be a list of [x, y, z] triples, got shape {t.shape}")
    return t, d.get("dwell_s")


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


def run_closed_loop(twin: Twin, scenario, task: Task, out: str | Path, seconds: float | None = None, seed: int = 0,
                    settings: ControllerSettings = ControllerSettings(), progress: bool = True,
                    pose_source: str = "slam") -> dict:
    """Run the loop; write the files of ``wvr sim run`` into ``out``; return the summary.

    ``pose_source="truth"`` hands the controller the true camera pose instead of SLAM's: a
    diagnostic that separates the controller's own error from SLAM's, never a mode of use."""
    if pose_source not in ("slam", "truth"):
        raise ValueError(f"pose_source {pose_source!r}: use 'slam' (the controller's input) or 'truth' (diagnostic)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    obs = twin.reset(scenario, seed=seed, seconds=seconds)
    n_frames = int(round(twin.seconds * twin.frame_rate))
    dt = 1.0 / twin.frame_rate
    use_slam = task.kind in ("fixate", "saccade")
    slam = None
    if use_slam:
        slam = MonoSLAM(twin.camera)
        slam.start(obs.image, obs.t, target_in_first_frame(twin))
    ctl = GazeController(twin.head, twin.camera, obs.encoders, dt, settings)
    tracker, track_rows = None, []
    if task.kind == "track":
        tracker = _make_tracker(task, obs.image, _true_corners(twin, twin.ground_truth.T_world_cam))
    rows, gt_T, est_T, times, refusals, events = [], [], [], [], [], []
    current = 0
    q_meas_prev = obs.encoders.copy()

    def set_mode(i: int, t: float) -> None:
        try:
            if task.kind == "fixate":
                ctl.fixate(task.targets[i])
            elif task.kind == "saccade":
                ctl.saccade(task.targets[i])
                events.append({"t": t, "event": "saccade", "target": i})
        except GazeRefused as e:
            refusals.append({"t": t, "target": i, "reason": str(e)})

    for i in tqdm(range(n_frames), desc=f"closed loop {task.kind} ({twin.scenario.name})", unit="frame",
                  disable=not progress):
        gt = twin.ground_truth
        T_est = slam.T_world_cam() if slam is not None and not (slam.stats and slam.stats[-1].lost) else None
        v_est = slam.state.v.copy() if T_est is not None else None
        if pose_source == "truth" and slam is not None:
            T_est, v_est = gt.T_world_cam, None
        if i == 1:
            # The first IMU rows arrive with the first step, and the mount's pose is known once
            # the controller has stepped once: the task starts then.
            if task.kind == "stabilise":
                ctl.attitude.update(obs.imu)
                obs = obs.__class__(obs.t, obs.image, np.zeros((0, 7)), obs.encoders)
                ctl.stabilise()
            elif task.kind == "body":
                ctl.body()
            else:
                set_mode(0, obs.t)
        if task.kind == "saccade" and i > 1 and obs.t >= (current + 1) * task.dwell_s:
            current += 1
            set_mode(current % len(task.targets), obs.t)
        if tracker is not None:
            res = tracker.track(obs.image) if i else None
            if res is not None and not res.lost:
                ctl.track(res.centre)
            elif res is not None:
                ctl.hold()                # a lost target is said (tracking.csv), not chased
            true_uv = _true_corners(twin, gt.T_world_cam)
            poly = res.polygon if res is not None else np.full((4, 2), np.nan)
            track_rows.append([obs.t, *poly.ravel(), int(res.lost) if res is not None else 0, *true_uv.ravel()])
        cmd = ctl.step(obs.t, obs.imu, obs.encoders, T_world_cam=T_est, v_world=v_est)
        if cmd.landed:
            events.append({"t": obs.t, "event": "landed", "target": current % len(task.targets)})
        times.append(obs.t)
        gt_T.append(gt.T_world_cam)
        est_T.append(slam.T_world_cam() if slam is not None else np.full((4, 4), np.nan))
        qd_meas = (obs.encoders - q_meas_prev) / dt if i else np.zeros(3)
        q_meas_prev = obs.encoders.copy()
        tgt = task.targets[current % len(task.targets)] if len(task.targets) else np.full(3, np.nan)
        rows.append([obs.t, *cmd.q, *obs.encoders, *cmd.qd, *qd_meas, cmd.mode, *tgt,
                     math.degrees(cmd.error_rad) if np.isfinite(cmd.error_rad) else float("nan")])
        if i == n_frames - 1:
            break
        obs = twin.step(cmd.q)
        if slam is not None:
            slam.process(obs.image, obs.t, imu=obs.imu)

    times = np.array(times)
    gt_T = np.array(gt_T)
    write_trajectory(out / "groundtruth.txt", times, gt_T, header="true camera-to-world poses (optical frame)")
    summary = {"scenario": twin.scenario.name, "task": task.kind, "pose_source": pose_source, "seconds": float(times[-1]), "frames": len(times),
               "motion_limit_deg_s": math.degrees(settings.motion_limit_rad_s), "refusals": refusals,
               "events": events, "prompts": len(ctl.prompts)}
    if slam is not None:
        est_T = np.array(est_T)
        write_trajectory(out / "trajectory.tum", times, est_T, header="SLAM camera-to-world poses during the loop")
        e = trajectory_errors(Trajectory.from_T_world_cam(times, est_T), Trajectory.from_T_world_cam(times, gt_T))
        summary.update(ate_rmse_m=e.ate_rmse_m, ate_max_m=e.ate_max_m,
                       lost_frames=sum(1 for s in slam.stats if s.lost))
        (out / "slam_stats.json").write_text(json.dumps({"frames": [asdict(s) for s in slam.stats]}, indent=0))
    with open(out / "joints.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", *[f"cmd_{n}" for n in JOINT_NAMES], *[f"meas_{n}" for n in JOINT_NAMES],
                    *[f"cmd_rate_{n}" for n in JOINT_NAMES], *[f"meas_rate_{n}" for n in JOINT_NAMES], "mode",
                    "target_x", "target_y", "target_z", "est_error_deg"])
        w.writerows(rows)
    with open(out / "prompts.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "kind", "turn_deg", "step_m", "text"])
        for t, p in ctl.prompts:
            w.writerow([f"{t:.3f}", p.kind, f"{math.degrees(p.turn_rad):.1f}", f"{p.step_m:.2f}", p.text])
    cmd_rate = np.array([r[7:10] for r in rows], float)
    meas_rate = np.array([r[10:13] for r in rows], float)
    summary["peak_cmd_rate_deg_s"] = float(np.degrees(np.abs(cmd_rate).max()))
    summary["peak_meas_rate_deg_s"] = float(np.degrees(np.abs(meas_rate[1:]).max())) if len(rows) > 1 else 0.0
    after = times >= times[0] + 1.0
    if task.kind in ("fixate", "saccade"):
        targets = np.array([r[14:17] for r in rows], float)
        err = np.degrees(fixation_errors(gt_T, targets))
        summary["fixation_error_deg"] = err.tolist()
        if task.kind == "fixate" and after.any():
            summary.update(fixation_rms_deg=float(np.sqrt(np.mean(err[after] ** 2))),
                           fixation_peak_deg=float(err[after].max()))
        if task.kind == "saccade":
            summary["landings"] = _landings(times, err, events, task)
    if task.kind in ("stabilise", "body"):
        pr = np.degrees(pitch_roll(gt_T[:, :3, :3]))
        dev = np.abs(pr - pr[0])
        summary.update(pitch_max_dev_deg=float(dev[:, 0].max()), roll_max_dev_deg=float(dev[:, 1].max()),
                       pitch_rms_dev_deg=float(np.sqrt(np.mean(dev[:, 0] ** 2))),
                       roll_rms_dev_deg=float(np.sqrt(np.mean(dev[:, 1] ** 2))))
        summary["pitch_roll_deg"] = pr.tolist()
    if tracker is not None:
        summary.update(_track_summary(out, np.array(track_rows, float), twin.camera, times))
    (out / "task.toml").write_text(_task_toml(task, twin.scenario.name, seed))
    _plots(out, times, summary, cmd_rate, meas_rate, settings)
    (out / "report.md").write_text(_report(summary))
    (out / "summary.json").write_text(json.dumps({k: v for k, v in summary.items()
                                                   if k not in ("fixation_error_deg", "pitch_roll_deg")}, indent=1))
    return summary


def _make_tracker(task: Task, image: np.ndarray, region_uv: np.ndarray):
    """The 2D tracker of a track task, learnt on the first image: on ``task.region``, else on the
    default region (4, 2) (its corners for the planar tracker, their bounding box for mean shift)."""
    region = task.region
    if region is None:
        lo, hi = region_uv.min(axis=0), region_uv.max(axis=0)
        region = region_uv if task.method == "hyperplane" else (*lo, *(hi - lo))
    return make_tracker(task.method, image, region)


#: The default tracked region: the known rectangle grown about its centre, so that it takes in
#: the card's edge and the bench's texture around it (the same plane): a plain black rectangle
#: alone gives a planar tracker little to lock on to.
TRACK_REGION_SCALE = 1.8


def _true_corners(twin: Twin, T_world_cam: np.ndarray) -> np.ndarray:
    """(4, 2) where the default tracked region's corners are in the image: the first frame's
    region (the user's selection) and, later, the evaluation's truth."""
    from kinematics.camera import project

    xyz = twin.scenario.bench.target_corners()
    c = xyz.mean(axis=0)
    xyz = c + TRACK_REGION_SCALE * (xyz - c)
    return project(twin.camera, (xyz - T_world_cam[:3, 3]) @ T_world_cam[:3, :3])


def _diagonals_meet(quads: np.ndarray) -> np.ndarray:
    """(n, 2) where the diagonals of each quadrilateral (n, 4, 2) cross: the image of the centre
    of the planar rectangle it shows (a projective invariant, unlike the corners' mean)."""
    h = np.concatenate([quads, np.ones(quads.shape[:2] + (1,))], axis=2)
    p = np.cross(np.cross(h[:, 0], h[:, 2]), np.cross(h[:, 1], h[:, 3]))
    return p[:, :2] / p[:, 2:3]


def _track_summary(out: Path, rows: np.ndarray, camera, times) -> dict:
    """tracking.csv, and the servo's error: the rectangle's true centre against the image
    centre after the first second, and the tracker's corner error against the true corners."""
    with open(out / "tracking.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", *[f"{a}{k}" for k in range(4) for a in ("x", "y")], "lost",
                    *[f"true_{a}{k}" for k in range(4) for a in ("x", "y")]])
        w.writerows(rows.tolist())
    poly, lost, truth = rows[:, 1:9].reshape(-1, 4, 2), rows[:, 9] > 0, rows[:, 10:18].reshape(-1, 4, 2)
    after = times >= times[0] + 1.0
    centre_err = np.linalg.norm(_diagonals_meet(truth) - [camera.cx, camera.cy], axis=1)
    ok = after & ~lost & np.isfinite(poly).all(axis=(1, 2))
    corner_err = np.linalg.norm(poly - truth, axis=2)
    return {"track_lost_frames": int(lost.sum()),
            "servo_centre_rms_px": float(np.sqrt(np.mean(centre_err[after] ** 2))) if after.any() else float("nan"),
            "servo_centre_max_px": float(centre_err[after].max()) if after.any() else float("nan"),
            "tracker_corner_rms_px": float(np.sqrt(np.mean(corner_err[ok] ** 2))) if ok.any() else float("nan")}


def _landings(times, err_deg, events, task: Task) -> list[dict]:
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


def _task_toml(task: Task, scenario: str, seed: int) -> str:
    lines = ['# the closed-loop task, world frame (m)', f'scenario = "{scenario}"', f"seed = {seed}",
             f'task = "{task.kind}"', f"dwell_s = {task.dwell_s}",
             "targets = [" + ", ".join("[" + ", ".join(f"{v:.6f}" for v in p) + "]" for p in task.targets) + "]"]
    return "\n".join(lines) + "\n"


def _plots(out: Path, times, summary, cmd_rate, meas_rate, settings) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3))
    if "fixation_error_deg" in summary:
        ax.plot(times, summary["fixation_error_deg"], lw=1)
        ax.set_ylabel("fixation error, deg (true)")
        ax.axhline(1.0, color="grey", ls=":", lw=0.8)
    elif "pitch_roll_deg" in summary:
        pr = np.array(summary["pitch_roll_deg"])
        ax.plot(times, pr[:, 0] - pr[0, 0], lw=1, label="pitch")
        ax.plot(times, pr[:, 1] - pr[0, 1], lw=1, label="roll")
        ax.set_ylabel("change from start, deg (true)")
        ax.legend()
    ax.set_xlabel("t, s")
    fig.tight_layout()
    fig.savefig(out / "fixation_error.png", dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 3))
    for j, n in enumerate(JOINT_NAMES):
        ax.plot(times, np.degrees(cmd_rate[:, j]), lw=1, label=f"{n} (cmd)")
    lim = math.degrees(settings.motion_limit_rad_s)
    ax.axhline(lim, color="grey", ls=":", lw=0.8)
    ax.axhline(-lim, color="grey", ls=":", lw=0.8)
    ax.set_xlabel("t, s")
    ax.set_ylabel("joint rate, deg/s")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "joint_rates.png", dpi=100)
    plt.close(fig)


def _report(s: dict) -> str:
    lines = [f"# Closed loop: {s['task']} on {s['scenario']}", "",
             f"{s['frames']} frames over {s['seconds']:.2f} s; controlled-motion limit {s['motion_limit_deg_s']:.0f} deg/s; "
             f"peak commanded joint rate {s['peak_cmd_rate_deg_s']:.1f} deg/s (measured {s['peak_meas_rate_deg_s']:.1f}).", ""]
    if "fixation_rms_deg" in s:
        lines.append(f"Fixation error after the first second (true optic axis against the true direction to the "
                     f"target): RMS {s['fixation_rms_deg']:.2f} deg, peak {s['fixation_peak_deg']:.2f} deg.")
    for k, L in enumerate(s.get("landings", [])):
        if L["landed"]:
            lines.append(f"- saccade {k} to target {L['target']} at {L['start_s']:.2f} s: landed after "
                         f"{L['duration_s']:.2f} s, error {L['error_deg']:.2f} deg (max {L['error_after_deg']:.2f} over 0.3 s)")
        else:
            lines.append(f"- saccade {k} to target {L['target']} at {L['start_s']:.2f} s: did not land")
    if "pitch_max_dev_deg" in s:
        lines.append(f"Camera attitude against its start (true): pitch max {s['pitch_max_dev_deg']:.2f} deg "
                     f"(RMS {s['pitch_rms_dev_deg']:.2f}), roll max {s['roll_max_dev_deg']:.2f} deg "
                     f"(RMS {s['roll_rms_dev_deg']:.2f}).")
    if "servo_centre_rms_px" in s:
        lines.append(f"Tracking and servoing (after the first second): the target's true centre is "
                     f"{s['servo_centre_rms_px']:.1f} px RMS (max {s['servo_centre_max_px']:.1f}) from the image centre; "
                     f"the tracker's corners are {s['tracker_corner_rms_px']:.2f} px RMS from the truth; "
                     f"{s['track_lost_frames']} frames lost (tracking.csv).")
    if "ate_rmse_m" in s:
        lines.append(f"SLAM during the run: ATE RMSE {100 * s['ate_rmse_m']:.2f} cm (max {100 * s['ate_max_m']:.2f}), "
                     f"{s['lost_frames']} frames lost.")
    for r in s["refusals"]:
        lines.append(f"- refused at {r['t']:.2f} s: {r['reason']}")
    lines += ["", f"{s['prompts']} wearer prompts (prompts.csv).", "", "![error](fixation_error.png)", "",
              "![joint rates](joint_rates.png)", "",
              "Files: groundtruth.txt (true poses), trajectory.tum (SLAM), task.toml, joints.csv, prompts.csv, summary.json."]
    return "\n".join(lines) + "\n"
