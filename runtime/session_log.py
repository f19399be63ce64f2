"""session.mcap: one run's sensors and estimates in a file Foxglove (and any MCAP reader) opens.

Each stream is a topic of its own, stamped with the sensor's time (log_time = publish_time =
round(t * 1e9) ns, t the frame's or sample's time in seconds, the same clock as trajectory.tum):

================== ============================ =============================================
topic              schema                       what
================== ============================ =============================================
/camera/image      foxglove.CompressedImage     the camera's images, JPEG
/slam/pose         foxglove.PoseInFrame         SLAM's camera pose T_world_cam (frame "world")
/slam/odometry     foxglove.Odometry            the same pose with its 6x6 covariance
                                                (x, y, z, rotation about world x, y, z; m, rad)
/slam/map          foxglove.PointCloud          the map's features, world m (every few frames)
/slam/trajectory   foxglove.PosesInFrame        the run's poses as written to trajectory.tum
/joints/commanded  foxglove.JointStates         the head's commanded joint angles, rad
/joints/measured   foxglove.JointStates         the observed (encoder) joint angles, rad
/imu               JSON                         one sample per message: t, gyro rad/s, accel m/s^2
/task/target       foxglove.Point3InFrame       the gaze target, world m
/prompts           foxglove.Log                 what the wearer was told
/events            foxglove.Log                 station actions and run events
================== ============================ =============================================

/slam/pose and /slam/map are the filter's as it ran; /slam/trajectory is trajectory.tum's (after
a natural start's IMU scale and gravity, where that was used).

A sink, never on the control path: it only reads what it is given. Never half-written: it is
written as ``session.mcap.part`` and renamed to ``session.mcap`` by :meth:`SessionLog.close`; a
killed run leaves only the ``.part`` file (readable up to its last chunk by ``mcap recover``).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.JointState_pb2 import JointState
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.Odometry_pb2 import Odometry
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3InFrame_pb2 import Point3InFrame
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema

from kinematics import JOINT_NAMES

from .slam.quaternion import quat_from_rotation

#: The file's name in a run's folder.
SESSION_FILE = "session.mcap"
#: The world frame's and the camera's names in the messages.
WORLD, CAMERA = "world", "camera"
#: JPEG quality of the logged images (cheap to encode, ample to look at).
JPEG_QUALITY = 80
#: The map is logged every this many frames (and on the last).
MAP_EVERY = 10

_IMU_SCHEMA = {"type": "object", "title": "wvr.Imu", "properties": {
    "t": {"type": "number", "description": "sample time, s"},
    "gyro": {"type": "array", "items": {"type": "number"}, "description": "rad/s, camera frame"},
    "accel": {"type": "array", "items": {"type": "number"}, "description": "specific force m/s^2, camera frame"}}}


def stamp_ns(t: float) -> int:
    """A time in seconds as MCAP's nanoseconds (rounded: trajectory.tum's 9 decimals read back exactly)."""
    ns = int(round(float(t) * 1e9))
    if ns < 0:
        raise ValueError(f"t = {t} s: session.mcap needs times >= 0 (its stamps are unsigned)")
    return ns


def _timestamp(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _pose(T: np.ndarray) -> Pose:
    q = quat_from_rotation(T[:3, :3])                    # w x y z
    p = Pose()
    p.position.x, p.position.y, p.position.z = (float(v) for v in T[:3, 3])
    p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z = (float(v) for v in q)
    return p


def pose_covariance(x_v: np.ndarray, P_vv: np.ndarray) -> np.ndarray:
    """(6, 6) the camera pose's covariance over (position m, rotation about the world axes rad)
    from the filter's camera block: x_v (>= 7,) [r, q (w x y z)], P_vv its covariance. The
    quaternion's covariance is carried through dtheta = 2 vec(dq * conj(q))."""
    w, v = float(x_v[3]), np.asarray(x_v[4:7], float)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    J = np.zeros((6, 7))
    J[:3, :3] = np.eye(3)
    J[3:, 3] = -2 * v
    J[3:, 4:7] = 2 * (w * np.eye(3) + vx)
    return J @ np.asarray(P_vv, float)[:7, :7] @ J.T


def _sink(method):
    """A stream's method that never raises into the run: on a failure (a full disk, a time
    before 0) the log says so once, keeps what it wrote as session.mcap.part and stops."""
    @functools.wraps(method)
    def logged(self, *args, **kwargs):
        if self._closed:
            return
        try:
            method(self, *args, **kwargs)
        except Exception as e:  # noqa: BLE001 - a sink never stops the run it logs
            self.error = f"session.mcap: logging stopped ({e}); the run's other files are unaffected"
            print(f"warning: {self.error}")
            self.abort()
    return logged


class SessionLog:
    """A session.mcap being written (see the module's table of topics).

    path : the folder's ``session.mcap``. jpeg_quality : the images' JPEG quality (0-100).
    Every method takes t, the sensor's time in seconds; non-finite poses and points are skipped.
    A failure to write never reaches the caller: it is said once and the log stops (``error``).
    """

    def __init__(self, path: str | Path, jpeg_quality: int = JPEG_QUALITY):
        self.path = Path(path)
        self.part = self.path.with_name(self.path.name + ".part")
        self.path.unlink(missing_ok=True)                # an older run's log never sits beside new results
        self.jpeg_quality = int(jpeg_quality)
        self._fh = open(self.part, "wb")
        self._w = Writer(self._fh, compression=CompressionType.ZSTD)
        self._w.start(profile="", library="wvr")
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self._closed = False
        self.error = ""

    # ------------------------------------------------------------------ writing
    def _channel(self, topic: str, message_class=None) -> int:
        if topic not in self._channels:
            if message_class is None:
                sid = self._w.register_schema("wvr.Imu", "jsonschema", json.dumps(_IMU_SCHEMA).encode())
                self._channels[topic] = self._w.register_channel(topic, "json", sid)
            else:
                self._channels[topic] = self._w.register_channel(topic, "protobuf",
                                                                 register_schema(self._w, message_class))
        return self._channels[topic]

    def _put(self, topic: str, ns: int, data: bytes, message_class=None) -> None:
        ch = self._channel(topic, message_class)
        seq = self._seq.get(topic, 0)
        self._w.add_message(ch, log_time=ns, data=data, publish_time=ns, sequence=seq)
        self._seq[topic] = seq + 1
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _proto(self, topic: str, ns: int, msg) -> None:
        self._put(topic, ns, msg.SerializeToString(), type(msg))

    # ------------------------------------------------------------------ the streams
    @_sink
    def image(self, t: float, img: np.ndarray) -> None:
        """img : (H, W, 3) uint8 RGB or (H, W) grey."""
        ns = stamp_ns(t)
        bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img
        ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if ok:
            self._proto("/camera/image", ns, CompressedImage(timestamp=_timestamp(ns), frame_id=CAMERA,
                                                             data=jpg.tobytes(), format="jpeg"))

    @_sink
    def pose(self, t: float, T_world_cam: np.ndarray, cov6: np.ndarray | None = None) -> None:
        """T_world_cam (4, 4) m; cov6 (6, 6) its covariance (see :func:`pose_covariance`) or None."""
        T = np.asarray(T_world_cam, float)
        if not np.isfinite(T).all():
            return
        ns = stamp_ns(t)
        pose = _pose(T)
        self._proto("/slam/pose", ns, PoseInFrame(timestamp=_timestamp(ns), frame_id=WORLD, pose=pose))
        if cov6 is not None and np.isfinite(cov6).all():
            self._proto("/slam/odometry", ns, Odometry(timestamp=_timestamp(ns), frame_id=WORLD, body_frame_id=CAMERA,
                                                       pose=pose, pose_covariance=np.ravel(cov6).tolist()))

    @_sink
    def trajectory(self, t: float, T_world_cam: np.ndarray) -> None:
        """The whole run's poses (N, 4, 4), as one message stamped t."""
        ns = stamp_ns(t)
        self._proto("/slam/trajectory", ns, PosesInFrame(timestamp=_timestamp(ns), frame_id=WORLD,
                                                         poses=[_pose(T) for T in np.asarray(T_world_cam, float)]))

    @_sink
    def map(self, t: float, xyz: np.ndarray) -> None:
        """xyz (N, 3) the map's points, world m (float32 in the cloud)."""
        ns = stamp_ns(t)
        p = np.asarray(xyz, float).reshape(-1, 3)
        p = p[np.isfinite(p).all(axis=1)].astype("<f4")
        F32 = PackedElementField.FLOAT32
        self._proto("/slam/map", ns, PointCloud(
            timestamp=_timestamp(ns), frame_id=WORLD, pose=_pose(np.eye(4)), point_stride=12,
            fields=[PackedElementField(name=n, offset=4 * i, type=F32) for i, n in enumerate("xyz")], data=p.tobytes()))

    @_sink
    def joints(self, t: float, q_cmd: np.ndarray | None, q_meas: np.ndarray | None) -> None:
        """The head's joint angles (3,) rad, commanded and measured (either may be None)."""
        ns = stamp_ns(t)
        for topic, q in (("/joints/commanded", q_cmd), ("/joints/measured", q_meas)):
            if q is not None:
                self._proto(topic, ns, JointStates(timestamp=_timestamp(ns), joints=[
                    JointState(name=n, position=float(v)) for n, v in zip(JOINT_NAMES, np.ravel(q))]))

    @_sink
    def imu(self, rows: np.ndarray) -> None:
        """rows (k, 7) [t, wx, wy, wz, ax, ay, az]: one message per sample, at its own stamp."""
        for r in np.asarray(rows, float).reshape(-1, 7):
            if np.isfinite(r[0]):
                self._put("/imu", stamp_ns(r[0]), json.dumps(
                    {"t": float(r[0]), "gyro": r[1:4].tolist(), "accel": r[4:7].tolist()}).encode())

    @_sink
    def target(self, t: float, xyz: np.ndarray) -> None:
        """The gaze target (3,) world m (skipped when NaN: no target)."""
        p = np.asarray(xyz, float).reshape(3)
        if np.isfinite(p).all():
            ns = stamp_ns(t)
            msg = Point3InFrame(timestamp=_timestamp(ns), frame_id=WORLD)
            msg.point.x, msg.point.y, msg.point.z = (float(v) for v in p)
            self._proto("/task/target", ns, msg)

    def _log(self, topic: str, t: float, text: str, level, name: str) -> None:
        ns = stamp_ns(t)
        self._proto(topic, ns, Log(timestamp=_timestamp(ns), level=level, message=str(text), name=name))

    @_sink
    def prompt(self, t: float, text: str) -> None:
        """A prompt to the wearer."""
        self._log("/prompts", t, text, Log.WARNING, "wearer")

    @_sink
    def event(self, t: float, text: str, refused: bool = False) -> None:
        """An event (a station action, a run's end); ``refused`` logs it as an error."""
        self._log("/events", t, text, Log.ERROR if refused else Log.INFO, "wvr")

    # ------------------------------------------------------------------ ending
    def close(self, ended: str = "complete") -> Path:
        """Finish the file (index, summary, the message counts and ``ended`` as metadata
        "session") and rename it into place; returns its path (None if logging had stopped).
        A second call does nothing."""
        if not self._closed:
            self._closed = True
            self._w.add_metadata("session", {"ended": ended, **{k: str(v) for k, v in self.counts.items()}})
            self._w.finish()
            self._fh.close()
            self.part.replace(self.path)
        return self.path if self.path.exists() else None

    def abort(self) -> None:
        """A run that failed: finish what was written but leave it as ``session.mcap.part``."""
        if not self._closed:
            self._closed = True
            try:
                self._w.add_metadata("session", {"ended": "failed"})
                self._w.finish()
            except Exception:  # noqa: BLE001 - what was written stays in the .part file
                pass
            finally:
                self._fh.close()


class LoopRecorder:
    """The closed loop's periods into a :class:`SessionLog` (``wvr sim run``, ``wvr run --rig``,
    ``wvr station``): the image when fresh, the IMU's samples, the joints commanded and observed,
    SLAM's pose with its covariance (and its map every :data:`MAP_EVERY` periods), the target, and
    the wearer's prompts and the loop's events as they come. A sink: if writing fails it says so
    once and stops logging; the loop goes on."""

    def __init__(self, path: str | Path, jpeg_quality: int = JPEG_QUALITY):
        self.log: SessionLog | None = SessionLog(path, jpeg_quality)
        self.path = Path(path)
        self._periods = self._prompts = self._events = self._refusals = self._station_events = 0
        self.error = ""

    def period(self, loop, obs, cmd, station_events: list | None = None) -> None:
        """After ``loop.step(obs)`` gave ``cmd`` (a ClosedLoop, an Observation, a JointCommand);
        ``station_events`` : the station's EventRecords so far (the new ones are logged)."""
        if self.log is None:
            return
        try:
            self._period(loop, obs, cmd, station_events)
        except Exception as e:  # noqa: BLE001 - a sink never stops the loop
            self.error = f"session.mcap: logging stopped at t = {obs.t:.3f} s: {e}"
            print(f"warning: {self.error}")
            self.abort()

    def _period(self, loop, obs, cmd, station_events) -> None:
        log, t, row = self.log, float(obs.t), loop.log.rows[-1]
        if obs.fresh_image or self._periods == 0:
            log.image(t, obs.image)
        log.imu(obs.imu.rows())
        log.joints(t, cmd.q, obs.q)
        log.target(t, row.target)
        slam = loop.slam
        if slam is not None and slam.state is not None:
            st = slam.state
            log.pose(t, row.T_est, pose_covariance(st.x_v, st.P[:st.cam_dim, :st.cam_dim]))
            if self._periods % MAP_EVERY == 0:
                log.map(t, slam.world_points())
        for tp, p in loop.prompts[self._prompts:]:
            log.prompt(tp, p.text)
        self._prompts = len(loop.prompts)
        for e in loop.log.events[self._events:]:
            log.event(e["t"], json.dumps({k: v for k, v in e.items() if k != "t"}))
        self._events = len(loop.log.events)
        for r in loop.log.refusals[self._refusals:]:
            log.event(r["t"], f"target {r['target']} refused: {r['reason']}", refused=True)
        self._refusals = len(loop.log.refusals)
        if station_events is not None:
            for e in station_events[self._station_events:]:
                log.event(e.t if np.isfinite(e.t) else t, f"{e.source}: {e.action} {e.detail} "
                          + ("accepted" if e.accepted else f"refused: {e.reason}"), refused=not e.accepted)
            self._station_events = len(station_events)
        self._periods += 1

    def close(self, ended: str = "complete") -> Path | None:
        """Finish session.mcap (see :meth:`SessionLog.close`); None if logging had stopped."""
        if self.log is None:
            return None
        log, self.log = self.log, None
        return log.close(ended)

    def abort(self) -> None:
        if self.log is not None:
            log, self.log = self.log, None
            log.abort()

    def discard(self) -> None:
        """A session that never ran: no file at all."""
        log = self.log
        self.abort()
        if log is not None:
            log.part.unlink(missing_ok=True)
