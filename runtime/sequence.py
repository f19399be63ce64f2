"""Image sequences, trajectories and sensor logs in the layout of shared/formats.md.

A sequence is a folder in the TUM RGB-D layout plus two small TOML files::

    SEQ/
      rgb.txt          "timestamp path" per line, '#' comments, paths relative to SEQ
      rgb/<t>.png      8-bit (or 16-bit) colour or grey images
      camera.toml      intrinsics (kinematics.camera), required
      target.toml      optional: >= 4 known world points and their pixels in the first frame
      groundtruth.txt  optional: "timestamp tx ty tz qx qy qz qw", camera-to-world
      imu.txt          optional: "timestamp wx wy wz ax ay az", rad/s and m/s^2, camera frame
      joints.txt       optional: "timestamp q_elevation q_pan q_cyclotorsion", rad
      depth.txt        optional: "timestamp path" of depth/<t>.png, TUM RGB-D's 16-bit depth
                       images (z along the optic axis, metres x 5000; 0 = no depth), for
                       evaluating maps (the twin renders them)

Frames and units
----------------
world
    the frame the target (or the ground truth) fixes; metres.
cam
    the camera's optical frame: x right, y down, z forward along the optic axis.
``T_world_cam``
    (4, 4) homogeneous transform mapping optical-frame coordinates to world coordinates: its
    translation is the optical centre in the world, its rotation takes cam axes to world axes.
    Trajectory files store it as TUM does: position, then the unit quaternion in x y z w order.
Times are seconds (float); angles radians; pixels in the OpenCV convention.

Errors in files raise :class:`SequenceError`, one line naming the file, the line or field and
the fix. Bad images never raise: :meth:`Sequence.frames` yields them with ``image=None`` and a
``problem`` so that a long recording with a few broken frames still runs.
"""

from __future__ import annotations

import math
import numbers
import os
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence as _Seq, TextIO

import cv2
import numpy as np
import tomli_w
from scipy.spatial.transform import Rotation, Slerp

from kinematics.camera import CameraIntrinsics, load_camera, save_camera
from kinematics.outdir import OutputFolderError, check_complete, check_folder, output_folder, writing
from kinematics.tomlfile import read_toml

# Column layouts of the text files (the '#' header line each writer puts at the top).
TRAJECTORY_COLUMNS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
IMU_COLUMNS = ("timestamp", "wx", "wy", "wz", "ax", "ay", "az")
JOINT_COLUMNS = ("timestamp", "q_elevation", "q_pan", "q_cyclotorsion")
_IMU_UNITS = "rad/s, m/s^2, camera frame"

#: A quaternion read from a file is normalised if its norm is within this of 1; further off
#: it is an error (a typo or a wrong column order), not rounding.
QUATERNION_NORM_TOL = 1e-3
#: A rotation matrix given to a writer must be orthonormal to this (max abs of R^T R - I).
ROTATION_TOL = 1e-6

# Digits written: %.9f keeps times, positions, rates and angles to 5e-10 (nanoseconds,
# sub-nanometre); quaternions get three more so that the rotation matrices rebuilt from them
# (quadratic in q) also reproduce to better than 1e-9.
_FMT_TIME = "%.9f"
_FMT_VALUE = "%.9f"
_FMT_QUAT = "%.12f"
_FMT_IMAGE_NAME = "%.6f"  # rgb/<t>.png, microseconds as the TUM data sets name them

_SEQUENCE_FILES = "see shared/formats.md"
DEPTH_SCALE = 5000.0  # TUM RGB-D: a depth PNG holds metres x 5000 (0.2 mm steps, up to 13.1 m)


#: The kind (kinematics.outdir) of a folder a SequenceWriter writes on its own (wvr sim record).
RECORDING = "sim record"


class SequenceError(ValueError):
    """A sequence, trajectory, log or target file (or array) that cannot be used; a one-line
    message naming the file, the line or field and the fix."""


# ---------------------------------------------------------------------------------------------
# Whitespace-separated time series (TUM style)
# ---------------------------------------------------------------------------------------------

def _read_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """The (1-based line number, text) of every line that is not blank or a '#' comment."""
    path = Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: no such file; give the path of a {what}")
    try:
        # utf-8-sig: files saved by Windows editors start with a byte-order mark.
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise SequenceError(f"{path}: cannot read ({e}); give a plain-text {what}") from None
    out = []
    for n, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((n, s))
    return out


def _read_table(path: str | Path, columns: tuple[str, ...], what: str) -> tuple[np.ndarray, list[int]]:
    """Read a file of ``len(columns)`` numbers per line.

    Returns the (N, len(columns)) float array and the file line number of each row (for later
    messages). Blank and '#' lines are skipped; a line with the wrong count of fields, a field
    that is not a number, a non-finite number, or a timestamp not after the previous one is an
    error naming the line. The first column is the timestamp.
    """
    path = Path(path)
    layout = " ".join(columns)
    rows, linenos, prev_t, prev_n = [], [], -math.inf, 0
    for n, s in _read_lines(path, what):
        fields_ = s.split()
        if len(fields_) != len(columns):
            raise SequenceError(f"{path}:{n}: {len(fields_)} fields, expected {len(columns)} "
                                f"({layout}); fix the line or start it with '#'")
        try:
            row = [float(x) for x in fields_]
        except ValueError:
            bad = next(x for x in fields_ if not _is_float(x))
            col = columns[fields_.index(bad)]
            raise SequenceError(f"{path}:{n}: {col} = {bad!r} is not a number; each line is "
                                f"'{layout}'") from None
        for col, v in zip(columns, row):
            if not math.isfinite(v):
                raise SequenceError(f"{path}:{n}: {col} = {v} is not finite; write a finite number "
                                    f"or remove the line")
        if not row[0] > prev_t:
            raise SequenceError(f"{path}:{n}: timestamp {row[0]!r} is not after {prev_t!r} on line "
                                f"{prev_n}; lines must be in increasing time order (sort the file)")
        prev_t, prev_n = row[0], n
        rows.append(row)
        linenos.append(n)
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(columns)), linenos


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _header_lines(columns: tuple[str, ...], header: str | None, units: str) -> list[str]:
    """'#' lines: the caller's free text (if any), then the column layout (as TUM files have)."""
    lines = [f"# {h}".rstrip() for h in header.splitlines()] if header else []
    lines.append(f"# {' '.join(columns)}" + (f"  ({units})" if units else ""))
    return lines


def _format_row(t: float, values: np.ndarray, fmts: _Seq[str]) -> str:
    return " ".join([_FMT_TIME % t] + [f % v for f, v in zip(fmts, values)])


def _as_times(t, name: str = "t") -> np.ndarray:
    """(N,) float array of finite, strictly increasing times, seconds."""
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1:
        raise SequenceError(f"{name} must have shape (N,), got {t.shape}")
    if not np.isfinite(t).all():
        raise SequenceError(f"{name}[{int(np.flatnonzero(~np.isfinite(t))[0])}] is not finite; times are seconds")
    if t.size > 1 and not (np.diff(t) > 0).all():
        i = int(np.flatnonzero(~(np.diff(t) > 0))[0]) + 1
        raise SequenceError(f"{name}[{i}] = {float(t[i])!r} is not after {name}[{i - 1}] = {float(t[i - 1])!r}; "
                            f"times must be strictly increasing")
    return t


def _as_columns(a, n: int, dim: int, name: str) -> np.ndarray:
    """(n, dim) finite float array."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n, dim):
        raise SequenceError(f"{name} must have shape ({n}, {dim}), got {a.shape}")
    if not np.isfinite(a).all():
        raise SequenceError(f"{name} has non-finite values in row {int(np.flatnonzero(~np.isfinite(a).all(1))[0])}")
    return a


def _write_rows(path: str | Path, header: list[str], rows: list[str]) -> None:
    Path(path).write_text("\n".join(header + rows) + "\n")


# ---------------------------------------------------------------------------------------------
# Trajectories (groundtruth.txt, and every trajectory wvr writes)
# ---------------------------------------------------------------------------------------------

def _unit_quaternions(q: np.ndarray, where) -> np.ndarray:
    """Normalise (N, 4) quaternions within QUATERNION_NORM_TOL of unit length; else an error.

    where(i) names row i in the message (a file line, or an array index).
    """
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= QUATERNION_NORM_TOL))
    if bad.size:
        i = int(bad[0])
        raise SequenceError(f"{where(i)}: quaternion (qx qy qz qw) has norm {norm[i]:.6g}, not 1; "
                            f"check the column order (tx ty tz qx qy qz qw) or normalise it")
    return q / norm[:, None]


def _rotations_from_T(T: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) rigid transforms -> positions (N, 3) and unit quaternions xyzw (N, 4).

    Refuses matrices that are not rigid (scipy would silently orthonormalise them, hiding a
    wrong matrix).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise SequenceError(f"{name} must have shape (N, 4, 4), got {T.shape}")
    if not np.isfinite(T).all():
        raise SequenceError(f"{name} has non-finite values")
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bottom = np.abs(T[:, 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = np.flatnonzero((err > ROTATION_TOL) | (np.linalg.det(R) <= 0) | (bottom > 0))
    if bad.size:
        i = int(bad[0])
        raise SequenceError(f"{name}[{i}] is not a rigid transform (rotation block not orthonormal "
                            f"with det +1, or last row not [0 0 0 1]); pass camera-to-world poses")
    return T[:, :3, 3].copy(), Rotation.from_matrix(R).as_quat()


@dataclass
class Trajectory:
    """A camera-to-world trajectory (TUM convention).

    t : (N,) float, seconds, strictly increasing.
    p_world_cam : (N, 3) float, metres: the optical centre in the world frame.
    q_xyzw : (N, 4) float, unit quaternions (x y z w) rotating optical-frame axes to world axes.
    """

    t: np.ndarray
    p_world_cam: np.ndarray
    q_xyzw: np.ndarray

    def __post_init__(self):
        self.t = _as_times(self.t)
        n = len(self.t)
        self.p_world_cam = _as_columns(self.p_world_cam, n, 3, "p_world_cam")
        self.q_xyzw = _unit_quaternions(_as_columns(self.q_xyzw, n, 4, "q_xyzw"),
                                        lambda i: f"q_xyzw[{i}]")

    @classmethod
    def from_T_world_cam(cls, t, T_world_cam) -> "Trajectory":
        """From times (N,) s and camera-to-world transforms (N, 4, 4)."""
        p, q = _rotations_from_T(T_world_cam, "T_world_cam")
        return cls(t, p, q)

    def __len__(self) -> int:
        return len(self.t)

    def R_world_cam(self) -> np.ndarray:
        """(N, 3, 3) rotations taking optical-frame vectors to world vectors."""
        if len(self) == 0:
            return np.zeros((0, 3, 3))
        return Rotation.from_quat(self.q_xyzw).as_matrix()

    def T_world_cam(self) -> np.ndarray:
        """(N, 4, 4) homogeneous camera-to-world transforms (metres)."""
        T = np.zeros((len(self), 4, 4))
        T[:, :3, :3] = self.R_world_cam()
        T[:, :3, 3] = self.p_world_cam
        T[:, 3, 3] = 1.0
        return T

    def interpolate(self, times) -> "Trajectory":
        """The trajectory at other times: positions linear, orientations by slerp.

        times : (M,) float, seconds, strictly increasing, each within [t[0], t[-1]].
        Returns a Trajectory of M poses (so its times must increase, as every Trajectory's do).
        Times outside the recorded range are refused rather than extrapolated (a pose guessed
        past the data would look measured).
        """
        times = _as_times(np.atleast_1d(np.asarray(times, dtype=np.float64)), "times")
        if len(self) == 0:
            raise SequenceError("cannot interpolate an empty trajectory")
        outside = np.flatnonzero((times < self.t[0]) | (times > self.t[-1]))
        if outside.size:
            ti = float(times[int(outside[0])])
            raise SequenceError(f"time {ti!r} s is outside the trajectory's range "
                                f"[{float(self.t[0])!r}, {float(self.t[-1])!r}] s; ask only for "
                                f"times within it")
        if len(self) == 1:  # Slerp needs two key times; the only valid time is t[0] itself
            return Trajectory(times, np.repeat(self.p_world_cam, len(times), 0),
                              np.repeat(self.q_xyzw, len(times), 0))
        p = np.column_stack([np.interp(times, self.t, self.p_world_cam[:, k]) for k in range(3)])
        q = Slerp(self.t, Rotation.from_quat(self.q_xyzw))(times).as_quat()
        return Trajectory(times, p, q)

    def at(self, t: float) -> np.ndarray:
        """(4, 4) T_world_cam interpolated at time t (seconds, within the recorded range)."""
        return self.interpolate([float(t)]).T_world_cam()[0]


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM trajectory: "timestamp tx ty tz qx qy qz qw" per line, camera-to-world.

    '#' lines and blank lines are skipped. Quaternions within 1e-3 of unit length are
    normalised; further off, malformed lines and times not increasing raise SequenceError
    naming the line.
    """
    path = Path(path)
    a, linenos = _read_table(path, TRAJECTORY_COLUMNS, "trajectory (timestamp tx ty tz qx qy qz qw)")
    q = _unit_quaternions(a[:, 4:8], lambda i: f"{path}:{linenos[i]}")
    return Trajectory(a[:, 0], a[:, 1:4], q)


def write_trajectory(path: str | Path, t, poses, header: str | None = None) -> None:
    """Write a TUM trajectory that evo and the TUM scripts read.

    t : (N,) float, seconds, strictly increasing.
    poses : (N, 4, 4) T_world_cam, or a pair (p_world_cam (N, 3) metres, q_xyzw (N, 4)).
    header : optional free text, written as '#' lines above the column line.

    Times and positions are written with 9 decimals, quaternions with 12, so read_trajectory
    gives back times, positions and transforms to 1e-9.
    """
    traj = _trajectory(t, poses)
    rows = [_format_row(ti, np.r_[p, q], [_FMT_VALUE] * 3 + [_FMT_QUAT] * 4)
            for ti, p, q in zip(traj.t, traj.p_world_cam, traj.q_xyzw)]
    _write_rows(path, _header_lines(TRAJECTORY_COLUMNS, header, "camera-to-world, m"), rows)


def _trajectory(t, poses) -> Trajectory:
    if isinstance(poses, (tuple, list)) and len(poses) == 2:
        return Trajectory(t, poses[0], poses[1])
    return Trajectory.from_T_world_cam(t, poses)


# ---------------------------------------------------------------------------------------------
# IMU and joint encoder logs
# ---------------------------------------------------------------------------------------------

@dataclass
class ImuLog:
    """IMU samples in the camera's optical frame.

    t : (N,) float, seconds, strictly increasing.
    gyro : (N, 3) float, angular rate wx wy wz, rad/s.
    accel : (N, 3) float, specific force ax ay az, m/s^2.
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __post_init__(self):
        self.t = _as_times(self.t)
        self.gyro = _as_columns(self.gyro, len(self.t), 3, "gyro")
        self.accel = _as_columns(self.accel, len(self.t), 3, "accel")

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class JointLog:
    """Head encoder readings.

    t : (N,) float, seconds, strictly increasing.
    q : (N, 3) float, joint angles (elevation, pan, cyclotorsion), rad.
    """

    t: np.ndarray
    q: np.ndarray

    def __post_init__(self):
        self.t = _as_times(self.t)
        self.q = _as_columns(self.q, len(self.t), 3, "q")

    def __len__(self) -> int:
        return len(self.t)


def read_imu(path: str | Path) -> ImuLog:
    """Read imu.txt: "timestamp wx wy wz ax ay az" (rad/s, m/s^2, camera frame) per line."""
    a, _ = _read_table(path, IMU_COLUMNS, "IMU log (timestamp wx wy wz ax ay az)")
    return ImuLog(a[:, 0], a[:, 1:4], a[:, 4:7])


def write_imu(path: str | Path, t, gyro, accel, header: str | None = None) -> None:
    """Write imu.txt. t (N,) s; gyro (N, 3) rad/s; accel (N, 3) m/s^2; both in the camera frame."""
    log = ImuLog(t, gyro, accel)
    rows = [_format_row(ti, np.r_[w, a], [_FMT_VALUE] * 6) for ti, w, a in zip(log.t, log.gyro, log.accel)]
    _write_rows(path, _header_lines(IMU_COLUMNS, header, _IMU_UNITS), rows)


def read_joints(path: str | Path) -> JointLog:
    """Read joints.txt: "timestamp q_elevation q_pan q_cyclotorsion" (rad) per line."""
    a, _ = _read_table(path, JOINT_COLUMNS, "joint log (timestamp q_elevation q_pan q_cyclotorsion)")
    return JointLog(a[:, 0], a[:, 1:4])


def write_joints(path: str | Path, t, q, header: str | None = None) -> None:
    """Write joints.txt. t (N,) s; q (N, 3) elevation, pan, cyclotorsion in rad."""
    log = JointLog(t, q)
    rows = [_format_row(ti, qi, [_FMT_VALUE] * 3) for ti, qi in zip(log.t, log.q)]
    _write_rows(path, _header_lines(JOINT_COLUMNS, header, "rad"), rows)


# ---------------------------------------------------------------------------------------------
# target.toml
# ---------------------------------------------------------------------------------------------

#: target.toml needs at least this many points (enough for a unique camera pose from a plane).
MIN_TARGET_POINTS = 4


@dataclass
class Target:
    """Known points that fix the world frame and scale at start-up.

    xyz : (N, 3) float, world positions, metres; N >= 4.
    uv : (N, 2) float, their pixels in the first frame of rgb.txt (OpenCV convention).
    """

    xyz: np.ndarray
    uv: np.ndarray

    def __post_init__(self):
        self.xyz = np.asarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise SequenceError(f"target xyz must have shape (N, 3), got {self.xyz.shape}")
        n = len(self.xyz)
        if n < MIN_TARGET_POINTS:
            raise SequenceError(f"a target needs at least {MIN_TARGET_POINTS} points, got {n}")
        self.xyz = _as_columns(self.xyz, n, 3, "target xyz")
        self.uv = _as_columns(self.uv, n, 2, "target uv")

    def __len__(self) -> int:
        return len(self.xyz)


_TARGET_EXAMPLE = "[[point]] tables each with xyz = [x, y, z] (metres) and uv = [u, v] (pixels)"


def load_target(path: str | Path) -> Target:
    """Read and check a target.toml: at least 4 [[point]] tables, each with exactly
    xyz (3 numbers, metres, world frame) and uv (2 numbers, pixels in the first frame)."""
    path = Path(path)
    doc = read_toml(path, SequenceError, "the path of a target.toml")
    for k in doc:
        if k != "point":
            raise SequenceError(f"{path}: unknown top-level key {k!r}; target.toml holds only "
                                f"{_TARGET_EXAMPLE}, so remove it")
    points = doc.get("point", [])
    if not isinstance(points, list) or not all(isinstance(p, dict) for p in points):
        raise SequenceError(f"{path}: 'point' must be an array of tables; write {_TARGET_EXAMPLE}")
    if len(points) < MIN_TARGET_POINTS:
        raise SequenceError(f"{path}: {len(points)} [[point]] tables, but at least {MIN_TARGET_POINTS} "
                            f"are needed to fix the world frame; add points ({_TARGET_EXAMPLE})")
    xyz, uv = [], []
    for i, p in enumerate(points, start=1):
        where = f"{path}: [[point]] {i}"
        for k in p:
            if k not in ("xyz", "uv"):
                raise SequenceError(f"{where}: unknown key {k!r}; each point has only xyz and uv, "
                                    f"so remove it")
        xyz.append(_toml_vector(p, "xyz", 3, where, "metres, world frame, e.g. xyz = [-0.1, -0.07, 0.0]"))
        uv.append(_toml_vector(p, "uv", 2, where, "pixels in the first frame, e.g. uv = [243.2, 301.6]"))
    return Target(np.array(xyz), np.array(uv))


def _toml_vector(table: dict, key: str, dim: int, where: str, hint: str) -> list[float]:
    if key not in table:
        raise SequenceError(f"{where}: missing {key}; add {key} = [{dim} numbers] ({hint})")
    v = table[key]
    if (not isinstance(v, list) or len(v) != dim
            or not all(isinstance(x, numbers.Real) and not isinstance(x, bool) for x in v)):
        raise SequenceError(f"{where}: {key} = {v!r} must be {dim} numbers ({hint})")
    if not all(math.isfinite(x) for x in v):
        raise SequenceError(f"{where}: {key} = {v!r} is not finite; give finite numbers ({hint})")
    return [float(x) for x in v]


def save_target(target: Target, path: str | Path) -> None:
    """Write target.toml; load_target gives back the same points exactly (tomli_w writes the
    shortest repr of each float)."""
    doc = {"point": [{"xyz": [float(x) for x in p], "uv": [float(x) for x in u]}
                     for p, u in zip(target.xyz, target.uv)]}
    Path(path).write_text(tomli_w.dumps(doc))


# ---------------------------------------------------------------------------------------------
# Image sequences
# ---------------------------------------------------------------------------------------------

@dataclass
class Frame:
    """One entry of rgb.txt.

    index : position in rgb.txt (0-based, counting image lines only).
    t : timestamp, seconds.
    path : the image file (absolute, or as rgb.txt gives it if that is absolute).
    image : np.uint8, (H, W) grey or (H, W, 3) RGB; None if the image could not be used.
    problem : why image is None (missing, unreadable, corrupt, wrong size); None otherwise.
    """

    index: int
    t: float
    path: Path
    image: np.ndarray | None
    problem: str | None = None

    @property
    def ok(self) -> bool:
        return self.image is not None


def _load_image(path: Path, width: int, height: int) -> tuple[np.ndarray | None, str | None]:
    """(image, None) or (None, problem). Never raises: one bad frame must not end a run."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None, f"{path}: no such file"
    except OSError as e:
        return None, f"{path}: cannot read ({e.strerror or e})"
    # imdecode rather than imread: it separates a missing file from a corrupt one, and reads
    # paths OpenCV's own file layer may not (non-ASCII names on some platforms).
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    except cv2.error:
        img = None
    if img is None:
        return None, f"{path}: not a readable image (corrupt, truncated or not an image file)"
    if img.dtype == np.uint16:
        # 65535 -> 255 exactly: divide by 257 with rounding.
        img = ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        return None, f"{path}: pixel type {img.dtype} not supported; store 8- or 16-bit images"
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        if img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)  # alpha carries nothing for tracking
        else:
            return None, f"{path}: {img.shape[2]} channels; store grey, colour or colour+alpha images"
    h, w = img.shape[:2]
    if (w, h) != (width, height):
        return None, f"{path}: image is {w}x{h} but camera.toml says {width}x{height}"
    return np.ascontiguousarray(img), None


@dataclass
class Sequence:
    """An image sequence folder (see the module docstring); build it with :func:`open_sequence`.

    root : the folder.
    camera : its camera.toml.
    timestamps : (N,) float, seconds, strictly increasing, from rgb.txt.
    paths : N image paths (root joined with rgb.txt's relative paths).
    target, groundtruth, imu, joints : the optional files, None when absent.
    """

    root: Path
    camera: CameraIntrinsics
    timestamps: np.ndarray
    paths: list[Path]
    target: Target | None = None
    groundtruth: Trajectory | None = None
    imu: ImuLog | None = None
    joints: JointLog | None = None
    depth_timestamps: np.ndarray | None = None
    depth_paths: list[Path] | None = None

    def __len__(self) -> int:
        return len(self.timestamps)

    def frame(self, index: int) -> Frame:
        """Load frame ``index`` (0-based); a bad image gives image=None and a problem."""
        index = range(len(self))[index]  # IndexError for out of range; negative indices work
        path = self.paths[index]
        image, problem = _load_image(path, self.camera.width, self.camera.height)
        return Frame(index, float(self.timestamps[index]), path, image, problem)

    def depth(self, index: int) -> np.ndarray | None:
        """Depth image (H, W) float32 of frame ``index``, metres along the optic axis (NaN where
        there is none), or None if the sequence has no depth for that frame's time."""
        if self.depth_paths is None:
            return None
        t = self.timestamps[index]
        j = int(np.argmin(np.abs(self.depth_timestamps - t)))
        if abs(self.depth_timestamps[j] - t) > 1e-6:
            return None
        raw = cv2.imread(str(self.depth_paths[j]), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16:
            raise SequenceError(f"{self.depth_paths[j]}: not a 16-bit depth PNG; depth images hold metres x "
                                f"{DEPTH_SCALE:g} as uint16")
        d = raw.astype(np.float32) / DEPTH_SCALE
        d[raw == 0] = np.nan
        return d

    def frames(self) -> Iterator[Frame]:
        """Every frame in rgb.txt order, loaded one at a time; never raises for bad images."""
        for i in range(len(self)):
            yield self.frame(i)


def open_sequence(path: str | Path, allow_incomplete: bool = False) -> Sequence:
    """Open a sequence folder: rgb.txt and camera.toml (required) and the optional
    target.toml, groundtruth.txt, imu.txt, joints.txt and depth.txt.

    Images are not read here (see :meth:`Sequence.frames`). File errors raise SequenceError,
    except camera.toml's, which raise kinematics.camera.CameraFileError naming the file.
    A recording whose writer has not finished (the ``INCOMPLETE`` marker of
    :mod:`kinematics.outdir`: still running, or killed) is refused, because its shorter files
    look whole; ``allow_incomplete`` reads what it holds (every line on disk is whole).
    """
    root = Path(path)
    if not root.is_dir():
        raise SequenceError(f"{root}: not a folder; give a sequence folder holding rgb.txt and "
                            f"camera.toml ({_SEQUENCE_FILES})")
    if not allow_incomplete:
        try:
            check_complete(root, "recording")
        except OutputFolderError as e:
            raise SequenceError(str(e)) from None
    cam_path = root / "camera.toml"
    if not cam_path.is_file():
        raise SequenceError(f"{cam_path}: missing; every sequence needs a camera.toml with a [camera] "
                            f"table (width, height, fx, fy, cx, cy; {_SEQUENCE_FILES})")
    camera = load_camera(cam_path)
    times, paths = _read_rgb_list(root / "rgb.txt")

    def optional(name, reader):
        p = root / name
        return reader(p) if p.exists() else None

    d_times, d_paths = _read_rgb_list(root / "depth.txt", "depth.txt") if (root / "depth.txt").exists() \
        else (None, None)
    return Sequence(root=root, camera=camera, timestamps=times, paths=paths,
                    depth_timestamps=d_times, depth_paths=d_paths,
                    target=optional("target.toml", load_target),
                    groundtruth=optional("groundtruth.txt", read_trajectory),
                    imu=optional("imu.txt", read_imu),
                    joints=optional("joints.txt", read_joints))


def _read_rgb_list(path: Path, name: str = "rgb.txt") -> tuple[np.ndarray, list[Path]]:
    """rgb.txt (or depth.txt) -> timestamps (N,) s and image paths relative to its folder."""
    if not path.is_file():
        raise SequenceError(f"{path}: missing; a sequence lists its images in rgb.txt, one "
                            f"'timestamp path' per line ({_SEQUENCE_FILES})")
    times, paths, prev_t, prev_n = [], [], -math.inf, 0
    for n, s in _read_lines(path, name):
        parts = s.split(maxsplit=1)  # the path may contain spaces
        if len(parts) != 2:
            raise SequenceError(f"{path}:{n}: expected 'timestamp path', got {s!r}; fix the line or "
                                f"start it with '#'")
        try:
            t = float(parts[0])
        except ValueError:
            raise SequenceError(f"{path}:{n}: timestamp {parts[0]!r} is not a number; each line is "
                                f"'timestamp path'") from None
        if not math.isfinite(t):
            raise SequenceError(f"{path}:{n}: timestamp {parts[0]!r} is not finite; give seconds")
        if not t > prev_t:
            raise SequenceError(f"{path}:{n}: timestamp {parts[0]} is not after {prev_t!r} on line "
                                f"{prev_n}; images must be listed in increasing time order")
        prev_t, prev_n = t, n
        times.append(t)
        paths.append(path.parent / parts[1].strip())
    return np.array(times, dtype=np.float64), paths


def check_new_recording(root: str | Path) -> Path:
    """Refuse, before any work, a folder a new recording cannot be written into: one that cannot
    be created or written (kinematics.outdir.check_output), or that already holds a sequence."""
    root = Path(root)
    try:
        check_folder(root, RECORDING)      # another command's folder, a finished recording, a live writer
    except OutputFolderError as e:
        raise SequenceError(str(e)) from None
    if (root / "rgb.txt").exists() and not (root / "INCOMPLETE").exists():
        raise SequenceError(f"{root / 'rgb.txt'}: already exists; record into a new folder, or delete {root} first")
    return root


class SequenceWriter:
    """Record a sequence folder as it happens (a context manager).

    ``SequenceWriter(root, camera, target=None)`` writes camera.toml (and target.toml) at once,
    then each ``add_*`` call appends one line to its text file and flushes it, so every line on
    disk is whole. Files a recording never adds to (groundtruth.txt, imu.txt, joints.txt,
    depth.txt) are not created.

    The folder is written inside :func:`kinematics.outdir.output_folder`: locked, and marked
    ``INCOMPLETE`` until :meth:`close` (or the end of a ``with`` block that did not raise), so a
    recording that is killed or fails is refused by :func:`open_sequence` instead of passing for
    a shorter whole one.

    root : the folder, created if needed; refused if it already holds an rgb.txt, unless
        overwrite=True (then the old text files are replaced; old images stay until overwritten).
    camera : the intrinsics; add_frame checks each image's size against them.
    target : optional known points (uv in the first frame).
    """

    def __init__(self, root: str | Path, camera: CameraIntrinsics, target: Target | None = None,
                 overwrite: bool = False):
        self.root = Path(root)
        self.camera = camera
        if not overwrite and not writing(self.root):     # a command's own folder (a session) it judged
            check_new_recording(self.root)
        self._files: dict[str, TextIO] = {}
        self._closed = True
        self._folder = ExitStack()
        self._folder.enter_context(output_folder(self.root, kind=RECORDING, reuse=overwrite))
        self._last_t: dict[str, float] = {}
        self._last_name: str | None = None  # the previous frame's image, rgb/<t>.png
        try:
            (self.root / "rgb").mkdir(parents=True, exist_ok=True)
            if overwrite:
                # Optional files of the old recording would otherwise be read as this one's.
                for name in ("target.toml", "groundtruth.txt", "imu.txt", "joints.txt", "depth.txt"):
                    (self.root / name).unlink(missing_ok=True)
            save_camera(camera, self.root / "camera.toml")
            if target is not None:
                self.set_target(target)
            self._closed = False
            self._open("rgb.txt", ["# timestamp filename  (image sequence, paths relative to this folder)"])
        except BaseException as e:
            self._close((type(e), e, e.__traceback__))
            raise

    # -- context manager --
    def __enter__(self) -> "SequenceWriter":
        return self

    def __exit__(self, *exc) -> None:
        self._close(exc)

    def close(self) -> None:
        """Close every file and mark the recording complete (idempotent)."""
        self._close((None, None, None))

    def _close(self, exc) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()
        self._closed = True
        # An exception leaves the INCOMPLETE marker in place (output_folder's exit sees it).
        self._folder.__exit__(*exc)

    # -- writing --
    def set_target(self, target: Target) -> None:
        """Write (or replace) target.toml, e.g. once the target is found in the first frame."""
        save_target(target, self.root / "target.toml")

    def add_frame(self, t: float, image: np.ndarray) -> Path:
        """Save an image as rgb/<t>.png and list it in rgb.txt.

        t : seconds, after the previous frame's (by at least 1 us, the file-name resolution).
        image : (H, W) grey or (H, W, 3) RGB, uint8 (or uint16), H x W as camera.toml says.
        Returns the image's path.
        """
        t = float(t)
        image = np.asarray(image)
        if image.dtype not in (np.uint8, np.uint16):
            raise SequenceError(f"image dtype {image.dtype} not supported; convert to uint8 (or uint16)")
        if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
            raise SequenceError(f"image shape {image.shape} must be (H, W) grey or (H, W, 3) RGB")
        if image.shape[:2] != (self.camera.height, self.camera.width):
            raise SequenceError(f"image is {image.shape[1]}x{image.shape[0]} but camera.toml says "
                                f"{self.camera.width}x{self.camera.height}; resize it or fix the camera")
        self._check_time("rgb.txt", t)
        name = f"rgb/{_FMT_IMAGE_NAME % t}.png"
        if name == self._last_name:
            raise SequenceError(f"frame time {t!r} names the same file {name} as the previous frame; "
                                f"frames must be at least 1 us apart")
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
        path = self._write_png(name, bgr)
        self._last_name = name
        self._append("rgb.txt", f"{_FMT_TIME % t} {name}", t)
        return path

    def add_depth(self, t: float, depth_m: np.ndarray) -> Path:
        """Save a depth image as depth/<t>.png (uint16, metres x 5000; NaN, <= 0 or beyond
        13.1 m become 0, "no depth") and list it in depth.txt. depth_m : (H, W) metres along the
        optic axis."""
        t = float(t)
        d = np.asarray(depth_m, dtype=np.float64)
        if d.shape != (self.camera.height, self.camera.width):
            raise SequenceError(f"depth image shape {d.shape} must be ({self.camera.height}, {self.camera.width}) "
                                f"as camera.toml says")
        self._check_time("depth.txt", t)
        raw = np.round(np.nan_to_num(d, nan=0.0) * DEPTH_SCALE)
        raw[(raw <= 0) | (raw > 65535)] = 0
        name = f"depth/{_FMT_IMAGE_NAME % t}.png"
        (self.root / "depth").mkdir(exist_ok=True)
        path = self._write_png(name, raw.astype(np.uint16))
        self._line("depth.txt", ["# timestamp filename  (depth images: uint16, metres x 5000 along the optic "
                                 "axis, 0 = none)"], f"{_FMT_TIME % t} {name}", t)
        return path

    def add_groundtruth(self, t: float, T_world_cam: np.ndarray) -> None:
        """Append a pose: t seconds, T_world_cam (4, 4) camera-to-world, metres."""
        self._check_time("groundtruth.txt", t)
        p, q = _rotations_from_T(np.asarray(T_world_cam, dtype=np.float64)[None], "T_world_cam")
        self._line("groundtruth.txt", _header_lines(TRAJECTORY_COLUMNS, None, "camera-to-world, m"),
                   _format_row(t, np.r_[p[0], q[0]], [_FMT_VALUE] * 3 + [_FMT_QUAT] * 4), t)

    def add_imu(self, t: float, gyro, accel) -> None:
        """Append an IMU sample: t s, gyro (3,) rad/s, accel (3,) m/s^2, camera frame."""
        self._check_time("imu.txt", t)
        w = _as_columns(np.reshape(gyro, (1, -1)), 1, 3, "gyro")[0]
        a = _as_columns(np.reshape(accel, (1, -1)), 1, 3, "accel")[0]
        self._line("imu.txt", _header_lines(IMU_COLUMNS, None, _IMU_UNITS),
                   _format_row(t, np.r_[w, a], [_FMT_VALUE] * 6), t)

    def add_joints(self, t: float, q) -> None:
        """Append encoder readings: t s, q (3,) elevation, pan, cyclotorsion in rad."""
        self._check_time("joints.txt", t)
        q = _as_columns(np.reshape(q, (1, -1)), 1, 3, "q")[0]
        self._line("joints.txt", _header_lines(JOINT_COLUMNS, None, "rad"),
                   _format_row(t, q, [_FMT_VALUE] * 3), t)

    # -- internals --
    def _write_png(self, name: str, image: np.ndarray) -> Path:
        """Encode ``image`` (OpenCV channel order) as root/name. Written to a temporary name and
        renamed, so that a list file never names a half-written image, even if the process
        dies mid-write."""
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise SequenceError(f"{self.root / name}: OpenCV could not encode the image as PNG")
        path = self.root / name
        tmp = path.with_name(path.name + ".part")
        tmp.write_bytes(png.tobytes())
        os.replace(tmp, path)
        return path

    def _open(self, name: str, header: list[str]) -> None:
        f = open(self.root / name, "w", encoding="utf-8")
        f.write("\n".join(header) + "\n")
        f.flush()
        self._files[name] = f

    def _check_time(self, name: str, t: float) -> None:
        t = float(t)  # numpy scalars would print as np.float64(...) in the messages
        if self._closed:
            raise SequenceError(f"{self.root}: the SequenceWriter is closed; open a new one")
        if not math.isfinite(t):
            raise SequenceError(f"{self.root / name}: time {t!r} is not finite; give seconds")
        last = self._last_t.get(name)
        if last is not None and not t > last:
            raise SequenceError(f"{self.root / name}: time {t!r} is not after the previous {last!r}; "
                                f"add samples in increasing time order")

    def _line(self, name: str, header: list[str], line: str, t: float) -> None:
        if name not in self._files:
            self._open(name, header)  # created on first use, so unused files stay absent
        self._append(name, line, t)

    def _append(self, name: str, line: str, t: float) -> None:
        f = self._files[name]
        f.write(line + "\n")
        f.flush()  # a killed process loses at most the line being written
        self._last_t[name] = float(t)
