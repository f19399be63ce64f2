"""The closed loop on any :class:`runtime.robot.Robot`: SLAM, the gaze controller and the 2D
trackers driving the head from the robot's observations alone (``wvr sim run`` on the twin,
``wvr run`` on the hardware rig).

Three parts, kept apart:

* **step** (:class:`ClosedLoop`): one observation in, one :class:`JointCommand` and one
  :class:`LoopRow` out. It sees what a real wearable gives: the image (through SLAM or a 2D
  tracker), the IMU samples and the joint angles; and, as inputs, the task and the start-up
  target (points of known position and where a person clicked them in the first image).
* **log** (:class:`LoopRow`, named columns; joints.csv and the trajectory files).
* **evaluate** (``runtime.apps.evaluate``): only where the robot offers truth
  (:class:`runtime.robot.TruthSource`), outside the control path.

Tasks
-----
``fixate``   hold the optic axis on the first target for the whole run.
``saccade``  saccade through the targets in turn, ``dwell_s`` on each (cycling), fixating in between.
``stabilise`` Path A: hold the camera's starting attitude from the IMU alone (no vision).
``body``     Path B: hold the starting gaze direction relative to the wearer's body.
``explore``  map: fixate where the map and the pose gain most (runtime.apps.explore), ``dwell_s``
             (default 1.5 s) after each landing, then choose again.
``track``    keep a 2D tracker's target centred (by default the start-up target's clicked
             rectangle, grown to take in its surround), the tracker seeing only the images.

Every task runs SLAM where it can start (trajectory.tum, scored like fixate's); fixate, saccade
and explore steer by its pose, stabilise, body and track only observe it (their commands are
those of a run without it).
"""

from __future__ import annotations

import csv
import json
import math
import signal
import threading
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
from kinematics.progress import progress_bar

from kinematics import JOINT_NAMES, forward_kinematics
from kinematics.tomlfile import read_toml

from ..gaze import ControllerSettings, GazeController, GazeRefused
from ..gaze.modes import Stabilise
from .recentre import Recentring
from ..session_log import SESSION_FILE, LoopRecorder
from ..background import DelayedResult
from ..robot import JointCommand, Observation, Robot, RobotInfo, SessionEnded, TruthSource
from ..sequence import Target, write_trajectory
from ..slam.config import DEFAULT_CONFIG, MapSettings, SlamConfig
from ..slam.head_motion_start import point_at_pixel
from ..slam.system import MonoSLAM
from .explore import ExploreSettings, choose_beyond_reach, choose_fixation, viewing_cone_sr
from .glances import GlanceSchedule, GlanceSettings, choose_glance, weakest_direction
from .head_motion import HeadMotionPhase
from ..vision2d.track import METHODS as TRACK_METHODS
from ..vision2d.track import make_tracker


class _CtrlC:
    """Ctrl-C (SIGINT) as a flag the loop reads each period, not an exception raised wherever
    the signal lands: a library mid-call (the QP solver) can turn that exception into an
    ordinary failure and swallow it. A second Ctrl-C raises at once (a blocked device wait).
    Only in the main thread (elsewhere Python keeps its own)."""

    def __init__(self):
        self.pressed = False
        self._old = None
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._press)

    def _press(self, signum, frame) -> None:
        if self.pressed:
            raise KeyboardInterrupt
        self.pressed = True

    def restore(self) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
            self._old = None


def slam_config(info: RobotInfo) -> SlamConfig:
    """The SLAM's filter settings for a robot: its IMU's noise where it reports one, and its
    clock offset's start."""
    cfg = replace(DEFAULT_CONFIG, time_offset0=info.imu_clock_offset_s)
    if info.imu_noise is None:
        return cfg
    return replace(cfg, imu_gyro_noise=info.imu_noise.gyro, imu_accel_noise=info.imu_noise.accel)


#: What the closed loop's controller may be asked to do.
TASKS = ("fixate", "saccade", "stabilise", "body", "track", "explore")

#: The default tracked region: the start-up target's clicked rectangle grown about its centre,
#: so that it takes in the card's edge and the bench's texture around it (the same plane): a
#: plain black rectangle alone gives a planar tracker little to lock on to.
TRACK_REGION_SCALE = 1.8


@dataclass(frozen=True)
class Task:
    """kind : one of :data:`TASKS`. targets : (n, 3) world points, m (fixate, saccade).
    dwell_s : time on each saccade target before the next (default 2 s), or explore's fixation
    after each landing (default 1.5 s). region : track: (x, y, w, h) pixels
    in the first frame (default: the start target's rectangle). method : track: the 2D tracker.
    recentre_per_s : stabilise: the gain of Path A's visual outer loop (runtime.apps.recentre),
    1/s; 0 (default) holds the attitude from the IMU alone. start : how SLAM starts: ``target``
    (the known target's clicked corners) or ``head-motion`` (no target: the head's own known
    motion fixes the scale, runtime.apps.head_motion, and the task begins after it; not with
    track; targets are then in the world frame that start makes, and fixate's default target is
    the clicked point or the image's centre). glances : fixate: leave the target briefly when
    SLAM's pose grows uncertain along one direction, look where that direction is best
    observed, come back (runtime.apps.glances). slam_imu : SLAM's prediction takes the IMU (False:
    the camera alone, the paper's system; the head-motion start reads the IMU either way)."""

    kind: str
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    dwell_s: float | None = None
    region: tuple | None = None
    method: str = "hyperplane"
    recentre_per_s: float = 0.0
    start: str = "target"
    glances: bool = False
    slam_imu: bool = True

    def __post_init__(self):
        if self.kind not in TASKS:
            raise ValueError(f"task {self.kind!r} unknown; choose one of {', '.join(TASKS)}")
        if self.start not in STARTS:
            raise ValueError(f"start {self.start!r} unknown; choose one of {', '.join(STARTS)}")
        if self.start == "head-motion" and self.kind == "track":
            raise ValueError("--start head-motion moves the head before the task, and track learns its region from "
                             "the first image, which that motion takes away: start track from the target "
                             "(--start target)")
        t = np.asarray(self.targets, float).reshape(-1, 3)
        if not np.isfinite(t).all():
            raise ValueError("task targets must be finite world points (x, y, z) m")
        if self.kind == "saccade" and len(t) == 0 or self.kind == "fixate" and len(t) == 0 and self.start == "target":
            raise ValueError(f"task {self.kind} needs a target: give --target X,Y,Z or --targets FILE")
        if self.kind == "saccade" and len(t) < 2:
            raise ValueError("task saccade needs at least two targets (--targets FILE)")
        if self.method not in TRACK_METHODS:
            raise ValueError(f"track method {self.method!r}: use one of {', '.join(TRACK_METHODS)}")
        if self.dwell_s is None:
            object.__setattr__(self, "dwell_s", EXPLORE_DWELL_S if self.kind == "explore" else SACCADE_DWELL_S)
        if not self.dwell_s > 0:
            raise ValueError(f"dwell_s = {self.dwell_s} must be positive")
        if not (math.isfinite(self.recentre_per_s) and self.recentre_per_s >= 0):
            raise ValueError(f"recentre_per_s = {self.recentre_per_s} must be >= 0 (1/s; 0 turns the outer loop off)")
        if self.glances and self.kind != "fixate":
            raise ValueError(f"glances leave a fixation target and come back to it: give them with task fixate, "
                             f"not {self.kind}")
        if self.recentre_per_s > 0 and self.kind != "stabilise":
            raise ValueError("recentring is Path A's outer loop: give it with task stabilise only")
        object.__setattr__(self, "targets", t)

    @property
    def uses_slam(self) -> bool:
        """Whether the control rests on SLAM's pose (fixate, saccade, explore). The other tasks
        run SLAM too, observed and scored but never fed to the controller."""
        return self.kind in ("fixate", "saccade", "explore")


#: The default time on each saccade target, and on each fixation explore chooses (after landing), s.
SACCADE_DWELL_S = 2.0
EXPLORE_DWELL_S = 1.5

#: Explore: a saccade that has not landed this long after its choice is given up, and the next
#: fixation chosen (SLAM lost on the way, or the wearer's motion keeps the error above landing).
EXPLORE_GIVE_UP_S = 3.0

#: Explore's dialogue with the wearer (issue 49, part 3): at most one request to turn this often,
#: and the map's uncertainty noted again this long after it (the turn made, the new view mapped).
ASK_EVERY_S = 10.0
ASK_AFTER_S = 6.0
#: The views beyond reach are searched beside the loop (about a second of CPU) on a snapshot
#: of the map; the answer is acted on this long after the snapshot.
ASK_SEARCH_DELAY_S = 1.0
#: Frames SLAM goes through each period after a head-motion start, to reach the present from the
#: frame the start was solved at (the head holds meanwhile).
CATCH_UP_PER_PERIOD = 3

#: Explore's and the glances' choices (a fixation IK per candidate view, about half a second of
#: CPU) are made beside the loop on a snapshot of the map and acted on this long after it; explore
#: takes its snapshot this long before its dwell ends, so that it saccades when the dwell does.
CHOICE_DELAY_S = 0.5

#: How SLAM's map can start in the closed loop.
STARTS = ("target", "head-motion")

#: How far from the world's origin a target may be, m (a wearable's scene is metres across).
MAX_TARGET_M = 1000.0


def load_targets(path: str | Path) -> tuple[np.ndarray, float | None]:
    """A targets file: TOML with ``targets = [[x, y, z], ...]`` (world, m) and optional ``dwell_s``."""
    d = read_toml(path, ValueError, "a targets TOML file (targets = [[x, y, z], ...])")
    if "targets" not in d:
        raise ValueError(f"{path}: no 'targets' list; write targets = [[x, y, z], ...] in metres, world frame")
    try:
        t = np.asarray(d["targets"], float)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: 'targets' must be a list of [x, y, z] triples of numbers (metres, world)") from None
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"{path}: 'targets' must be a list of [x, y, z] triples, got shape {t.shape}")
    bad = np.flatnonzero(~(np.abs(t) <= MAX_TARGET_M).all(axis=1))
    if bad.size:
        raise ValueError(f"{path}: target {bad[0] + 1} {t[bad[0]].tolist()} is not a finite world point within "
                         f"{MAX_TARGET_M:g} m of the origin; give x, y, z in metres")
    dwell = d.get("dwell_s")
    if dwell is not None and not (isinstance(dwell, (int, float)) and not isinstance(dwell, bool)
                                  and math.isfinite(dwell) and dwell > 0):
        raise ValueError(f"{path}: dwell_s = {dwell!r} must be a number of seconds above 0")
    return t, dwell


def default_region(target: Target) -> np.ndarray:
    """(4, 2) the default tracked region in the first image: the target's clicked corners grown
    by :data:`TRACK_REGION_SCALE` about their centre."""
    uv = np.asarray(target.uv, float)[:4]
    c = uv.mean(axis=0)
    return c + TRACK_REGION_SCALE * (uv - c)


def region_polygon(region) -> np.ndarray:
    """(4, 2) corners of a region given as (x, y, w, h) or as 4 corners."""
    r = np.asarray(region, float)
    if r.shape == (4, 2):
        return r
    x, y, w, h = r.reshape(4)
    return np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]])


#: The start-up target: known points with their pixels in the first image, or a callable that
#: is shown the first observation and returns them.
StartTarget = Target | Callable[[Observation], Target]


# ---------------------------------------------------------------------------------------------
# log
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LoopRow:
    """One control period, as logged. Angles rad, rates rad/s, target world m.

    t : the observation's time. cmd_q, cmd_rate : what the controller commanded. meas_q,
    meas_rate : the observation's joint angles (encoders, or commands where the robot has no
    encoders: see ``q_source``) and their rate. mode : the controller's mode. target : the
    current fixation or saccade target (NaN if none). est_error_deg : the controller's own
    estimate of its error. T_est : (4, 4) SLAM's camera pose (NaN without SLAM; the frames a
    head-motion start's SLAM goes through late get theirs when it is made). lost : SLAM
    lost this frame. polygon : (4, 2) the 2D tracker's region (NaN without). track_lost.
    reachable : the target was within the head's reach (else the head held and the wearer was
    prompted).
    """

    t: float
    cmd_q: np.ndarray
    meas_q: np.ndarray
    cmd_rate: np.ndarray
    meas_rate: np.ndarray
    mode: str
    target: np.ndarray
    est_error_deg: float
    q_source: str = "measured"
    T_est: np.ndarray = field(default_factory=lambda: np.full((4, 4), np.nan))
    lost: bool = False
    polygon: np.ndarray = field(default_factory=lambda: np.full((4, 2), np.nan))
    track_lost: bool = False
    reachable: bool = True

    #: joints.csv's columns, in order.
    CSV_HEADER = ["t", *[f"cmd_{n}" for n in JOINT_NAMES], *[f"meas_{n}" for n in JOINT_NAMES],
                  *[f"cmd_rate_{n}" for n in JOINT_NAMES], *[f"meas_rate_{n}" for n in JOINT_NAMES], "mode",
                  "target_x", "target_y", "target_z", "est_error_deg"]

    def csv_row(self) -> list:
        return [self.t, *self.cmd_q, *self.meas_q, *self.cmd_rate, *self.meas_rate, self.mode, *self.target,
                self.est_error_deg]


@dataclass
class LoopLog:
    """Everything the loop did, for writing and for evaluation: the rows, and the events
    (saccade starts and landings), refusals and prompts in time order. task_t0 : when the task
    began, s (after a head-motion start, once SLAM has caught up; None before)."""

    rows: list[LoopRow] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    refusals: list[dict] = field(default_factory=list)
    task_t0: float | None = None

    def column(self, name: str) -> np.ndarray:
        return np.array([getattr(r, name) for r in self.rows], float)

    @property
    def times(self) -> np.ndarray:
        return self.column("t")


# ---------------------------------------------------------------------------------------------
# step
# ---------------------------------------------------------------------------------------------

class ClosedLoop:
    """The control program of one task on one robot, a period at a time.

    info : what the robot reports (head, camera, frame rate). task : the :class:`Task`.
    start_target : the known points and their clicked pixels in the first image (SLAM's
    start-up, and the default tracked region), or a callable that is shown the first
    observation and returns them (a person clicking); required for fixate, saccade and track
    without a region. settings : the gaze controller's.
    """

    def __init__(self, info: RobotInfo, task: Task, start_target: StartTarget | None = None,
                 settings: ControllerSettings = ControllerSettings()):
        if task.uses_slam and start_target is None and task.start == "target":
            raise ValueError(f"task {task.kind} starts SLAM from a known target: give its target.toml "
                             f"(known points and their pixels in the first image)")
        if task.kind == "track" and task.region is None and start_target is None:
            raise ValueError("task track needs a region (--init X,Y,W,H) or a start target whose rectangle to track")
        self.info = info
        self.task = task
        self.start_target = start_target
        self.settings = settings
        self.dt = 1.0 / info.frame_rate
        self.log = LoopLog()
        self.slam: MonoSLAM | None = None
        self.ctl: GazeController | None = None
        self.tracker = None
        self.recentring: Recentring | None = None
        self.region_uv: np.ndarray | None = None
        self._i = 0
        self._current = 0
        self._q_prev = None
        self._imu_pending = []
        self._basis_t: float | None = None
        # Set once someone outside the task (an operator) changes the mode: from then on the
        # task's own schedule (its first target, the saccade dwell) no longer runs.
        self._kind: str = task.kind
        self._external_target: np.ndarray | None = None
        self.external = False
        self.head_start: HeadMotionPhase | None = None
        self.start_result = None            # the head-motion start's HeadMotionResult, once made
        self._catch_up: deque | None = None  # the frames SLAM has still to go through after it
        self._task_t0: float | None = None  # when the task began (the saccades' dwell counts from it)
        self.explore_settings = ExploreSettings()
        self.explore_choice = None          # explore: the last ExploreChoice (candidates and scores)
        self._explore_target: np.ndarray | None = None
        self._explore_n = -1                # explore: how many fixations chosen, less one
        self._explore_t = -np.inf           # explore: when the last was chosen, s
        self._explore_landed_t: float | None = None
        self._ask_t = -np.inf               # explore: when the wearer was last asked to turn, s
        self._ask_pending: float | None = None
        self._beyond = DelayedResult("explore-beyond-reach", ASK_SEARCH_DELAY_S, info.clock_waits)
        self._choice = DelayedResult("gaze-choice", CHOICE_DELAY_S, info.clock_waits)   # explore's or a glance's
        self.glances = GlanceSchedule(GlanceSettings()) if task.glances else None
        self.glance_choice = None           # glances: the last one's ExploreChoice (score: nats along the weak direction)

    # -- start-up: the first observation
    def start(self, obs: Observation) -> None:
        if callable(self.start_target):
            self.start_target = self.start_target(obs)
        if self.task.uses_slam or self.task.start == "head-motion" or self.start_target is not None:
            # Camera only (slam_imu False): the IMU is still read by the head-motion start.
            self.slam = MonoSLAM(self.info.camera, slam_config(self.info),
                                 replace(MapSettings(), use_imu=self.task.slam_imu), imu=True)
            if self.task.start == "head-motion":
                self.head_start = HeadMotionPhase(self.info.head, self.info.camera, obs.q,
                                                  clock_waits=self.info.clock_waits)
            else:
                self.slam.start(obs.image, obs.t, self.start_target)
        self.ctl = GazeController(self.info.head, self.info.camera, obs.q, self.dt, self.settings)
        if self.task.kind == "track":
            self.region_uv = region_polygon(self.task.region) if self.task.region is not None \
                else default_region(self.start_target)
            lo, hi = self.region_uv.min(axis=0), self.region_uv.max(axis=0)
            init = self.region_uv if self.task.method == "hyperplane" and self.task.region is None else (*lo, *(hi - lo))
            self.tracker = make_tracker(self.task.method, obs.image, init)
        if self.slam is None:
            self.log.events.append({"t": obs.t, "event": "start", "text": f"SLAM not run: task {self.task.kind} was "
                                    "given no start target to start it from (SLAM is only observed in this task)"})
        self._q_prev = np.asarray(obs.q, float).copy()
        self._i = 0
        self._basis_t = obs.t
        self._task_t0 = self.log.task_t0 = obs.t if self.head_start is None else None

    @property
    def prompts(self):
        return self.ctl.prompts if self.ctl is not None else []

    # -- hooks for a caller outside the task (the operator's station): mode changes between steps
    def saccade_to(self, p_world) -> None:
        """Saccade to a world point (3,) m at the controlled-motion limit, then fixate it; the
        task's own schedule stops. Raises GazeRefused (with the wearer's prompt) when it is out of
        reach, ValueError when it is not a finite point. Needs SLAM (a task that uses it)."""
        if self.slam is None:
            raise ValueError(f"saccades need SLAM's pose; this loop runs task {self.task.kind} without SLAM")
        p = np.asarray(p_world, float).reshape(-1)
        self.ctl.saccade(p)             # validates (finite, 3) and refuses the unreachable
        self._take_over("saccade")
        self._external_target = p.copy()

    def set_mode(self, mode: str, image: np.ndarray | None = None, region=None, method: str | None = None) -> None:
        """Switch the controller's mode from outside: ``hold``, ``stabilise`` (Path A, the present
        attitude), ``body`` (Path B, the present direction), ``track`` (a 2D tracker on ``region``
        (x, y, w, h) of ``image``, by default the image's central quarter; ``method`` the 2D
        tracker, by default the task's) or ``explore`` (choose a fixation, saccade, dwell, repeat:
        :meth:`_explore`; needs SLAM started). Fixation is :meth:`saccade_to`. Raises ValueError
        or GazeRefused with the reason."""
        if mode == "explore":
            if self.slam is None:
                raise ValueError(f"explore chooses views from SLAM's map; this loop runs task {self.task.kind} "
                                 "without SLAM")
            if not self.slam.started:
                raise ValueError("explore chooses views from SLAM's map, which has not started yet; "
                                 "set explore once SLAM has started")
            # Choose at the next period (the saccade starts from there), not after a dwell.
            self._explore_target, self._explore_t, self._explore_landed_t = None, -np.inf, None
            self.explore_choice = None
        elif mode == "hold":
            self.ctl.hold()
        elif mode == "stabilise":
            self.ctl.stabilise()
        elif mode == "body":
            self.ctl.body()
        elif mode == "track":
            if image is None:
                raise ValueError("track needs the current image to learn its target from")
            h, w = image.shape[:2]
            region = (w / 2 - w / 8, h / 2 - h / 8, w / 4, h / 4) if region is None else region
            self.tracker = make_tracker(method or self.task.method, image, tuple(np.asarray(region, float)))
            self.region_uv = region_polygon(region)
        else:
            raise ValueError(f"mode {mode!r} cannot be set from outside; use hold, stabilise, body, track or "
                             f"explore (fixation: saccade_to a point)")
        if mode != "track":
            self.tracker = None
        self._take_over(mode)
        self._external_target = None

    def _take_over(self, kind: str) -> None:
        self.external = True
        self._kind = kind

    @property
    def kind(self) -> str:
        """What the loop does now: the task's kind, or the mode an operator set since."""
        return self._kind

    def _set_target(self, i: int, t: float) -> None:
        task = self.task
        try:
            if task.kind == "fixate":
                self.ctl.fixate(task.targets[i])
            elif task.kind == "saccade":
                self.ctl.saccade(task.targets[i])
                self.log.events.append({"t": t, "event": "saccade", "target": i})
        except GazeRefused as e:
            self.log.refusals.append({"t": t, "target": i, "reason": str(e)})

    def _T_world_mount(self, q: np.ndarray) -> np.ndarray:
        """(4, 4) the mount's pose from SLAM's camera pose and the head's angles ``q`` (3,) rad."""
        return self.slam.T_world_cam() @ np.linalg.inv(forward_kinematics(self.info.head, q).T_mount_cam)

    def _explore(self, obs: Observation) -> None:
        """Explore: start choosing the next fixation (runtime.apps.explore) from a snapshot of
        SLAM's map and the head's reach, beside the loop (:meth:`_explored` acts on it). Nothing
        is chosen while SLAM is lost or a choice is in flight."""
        slam, t = self.slam, obs.t
        if slam is None or not slam.localised or self._choice.busy:
            return
        self._explore_t = t + CHOICE_DELAY_S
        q = np.asarray(obs.q, float)
        T_world_mount = self._T_world_mount(q)
        self._choice.submit(t, choose_fixation, self.info.head, self.info.camera, slam.state.copy(),
                            T_world_mount.copy(), q.copy(), slam.cfg.sigma_pixel, self.explore_settings,
                            map_points_world=slam.world_points().copy(), context=("explore", T_world_mount, q, None))

    def _explored(self, t: float, ch, T_world_mount: np.ndarray, q: np.ndarray) -> None:
        """Explore's choice is ready: saccade to the best candidate the controller accepts (a
        refused one is skipped); the wearer's dialogue looks at the same choice."""
        self.explore_choice = ch
        self._dialogue(t, ch, T_world_mount, q)
        self._explore_landed_t = None
        k = self._saccade_to_best(t, ch, -np.inf, "explore-skip")
        if k is None:
            return                  # none accepted: hold the present fixation, choose again after EXPLORE_GIVE_UP_S
        self._explore_n += 1
        self._explore_target = ch.points_world[k].copy()
        self.log.events.append({"t": t, "event": "explore", "target": self._explore_target.tolist(),
                                "score": float(ch.score[k]), "pose_info": float(ch.pose_info[k]),
                                "visible": int(ch.n_visible[k]), "index": self._explore_n})

    def _chosen(self, t: float) -> None:
        """Act on explore's or a glance's choice once it is back (:data:`CHOICE_DELAY_S`), if the
        loop still does what asked for it (an operator may have taken it elsewhere meanwhile)."""
        r = self._choice.collect(t)
        if r is None:
            return
        ch, (what, T_world_mount, q, weak) = r
        if not self.slam.localised:
            return                  # a saccade needs the pose: explore chooses again after its dwell
        if what == "explore" and self._kind == "explore":
            self._explored(t, ch, T_world_mount, q)
        elif what == "glance" and self.glances is not None and not self.external and not self.glances.away:
            self._glanced(t, ch, *weak)

    def _saccade_to_best(self, t: float, ch, floor: float, skip_event: str | None) -> int | None:
        """Saccade to the best of ``ch``'s candidates (an ExploreChoice) that scores at least
        ``floor`` and that the controller accepts, best first; each refused one is logged as a
        ``skip_event`` event (None: not logged). Its index, or None if none."""
        for k in np.argsort(-ch.score):
            if not (np.isfinite(ch.score[k]) and ch.score[k] >= floor):
                break
            try:
                self.ctl.saccade(ch.points_world[k])
            except GazeRefused as e:
                if skip_event is not None:
                    self.log.events.append({"t": t, "event": skip_event, "target": ch.points_world[k].tolist(),
                                            "reason": str(e)})
                continue
            return int(k)
        return None

    def _map_uncertainty(self) -> dict:
        """The map's uncertainty now (the dialogue's before and after): the camera position's
        standard deviation along its weakest direction, the median of the map points' largest
        standard deviations, m, the map's viewing cone, sr, and its size."""
        slam = self.slam
        n = slam.state.n_features
        cov = slam.track.map.point_covariances(np.arange(n)) if n else np.zeros((0, 3, 3))
        point_sigma = np.sqrt(np.clip(np.linalg.eigvalsh(cov)[:, -1], 0.0, None)) if n else np.zeros(0)
        return {"pose_sigma_m": weakest_direction(slam.state.P[0:3, 0:3])[0],
                "point_sigma_m": float(np.median(point_sigma)) if n else None,
                "map_cone_sr": viewing_cone_sr(slam.world_points(), slam.T_world_cam()[:3, 3]), "map_features": n}

    def _dialogue(self, t: float, ch, T_world_mount: np.ndarray, q: np.ndarray) -> None:
        """Explore's dialogue with the wearer (issue 49, part 3), at each explore choice: note the
        map's uncertainty ASK_AFTER_S after a request, and, at most every ASK_EVERY_S, start the
        search of the views beyond the head's reach on a snapshot of the map (beside the loop;
        :meth:`_ask` acts on it)."""
        if self._ask_pending is not None and t - self._ask_pending >= ASK_AFTER_S:
            self.log.events.append({"t": t, "event": "after-turn", **self._map_uncertainty()})
            self._ask_pending = None
        if t - self._ask_t < ASK_EVERY_S or self._beyond.busy:
            return
        slam, s = self.slam, self.explore_settings
        within = float(np.max(ch.score)) if np.isfinite(ch.score).any() else 0.0
        self._beyond.submit(t, choose_beyond_reach, self.info.head, self.info.camera, slam.state.copy(),
                            T_world_mount.copy(), q.copy(), slam.cfg.sigma_pixel, s,
                            map_points_world=slam.world_points().copy(), context=within)

    def _ask(self, t: float) -> None:
        """When the best view all round (searched by :meth:`_dialogue`) is beyond the head's reach
        and worth ``ask_margin_nats`` more than the best within it then, ask the wearer to turn
        (the controller's prompt, which a twin's obeying wearer acts on), noting the map's
        uncertainty. Not asked if the loop no longer explores."""
        r = self._beyond.collect(t)
        if r is None:
            return
        wish, within = r
        if self._kind != "explore":
            return                        # an operator has taken the loop elsewhere meanwhile
        if wish is None or not wish.score > within + self.explore_settings.ask_margin_nats:
            return
        self.ctl.emit(wish.prompt, force=True)
        self._ask_t = self._ask_pending = t
        self.log.events.append({"t": t, "event": "ask-turn", "text": wish.prompt.text,
                                "turn_deg": math.degrees(wish.prompt.turn_rad), "score": wish.score,
                                "best_within_reach": within, "target": wish.point_world.tolist(),
                                **self._map_uncertainty()})

    def _explore_due(self, t: float) -> bool:
        """Whether explore chooses again now: ``dwell_s`` after landing, or after giving up a
        saccade that did not land (or a choice that found nothing); before any choice, as soon as
        SLAM is localised, then every ``dwell_s``."""
        # An operator's explore on another task's loop takes explore's own dwell.
        dwell = self.task.dwell_s if self.task.kind == "explore" else EXPLORE_DWELL_S
        if self._explore_target is None:
            return t + CHOICE_DELAY_S - self._explore_t >= dwell
        if self._explore_landed_t is not None:
            return t + CHOICE_DELAY_S - self._explore_landed_t >= dwell
        return t - self._explore_t >= EXPLORE_GIVE_UP_S

    def _glance(self, obs: Observation) -> None:
        """Glances (runtime.apps.glances): send the head back when the glance is over; while
        fixating, glance when SLAM's position is uncertain enough along its weakest direction and
        a reachable view observes that direction."""
        g, slam, ctl, t = self.glances, self.slam, self.ctl, obs.t
        i_target = self._current % len(self.task.targets)
        act = g.step(t)
        if act == "return":
            try:
                ctl.saccade(self.task.targets[i_target])    # back at the controlled-motion limit
            except GazeRefused as e:
                self.log.refusals.append({"t": t, "target": i_target, "reason": str(e)})
                g.landed(t)                                   # nothing to go back along
                self.log.events.append({"t": t, "event": "glance-end", "index": g.count - 1})
                return
            self.log.events.append({"t": t, "event": "glance-return", "index": g.count - 1})
            return
        if act == "resume":
            self._set_target(i_target, t)
            self.log.events.append({"t": t, "event": "glance-end", "index": g.count - 1})
            return
        if slam is None or not slam.localised:
            return
        sigma, v = weakest_direction(slam.state.P[0:3, 0:3])
        if not g.due(t, sigma):
            return
        if self._choice.busy:
            return
        q = np.asarray(obs.q, float)
        T_world_mount = self._T_world_mount(q)
        # The dwell's frames each measure the view: their information adds, as one update whose
        # pixel noise is the filter's over the frames' count.
        frames = max(1, round(g.settings.dwell_s / self.dt))
        self._choice.submit(t, choose_glance, self.info.head, self.info.camera, slam.state.copy(),
                            T_world_mount.copy(), q.copy(), slam.cfg.sigma_pixel / math.sqrt(frames), v.copy(),
                            g.settings, map_points_world=slam.world_points().copy(),
                            context=("glance", T_world_mount, q, (sigma, v)))

    def _glanced(self, t: float, ch, sigma: float, v: np.ndarray) -> None:
        """A glance's choice (for the weakest direction ``v`` (3,), sigma m, it was chosen for)
        is ready: saccade out to the best view worth ``min_gain_nats``, or wait
        ``min_interval_s`` before asking again."""
        g = self.glances
        self.glance_choice = ch
        k = None if ch.best < 0 else self._saccade_to_best(t, ch, g.settings.min_gain_nats, None)
        if k is None:
            g.not_worth(t)
            return
        g.begin(t, ch.points_world[k])
        self.log.events.append({"t": t, "event": "glance", "index": g.count - 1,
                                "target": ch.points_world[k].tolist(), "sigma_m": sigma,
                                "direction": v.tolist(), "gain_nats": float(ch.score[k])})

    def _head_motion_start(self, obs: Observation) -> bool:
        """A period of the head-motion start; True at the period SLAM starts (the task begins)."""
        phase, slam = self.head_start, self.slam
        if self._catch_up is None:
            n_said = len(phase.said)
            r = phase.step(obs, self.ctl)
            for t, text in phase.said[n_said:]:
                self.log.events.append({"t": t, "event": "start", "text": text})
            if r is None:
                return False
            # The start is at the frame its solve was asked at; SLAM then goes through the
            # frames seen since, a few a period, the head holding, before the task begins.
            slam.add_imu(phase.imu_rows)
            image, t_start = phase.frame
            slam.start_natural(image, t_start, r.start)
            self._fill_pose(t_start)
            # The backlog ends with this period's frame.
            self.start_result, self._catch_up = r, deque(phase.backlog)
        else:
            self.ctl.hold()
            slam.add_imu(obs.imu.rows())
            if obs.fresh_image:
                self._catch_up.append((obs.image, obs.t))
        for _ in range(CATCH_UP_PER_PERIOD):
            if not self._catch_up:
                break
            image, t_frame = self._catch_up.popleft()
            slam.process(image, t_frame)
            self._fill_pose(t_frame)
        if self._catch_up:
            return False
        r = self.start_result
        self._catch_up = None
        self.head_start = None
        self._task_t0 = self.log.task_t0 = obs.t
        if self.task.kind == "fixate" and len(self.task.targets) == 0:
            # Fixate what the person clicked in the first image (start() took the clicks), else
            # what the camera looked at.
            tgt = self.start_target
            uv = (np.asarray(tgt.uv, float)[:4].mean(axis=0) if tgt is not None
                  else np.array([self.info.camera.cx, self.info.camera.cy]))
            p = point_at_pixel(self.info.camera, r, uv)
            self.task = replace(self.task, targets=p[None])
            self.log.events.append({"t": obs.t, "event": "start", "text": "fixation target from the first image's "
                                    f"{'click' if tgt is not None else 'centre'}: {np.round(p, 3).tolist()} m"})
        return True

    def _fill_pose(self, t: float) -> None:
        """SLAM's pose at the frame of time t, gone through late (after a head-motion start), into
        that period's row: the estimate from the frames up to it, as if made on time."""
        rows = self.log.rows
        for k in range(len(rows) - 1, -1, -1):
            if rows[k].t == t:
                rows[k] = replace(rows[k], T_est=self.slam.T_world_cam(), lost=not self.slam.localised)
                return
            if rows[k].t < t:
                return

    def step(self, obs: Observation) -> JointCommand:
        """One period: the observation in (after the robot's step, or the first one after
        :meth:`start`), the command for the next period out; appends a :class:`LoopRow`."""
        if self.ctl is None:
            raise RuntimeError("call start(first observation) first")
        i, task, ctl, slam = self._i, self.task, self.ctl, self.slam
        imu = obs.imu.rows()
        begin = i == 1
        if self.head_start is not None:
            begin = self._head_motion_start(obs)
            task = self.task
        elif slam is not None and i > 0:
            # SLAM folds in each fresh image with the IMU since the last one it saw.
            self._imu_pending.append(imu)
            if obs.fresh_image:
                slam.process(obs.image, obs.t, imu=np.vstack(self._imu_pending))
                self._imu_pending = []
        lost = bool(slam is not None and not slam.localised)
        behind = self._catch_up is not None       # SLAM's pose is a past frame's: none for now
        T_est = slam.T_world_cam() if slam is not None and not lost and not behind else None
        v_est = slam.state.v.copy() if T_est is not None else None
        # Stabilise, body and track run SLAM to be scored, not to be steered by: their control
        # gets no pose unless an operator has taken over (a saccade needs one).
        drives = self.task.uses_slam or self.external
        T_ctl, v_ctl = (T_est, v_est) if drives else (None, None)
        if begin and not self.external:
            # The first IMU rows arrive with the first step, and the mount's pose is known once
            # the controller has stepped once: the task starts then.
            if task.kind == "stabilise":
                ctl.attitude.update(imu)
                imu = np.zeros((0, 7))
                ctl.stabilise()
                if task.recentre_per_s > 0:
                    self.recentring = Recentring(self.info.camera, task.recentre_per_s)
            elif task.kind == "body":
                ctl.body()
            elif task.kind in ("fixate", "saccade"):
                self._set_target(0, obs.t)
            elif task.kind == "explore":
                self._explore(obs)
        elif self._kind == "explore" and i > 1 and self._explore_due(obs.t):
            self._explore(obs)
        if self._choice.busy:
            self._chosen(obs.t)
        if self._beyond.busy:
            self._ask(obs.t)
        elif self.glances is not None and not self.external and i > 1 and self._task_t0 is not None:
            self._glance(obs)
        if task.kind == "saccade" and not self.external and i > 1 and self._task_t0 is not None \
                and obs.t - self._task_t0 >= (self._current + 1) * task.dwell_s:
            self._current += 1
            self._set_target(self._current % len(task.targets), obs.t)
        if self.recentring is not None and self._kind == "stabilise" and obs.fresh_image \
                and isinstance(ctl.active, Stabilise):
            R_turn = self.recentring.correction(obs.t, obs.image, obs.imu.rows())
            ctl.stabilise(ctl.active.R_world_cam @ R_turn)
        poly, track_lost = np.full((4, 2), np.nan), False
        if self.tracker is not None:
            if i == 0:
                poly = self.region_uv.copy()
            elif obs.fresh_image:
                res = self.tracker.track(obs.image)
                poly, track_lost = res.polygon, bool(res.lost)
                if not res.lost:
                    ctl.track(res.centre)
                else:
                    ctl.hold()                # a lost target is said (tracking.csv), not chased
        # What the command rests on, for the robot's safety watchdog: the newest SLAM pose, IMU
        # sample or tracker fix (the task's own estimate; none for Path B).
        kind = self._kind
        if self.head_start is not None:
            self._basis_t = obs.t          # the start's motion rests on the encoders alone
        elif kind in ("fixate", "saccade", "explore", "hold") and slam is not None and drives:
            if T_est is not None:
                self._basis_t = obs.t
        elif kind == "stabilise":
            if len(obs.imu):
                self._basis_t = float(obs.imu.t[-1])
        elif kind == "track":
            if i == 0 or (obs.fresh_image and not track_lost):
                self._basis_t = obs.t
        else:
            self._basis_t = None
        cmd = ctl.step(obs.t, imu, obs.q, T_world_cam=T_ctl, v_world=v_ctl)
        if cmd.landed:
            if self._kind == "explore":
                self._explore_landed_t = obs.t
            if self.glances is not None and self.glances.away:
                back = self.glances.phase == "back"
                self.glances.landed(obs.t)
                if back:
                    self.log.events.append({"t": obs.t, "event": "glance-end", "index": self.glances.count - 1})
            self.log.events.append({"t": obs.t, "event": "landed", "target": self._explore_n if self._kind == "explore"
                                    else "external" if self.external else self._current % len(task.targets)})
        q = np.asarray(obs.q, float)
        qd_meas = (q - self._q_prev) / self.dt if i else np.zeros(3)
        self._q_prev = q.copy()
        tgt = task.targets[self._current % len(task.targets)] if len(task.targets) else np.full(3, np.nan)
        if self.external:
            tgt = self._external_target if self._external_target is not None else np.full(3, np.nan)
        if self._kind == "explore" and self._explore_target is not None:
            tgt = self._explore_target
        if self.glances is not None and self.glances.phase in ("out", "at"):
            tgt = self.glances.point
        err = math.degrees(cmd.error_rad) if np.isfinite(cmd.error_rad) else float("nan")
        self.log.rows.append(LoopRow(
            t=obs.t, cmd_q=cmd.q.copy(), meas_q=q.copy(), cmd_rate=cmd.qd.copy(), meas_rate=qd_meas, mode=cmd.mode,
            target=np.asarray(tgt, float).copy(), est_error_deg=err, q_source=obs.q_source,
            T_est=slam.T_world_cam() if slam is not None and slam.started and not behind else np.full((4, 4), np.nan),
            lost=lost,
            polygon=np.asarray(poly, float), track_lost=track_lost, reachable=bool(cmd.reachable)))
        self._i += 1
        return JointCommand(cmd.q, cmd.qd, basis_t=self._basis_t)


# ---------------------------------------------------------------------------------------------
# the run: step until done, log, and (with truth) evaluate
# ---------------------------------------------------------------------------------------------

def run_closed_loop(robot: Robot, task: Task, out: str | Path, start_target: StartTarget | None = None,
                    seconds: float | None = None, settings: ControllerSettings = ControllerSettings(),
                    progress: bool = True, truth: TruthSource | None = None, label: str = "",
                    task_info: dict | None = None, on_period: Callable[[Observation, JointCommand], None] | None = None,
                    on_end: Callable[[], None] | None = None, session_log: bool = True,
                    wearer: Callable[[float, object], bool] | None = None) -> dict:
    """Run ``task`` on ``robot`` for ``seconds`` (None: until the robot's session ends or Ctrl-C);
    write joints.csv, prompts.csv, task.toml, trajectory.tum (SLAM), report.md and
    summary.json into ``out``; return the summary.

    ``truth`` : where the robot offers it (the twin), the truth is logged beside each period,
    written as groundtruth.txt and scored (fixation error, attitude held, ATE, tracking): read
    only between periods, never by the control step. ``on_period(obs, command)`` : called
    every period (a session recorder). ``on_end()`` : called as soon as the loop stops, however it
    stops, before anything is scored or written (a rig's safe stop: the head is not left holding
    while the plots are drawn). ``label`` : what the report calls the robot's setting
    (the scenario); ``task_info`` : extra keys for task.toml. ``session_log`` : also session.mcap
    (images, IMU, joints, SLAM's pose and map, target, prompts, events; runtime.session_log).
    ``wearer(t, prompt)`` : who hears each wearer prompt as it is made (the twin's wearer, who
    may obey it: ``Twin.tell``); an obeyed one is logged as a ``wearer-obeys`` event.
    """
    from .evaluate import evaluate, start_map_scale
    from .report import write_outputs

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    info = robot.info
    n_frames = None if seconds is None else max(1, int(round(seconds * info.frame_rate)))
    loop = ClosedLoop(info, task, start_target, settings)
    truths = []
    obs = robot.reset()
    loop.start(obs)
    recorder = LoopRecorder(out / SESSION_FILE) if session_log else None
    interrupted, fault = None, None
    bar = progress_bar(total=n_frames, desc=f"closed loop {task.kind} ({label or info.name})", unit="frame",
               disable=not progress)
    ctrl_c = _CtrlC()
    start_depth, depth_at, n_said, n_prompts = None, None, 0, 0
    try:
        i = 0
        while True:
            if ctrl_c.pressed:
                raise KeyboardInterrupt
            if truth is not None:
                truths.append(truth.truth())
            cmd = loop.step(obs)
            for e in loop.log.events[n_said:]:
                if e["event"] == "start" and progress:
                    progress_bar.write(f"t = {e['t']:.1f} s: {e['text']}")
            n_said = len(loop.log.events)
            if wearer is not None:
                for t_p, prompt in loop.prompts[n_prompts:]:
                    if wearer(t_p, prompt):
                        loop.log.events.append({"t": t_p, "event": "wearer-obeys", "text": prompt.text})
            n_prompts = len(loop.prompts)
            phase = loop.head_start
            if phase is not None and phase.solving_at is not None and phase.solving_at != depth_at \
                    and hasattr(truth, "render_depth"):
                # Scoring only, after the step: the true depth at the frame the head-motion start
                # is solved at (once per try).
                depth_at, start_depth = phase.solving_at, truth.render_depth()
            if recorder is not None:
                recorder.period(loop, obs, cmd)
            if on_period is not None:
                on_period(obs, cmd)
            bar.update(1)
            i += 1
            if n_frames is not None and i >= n_frames:
                break
            try:
                obs = robot.step(cmd)
            except SessionEnded as e:
                interrupted = str(e) or "the robot's session ended"
                break
    except KeyboardInterrupt:
        interrupted = "stopped by Ctrl-C"
    except Exception as e:  # noqa: BLE001 - a device fault: write what was done, then re-raise
        interrupted, fault = f"fault: {e}", e
    finally:
        ctrl_c.restore()
        bar.close()
        if on_end is not None:
            on_end()
        if recorder is not None:
            recorder.close(interrupted or "complete")
    log = loop.log
    summary = {"scenario": label or info.name, "task": task.kind, "seconds": float(log.rows[-1].t - log.rows[0].t)
               if len(log.rows) > 1 else 0.0, "frames": len(log.rows),
               "motion_limit_deg_s": math.degrees(settings.motion_limit_rad_s), "refusals": log.refusals,
               "events": log.events, "prompts": len(loop.prompts), "ended": interrupted or "complete"}
    if loop.slam is not None:
        summary["lost_frames"] = sum(1 for s in loop.slam.stats if s.lost)
        state = loop.slam.state
        if state is not None and state.has_time_offset:
            # What the IMU's stamps lag the camera's by, as the filter learnt it (a rig's host
            # stamps both on arrival): worth knowing before trusting either clock.
            summary["imu_clock_offset_ms"] = 1000 * state.t_d
        if loop.slam.started and loop.slam.localised:
            # How much of the scene the map covers, seen from where the head ended: the solid
            # angle of its features' directions (runtime.apps.explore.viewing_cone_sr).
            Y = loop.slam.world_points()
            summary["map_features"] = int(len(Y))
            summary["map_cone_sr"] = viewing_cone_sr(Y, loop.slam.T_world_cam()[:3, 3])
        (out / "slam_stats.json").write_text(json.dumps({"frames": [asdict(s) for s in loop.slam.stats]}, indent=0))
    cmd_rate, meas_rate = log.column("cmd_rate"), log.column("meas_rate")
    summary["peak_cmd_rate_deg_s"] = float(np.degrees(np.abs(cmd_rate).max()))
    summary["peak_meas_rate_deg_s"] = float(np.degrees(np.abs(meas_rate[1:]).max())) if len(log.rows) > 1 else 0.0
    times = log.times
    if loop.slam is not None:
        # Periods before SLAM started (a head-motion start's motion) have no pose, and no row.
        T_est = np.array([r.T_est for r in log.rows])
        has = np.isfinite(T_est).all(axis=(1, 2))
        write_trajectory(out / "trajectory.tum", times[has], T_est[has], header="SLAM camera-to-world poses during the loop")
    if truth is not None:
        # A step that raised has its truth but no row.
        T_true = np.array([tr.T_world_cam for tr in truths[:len(log.rows)]])
        write_trajectory(out / "groundtruth.txt", times, T_true, header="true camera-to-world poses (optical frame)")
        summary.update(evaluate(log, T_true, truth.landmarks(), loop.task, info.camera, loop.region_uv, out))
        if loop.start_result is not None and start_depth is not None:
            summary.update(start_map_scale(loop.start_result.start, start_depth))
    with open(out / "joints.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(LoopRow.CSV_HEADER)
        w.writerows(r.csv_row() for r in log.rows)
    with open(out / "prompts.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "kind", "turn_deg", "step_m", "text"])
        for t, p in loop.prompts:
            w.writerow([f"{t:.3f}", p.kind, f"{math.degrees(p.turn_rad):.1f}", f"{p.step_m:.2f}", p.text])
    if loop.tracker is not None and truth is None:
        from .evaluate import write_tracking

        write_tracking(out, log, None)
    (out / "task.toml").write_text(task_toml(loop.task, task_info or {}))
    write_outputs(out, times, summary, cmd_rate, settings)
    if fault is not None:
        raise fault
    return summary


def task_toml(task: Task, extra: dict) -> str:
    """task.toml: the task as run (world frame, m), with ``extra`` keys (scenario, seed)."""
    lines = ['# the closed-loop task, world frame (m)']
    for k, v in extra.items():
        lines.append(f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {v}")
    lines += [f'task = "{task.kind}"', f'start = "{task.start}"', f"slam_imu = {str(task.slam_imu).lower()}",
              f"dwell_s = {task.dwell_s}",
              "targets = [" + ", ".join("[" + ", ".join(f"{v:.6f}" for v in p) + "]" for p in task.targets) + "]"]
    return "\n".join(lines) + "\n"
