"""The station's live loop: the closed loop (SLAM, gaze controller, the robot) in its own thread
at the robot's rate, never waiting for a browser.

* Actions from the page or the API go into a queue the loop drains at the start of each period;
  each is answered (:class:`~.actions.ActionResult`) through its :class:`Pending`.
* After each period the loop publishes a :class:`Snapshot` into a one-slot mailbox: readers (the
  3D view, the camera-view server) take the newest when they are ready; older ones are dropped,
  never queued.
* The emergency stop is latched: the head holds where it was last commanded (every period's
  command is that posture) until an explicit reset; a robot with its own latch (the rig's safety
  chain, ``robot.estop``) is tripped too.
* Truth, where the robot offers it (the twin), is read between periods for the recording only.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from kinematics import forward_kinematics

from ...gaze import ControllerSettings, GazeRefused
from ...robot import JointCommand, Observation, Robot, SessionEnded, TruthSource
from ...sequence import Target
from ..closed_loop import ClosedLoop, Task
from . import actions as A
from .geometry import ExploreView, Label, VirtualObject, feature_at_pixel
from .slam_view import MapView, empty_view, map_view

#: A wearer prompt stays on the pages this long after it was last said.
PROMPT_SHOW_S = 4.0
#: The 2D tracker the operator's track mode uses (on the image's centre when it is chosen).
TRACK_METHOD = "meanshift"
#: A command counts as motion once some joint is commanded faster than this (rad/s).
MOTION_RAD_S = math.radians(0.5)


@dataclass(frozen=True)
class Snapshot:
    """One period as the displays see it.

    seq : period number. t : the observation's time, s. wall : time.time() of publication.
    image : (H, W, 3) uint8 the camera's image. view : SLAM's :class:`MapView`. q : (3,) the
    joint angles observed, rad. cmd_qd : (3,) the commanded rates, rad/s. mode : controller mode.
    target : (3,) the fixation target, world m (NaN if none). estop : latched. prompt : the
    wearer's standing prompt text ("" if none). labels, objects : the operator's. T_world_joints :
    (3, 3) the head's joint origins and ``p_cam`` (3,) the optical centre, world m, through SLAM's
    pose (NaN without it). trajectory : (M, 3) SLAM's camera centres so far. loop_hz : the
    period rate over the last second of wall time. explore : explore's candidates and scores
    while the loop explores (empty before its first choice), None otherwise."""

    seq: int
    t: float
    wall: float
    image: np.ndarray
    view: MapView
    q: np.ndarray
    cmd_qd: np.ndarray
    mode: str
    target: np.ndarray
    estop: bool
    estop_reason: str
    prompt: str
    labels: tuple
    objects: tuple
    T_world_joints: np.ndarray
    trajectory: np.ndarray
    loop_hz: float
    explore: ExploreView | None = None


class Pending:
    """An action waiting for the loop; :meth:`wait` gives its :class:`ActionResult`."""

    def __init__(self, action, source: str):
        self.action, self.source = action, source
        self.received_wall = time.time()
        self._done = threading.Event()
        self.result: A.ActionResult | None = None

    def answer(self, result: A.ActionResult) -> None:
        self.result = result
        self._done.set()

    def wait(self, timeout: float = 5.0) -> A.ActionResult:
        if not self._done.wait(timeout):
            return A.ActionResult(False, "the loop did not answer in time (stopped or stalled)")
        return self.result


@dataclass
class EventRecord:
    """One action as events.csv records it."""

    t: float
    wall: float
    source: str
    action: str
    detail: str
    accepted: bool
    reason: str
    first_motion_wall: float = float("nan")     # the first period after it that commanded motion
    applied_wall: float = float("nan")


@dataclass
class StationRun:
    """What a station session did: the loop's rows (t, T_est, truth), the events and annotations,
    and why it ended."""

    times: list = field(default_factory=list)
    T_est: list = field(default_factory=list)
    T_true: list = field(default_factory=list)
    events: list = field(default_factory=list)
    labels: list = field(default_factory=list)
    objects: list = field(default_factory=list)
    ended: str = ""
    fault: BaseException | None = None


class LiveStation:
    """The live closed loop behind the station.

    robot : any :class:`Robot`. start_target : the known target and its clicked pixels in the
    first image (or a callable shown the first observation). truth : the twin (recording only).
    seconds : stop after this much robot time (None: until stopped or the robot's session ends).
    pace : keep the loop no faster than real time (a twin steps as fast as it renders).
    on_finish : called in the loop's thread when it ends (close a twin there: its renderer's GL
    context belongs to the thread that made it; a rig's safe stop).
    """

    def __init__(self, robot: Robot, start_target: Target | Callable[[Observation], Target],
                 settings: ControllerSettings = ControllerSettings(), truth: TruthSource | None = None,
                 seconds: float | None = None, pace: bool = True, on_finish: Callable[[], object] | None = None):
        self.robot = robot
        self.info = robot.info
        self.camera = robot.info.camera
        self.start_target = start_target
        self.settings = settings
        self.truth = truth
        self.seconds = seconds
        self.pace = pace
        self.on_finish = on_finish
        self.finish_result = None
        #: A session.mcap sink (runtime.session_log.LoopRecorder), set by the station; fed after each period.
        self.recorder = None
        self.run = StationRun()
        self.loop: ClosedLoop | None = None
        self._actions: queue.Queue[Pending] = queue.Queue()
        self._halt = threading.Event()
        self._cond = threading.Condition()
        self._snap: Snapshot | None = None
        self._thread: threading.Thread | None = None
        self._estop, self._estop_reason = False, ""
        self._q_stop: np.ndarray | None = None
        self._awaiting_motion: list[EventRecord] = []
        self._walls: list[float] = []
        self._traj: list[np.ndarray] = []
        self.started = threading.Event()
        self.finished = threading.Event()

    # ------------------------------------------------------------------ control from outside
    def start(self) -> "LiveStation":
        self._thread = threading.Thread(target=self._run, name="station-loop", daemon=True)
        self._thread.start()
        return self

    def submit(self, action, source: str) -> Pending:
        """Queue an action for the next period; answered at once if the loop has ended."""
        p = Pending(action, source)
        if self.finished.is_set():
            p.answer(A.ActionResult(False, "stopped: the station's loop has ended"))
            self._record(p, p.result, float("nan"))
        else:
            self._actions.put(p)
        return p

    def request(self, action, source: str, timeout: float = 5.0) -> A.ActionResult:
        return self.submit(action, source).wait(timeout)

    def stop(self, reason: str = "stopped") -> None:
        """End the session (not the emergency stop): the loop finishes its period and exits."""
        if not self.run.ended:
            self.run.ended = reason
        self._halt.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def latest(self) -> Snapshot | None:
        with self._cond:
            return self._snap

    def wait_newer(self, seq: int, timeout: float = 1.0) -> Snapshot | None:
        """The newest snapshot after period ``seq``, waiting up to ``timeout`` s; None if none came."""
        with self._cond:
            self._cond.wait_for(lambda: (self._snap is not None and self._snap.seq > seq) or self.finished.is_set(),
                                timeout)
            s = self._snap
        return s if s is not None and s.seq > seq else None

    # ------------------------------------------------------------------ the loop thread
    def _run(self) -> None:
        answered: list = []
        try:
            obs = self.robot.reset()
            target = self.start_target(obs) if callable(self.start_target) else self.start_target
            # Start by fixating the known target's centre (SLAM's best-conditioned view), until
            # the operator redirects the gaze.
            task = Task("fixate", np.asarray(target.xyz, float).mean(axis=0)[None])
            self.loop = loop = ClosedLoop(self.info, task, target, self.settings)
            loop.start(obs)
            n_frames = None if self.seconds is None else max(1, int(round(self.seconds * self.info.frame_rate)))
            i = 0
            wall0, t0 = time.perf_counter(), obs.t
            while not self._halt.is_set():
                answered = self._drain(obs)
                truth = self.truth.truth() if self.truth is not None else None
                cmd = loop.step(obs)
                if self._estop:
                    cmd = JointCommand(self._q_stop, np.zeros(3), basis_t=None)
                self._after_step(obs, cmd, truth)
                if self.recorder is not None:
                    self.recorder.period(loop, obs, cmd, self.run.events)
                # Answered once the period they changed is published: a client that reads the
                # state after its answer sees the change.
                for p, res in answered:
                    p.answer(res)
                answered = []
                i += 1
                if n_frames is not None and i >= n_frames:
                    self.run.ended = self.run.ended or "complete"
                    break
                if self.pace:
                    ahead = (obs.t - t0) - (time.perf_counter() - wall0)
                    if ahead > 0:
                        self._halt.wait(ahead)
                try:
                    obs = self.robot.step(cmd)
                except SessionEnded as e:
                    self.run.ended = self.run.ended or (str(e) or "the robot's session ended")
                    break
        except BaseException as e:  # noqa: BLE001 - a device fault: keep what was recorded, say why
            self.run.fault = e
            self.run.ended = f"fault: {e}"
            for p, res in answered:
                p.answer(res)
        finally:
            self.run.ended = self.run.ended or "stopped"
            if self.on_finish is not None:
                try:
                    self.finish_result = self.on_finish()
                except Exception as e:  # noqa: BLE001 - say it; the recording is still written
                    self.finish_result = f"failed: {e}"
            self.finished.set()
            with self._cond:
                self._cond.notify_all()
            while True:                      # anything still queued is refused, not left hanging
                try:
                    p = self._actions.get_nowait()
                except queue.Empty:
                    break
                p.answer(A.ActionResult(False, "stopped: the station's loop has ended"))
                self._record(p, p.result, float("nan"))

    def _after_step(self, obs: Observation, cmd: JointCommand, truth) -> None:
        loop = self.loop
        view = map_view(loop.slam)
        row = loop.log.rows[-1]
        now = time.time()
        self.run.times.append(obs.t)
        self.run.T_est.append(view.T_world_cam.copy())
        if truth is not None:
            self.run.T_true.append(np.asarray(truth.T_world_cam, float).copy())
        if view.localised:
            self._traj.append(view.T_world_cam[:3, 3].copy())
        qd = np.asarray(cmd.qd, float)
        if np.abs(qd).max() > MOTION_RAD_S:
            for ev in self._awaiting_motion:
                ev.first_motion_wall = now
            self._awaiting_motion = []
        self._walls = [w for w in self._walls if now - w < 1.0] + [now]
        prompt = ""
        if loop.prompts and obs.t - loop.prompts[-1][0] <= PROMPT_SHOW_S:
            prompt = loop.prompts[-1][1].text
        joints = np.full((3, 3), np.nan)
        if view.localised:
            pose = forward_kinematics(self.info.head, np.asarray(obs.q, float))
            T_wm = view.T_world_cam @ np.linalg.inv(pose.T_mount_cam)
            joints = np.vstack([pose.origins_mount, pose.p_mount_cam[None]]) @ T_wm[:3, :3].T + T_wm[:3, 3]
        snap = Snapshot(
            seq=len(self.run.times), t=float(obs.t), wall=now, image=np.array(obs.image, copy=True), view=view,
            q=np.asarray(obs.q, float).copy(), cmd_qd=qd.copy(), mode="stopped" if self._estop else row.mode,
            target=np.asarray(row.target, float).copy(), estop=self._estop, estop_reason=self._estop_reason,
            prompt=prompt, labels=tuple(self.run.labels), objects=tuple(self.run.objects),
            T_world_joints=joints, trajectory=np.array(self._traj).reshape(-1, 3),
            loop_hz=(len(self._walls) - 1) / max(self._walls[-1] - self._walls[0], 1e-9) if len(self._walls) > 1 else 0.0,
            explore=ExploreView.of(loop.explore_choice, row.target) if loop.kind == "explore" else None)
        with self._cond:
            self._snap = snap
            self._cond.notify_all()
        self.started.set()                 # once the first snapshot is out

    # ------------------------------------------------------------------ actions
    def _drain(self, obs: Observation) -> list:
        """Apply the queued actions; returns them with their results, to be answered."""
        out = []
        while True:
            try:
                p = self._actions.get_nowait()
            except queue.Empty:
                return out
            try:
                res = self._apply(p.action, obs)
            except (A.BadAction, ValueError) as e:
                res = A.ActionResult(False, str(e), obs.t)
            except Exception as e:  # noqa: BLE001 - a bad action never stops the loop
                res = A.ActionResult(False, f"internal error: {e}", obs.t)
            ev = self._record(p, res, obs.t)
            if res.accepted and isinstance(p.action, (A.Fixate, A.SetMode)):
                self._awaiting_motion.append(ev)
            out.append((p, res))

    def _record(self, p: Pending, res: A.ActionResult, t: float) -> EventRecord:
        a = p.action
        # %.6g, not rounding: np.round(1e308, 4) overflows to inf, which events.csv must never hold.
        detail = {k: ([float(f"{e:.6g}") for e in np.ravel(v)] if isinstance(v, np.ndarray) else v)
                  for k, v in vars(a).items() if k != "name" and v is not None}
        ev = EventRecord(t=t, wall=p.received_wall, source=p.source, action=a.name, detail=str(detail),
                         accepted=res.accepted, reason=res.reason, applied_wall=time.time())
        self.run.events.append(ev)
        return ev

    def _view_now(self) -> MapView:
        return map_view(self.loop.slam) if self.loop is not None else empty_view()

    def _resolve_point(self, act, view: MapView) -> tuple[np.ndarray, dict]:
        """The world point an action names (a feature, a point, a pixel), and what it resolved to."""
        if act.feature is not None:
            p = view.point_of(act.feature)
            if p is None:
                raise A.BadAction(f"unknown feature id {act.feature}: the map has "
                                  f"{', '.join(map(str, view.ids[:20].tolist())) or 'no features'}")
            return p, {"feature": int(act.feature), "xyz": p.tolist()}
        if act.uv is not None:
            w, h = self.camera.width, self.camera.height
            if not (-0.5 <= act.uv[0] <= w - 0.5 and -0.5 <= act.uv[1] <= h - 0.5):
                raise A.BadAction(f"uv ({act.uv[0]:.3g}, {act.uv[1]:.3g}) px is outside the {w}x{h} image; "
                                  "give a pixel of the camera view")
            if not view.localised:
                raise A.BadAction("a pixel cannot be resolved while SLAM is lost")
            fid = feature_at_pixel(view, self.camera, act.uv)
            if fid is None:
                raise A.BadAction(f"no map feature within a few pixels of ({act.uv[0]:.0f}, {act.uv[1]:.0f}); "
                                  "click on a feature's mark")
            p = view.point_of(fid)
            return p, {"feature": fid, "xyz": p.tolist()}
        return np.asarray(act.xyz, float), {"xyz": np.asarray(act.xyz, float).tolist()}

    def _apply(self, act, obs: Observation) -> A.ActionResult:
        loop, t = self.loop, obs.t
        if isinstance(act, A.Stop):
            if not self._estop:
                self._estop, self._estop_reason = True, act.reason
                self._q_stop = loop.ctl.filter.q.copy()
                loop.set_mode("hold")
                loop.ctl.filter.reset(self._q_stop)
                loop.ctl.qd_prev = np.zeros(3)
                latch = getattr(self.robot, "estop", None)
                if latch is not None and hasattr(latch, "trip"):
                    latch.trip(act.reason)
            return A.ActionResult(True, "", t, {"estop": True})
        if isinstance(act, A.Reset):
            latch = getattr(self.robot, "estop", None)
            if latch is not None and hasattr(latch, "reset"):
                latch.reset()
            self._estop, self._estop_reason = False, ""
            return A.ActionResult(True, "", t, {"estop": False, "mode": loop.ctl.mode})
        view = self._view_now()
        if isinstance(act, A.AddLabel):
            p, detail = self._resolve_point(act, view)
            lb = Label(len(self.run.labels), p, act.text)
            self.run.labels.append(lb)
            return A.ActionResult(True, "", t, {"label": lb.id, **detail})
        if isinstance(act, A.AddObject):
            p, detail = self._resolve_point(act, view)
            ob = VirtualObject(len(self.run.objects), act.kind, p, np.asarray(act.size, float))
            self.run.objects.append(ob)
            return A.ActionResult(True, "", t, {"object": ob.id, **detail})
        if self._estop:
            return A.ActionResult(False, f"stopped: the emergency stop is latched ({self._estop_reason}); "
                                  "reset it first", t)
        if isinstance(act, A.Fixate):
            p, detail = self._resolve_point(act, view)
            try:
                loop.saccade_to(p)
            except GazeRefused as e:
                return A.ActionResult(False, f"unreachable: {e}", t,
                                      {"prompt": e.prompt.text if e.prompt is not None else "", **detail})
            return A.ActionResult(True, "", t, {"mode": "saccade", **detail})
        if isinstance(act, A.SetMode):
            try:
                # CamShift starts at once; the hyperplane tracker learns for seconds, which
                # would hold the loop.
                loop.set_mode(act.mode, image=obs.image, method=TRACK_METHOD)
            except GazeRefused as e:
                return A.ActionResult(False, f"unreachable: {e}", t)
            return A.ActionResult(True, "", t, {"mode": act.mode})
        raise A.BadAction(f"unknown action {act!r}")
