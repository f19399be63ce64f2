"""The text files of a sequence: TUM-style time series (trajectories, imu.txt, joints.txt; one
line of numbers per time, '#' comments) and target.toml, read with one-line errors naming the
file and line, and written so that reading gives the same numbers back (to 1e-9)."""

from __future__ import annotations

import math
import numbers
from pathlib import Path
from typing import Sequence as _Seq

import numpy as np
import tomli_w

from kinematics.textnumbers import first_non_number
from kinematics.tomlfile import read_toml

from .types import (IMU_COLUMNS, JOINT_COLUMNS, MIN_TARGET_POINTS, TRAJECTORY_COLUMNS, ImuLog, JointLog,
                    SequenceError, Target, Trajectory, _unit_quaternions)

_IMU_UNITS = "rad/s, m/s^2, camera frame"

# Digits written: %.9f keeps times, positions, rates and angles to 5e-10 (nanoseconds,
# sub-nanometre); quaternions get three more so that the rotation matrices rebuilt from them
# (quadratic in q) also reproduce to better than 1e-9.
_FMT_TIME = "%.9f"
_FMT_VALUE = "%.9f"
_FMT_QUAT = "%.12f"
_FMT_IMAGE_NAME = "%.6f"  # rgb/<t>.png, microseconds as the TUM data sets name them


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


def _read_table(path: str | Path, columns: tuple[str, ...], what: str,
                dropped: dict[str, int] | None = None) -> tuple[np.ndarray, list[int]]:
    """Read a file of ``len(columns)`` numbers per line.

    Returns the (N, len(columns)) float array and the file line number of each row (for later
    messages). Blank and '#' lines are skipped; a line with the wrong count of fields or a field
    that is not a number is an error naming the line. A non-finite number, or a timestamp not
    after the previous one, is too, unless ``dropped`` is given: then the row is dropped and
    counted there ("non_finite", "duplicate", "out_of_order"), as a sensor log's glitches are.
    The first column is the timestamp.
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
            bad = first_non_number(fields_)
            col = columns[fields_.index(bad)]
            raise SequenceError(f"{path}:{n}: {col} = {bad!r} is not a number; each line is "
                                f"'{layout}'") from None
        bad = next(((col, v) for col, v in zip(columns, row) if not math.isfinite(v)), None)
        if bad is not None:
            if dropped is not None:
                dropped["non_finite"] = dropped.get("non_finite", 0) + 1
                continue
            raise SequenceError(f"{path}:{n}: {bad[0]} = {bad[1]} is not finite; write a finite number "
                                f"or remove the line")
        if not row[0] > prev_t:
            if dropped is not None:
                key = "duplicate" if row[0] == prev_t else "out_of_order"
                dropped[key] = dropped.get(key, 0) + 1
                continue
            raise SequenceError(f"{path}:{n}: timestamp {row[0]!r} is not after {prev_t!r} on line "
                                f"{prev_n}; lines must be in increasing time order (sort the file)")
        prev_t, prev_n = row[0], n
        rows.append(row)
        linenos.append(n)
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(columns)), linenos


def _header_lines(columns: tuple[str, ...], header: str | None, units: str) -> list[str]:
    """'#' lines: the caller's free text (if any), then the column layout (as TUM files have)."""
    lines = [f"# {h}".rstrip() for h in header.splitlines()] if header else []
    lines.append(f"# {' '.join(columns)}" + (f"  ({units})" if units else ""))
    return lines


def _format_row(t: float, values: np.ndarray, fmts: _Seq[str]) -> str:
    return " ".join([_FMT_TIME % t] + [f % v for f, v in zip(fmts, values)])


def _write_rows(path: str | Path, header: list[str], rows: list[str]) -> None:
    Path(path).write_text("\n".join(header + rows) + "\n")


# ---------------------------------------------------------------------------------------------
# Trajectories (groundtruth.txt, and every trajectory wvr writes)
# ---------------------------------------------------------------------------------------------

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

def read_imu(path: str | Path) -> ImuLog:
    """Read imu.txt: "timestamp wx wy wz ax ay az" (rad/s, m/s^2, camera frame) per line. Rows
    with a non-finite number, a repeated or an earlier timestamp are dropped and counted
    (``ImuLog.dropped``): a sensor's glitches, not a broken file."""
    dropped: dict[str, int] = {}
    a, _ = _read_table(path, IMU_COLUMNS, "IMU log (timestamp wx wy wz ax ay az)", dropped)
    return ImuLog(a[:, 0], a[:, 1:4], a[:, 4:7], dropped)


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
