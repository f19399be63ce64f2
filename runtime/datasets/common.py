"""What the public data set readers share: exact nanosecond stamps, the sequence they return,
rigid transforms read from text, and the writer of our TUM layout.

Stamps
------
EuRoC stamps are integer nanoseconds since 1970 (about 1.4e18): a float64 of seconds holds them
only to about 0.24 us. So every reader keeps the stamps as exact ``int`` nanoseconds
(``DatasetSequence.stamps_ns`` etc., int64 arrays) beside the float seconds the rest of wvr uses,
and the writer prints seconds from the integers (``ns_to_text``: ``"1403636584.763555584"``), so
that the text is exact and :func:`read_stamps_ns` maps a converted file back to the nanoseconds.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, fields
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from kinematics.camera import save_camera
from kinematics.outdir import output_folder
from runtime.sequence import Sequence, SequenceError


NS_PER_S = 10**9

#: A rotation read from a text file (printed to 7-12 digits) is re-orthonormalised if R^T R is
#: within this of I; further off it is an error (a wrong matrix, not rounding).
ROTATION_TOL = 1e-3

# Values as runtime.sequence writes them: 9 decimals (sub-nanometre), quaternions 12.
_FMT_VALUE = "%.9f"
_FMT_QUAT = "%.12f"


# ---------------------------------------------------------------------------------------------
# Stamps
# ---------------------------------------------------------------------------------------------

def parse_ns(text: str, where: str) -> int:
    """Integer nanoseconds from a decimal string of nanoseconds ("1403636584763555584", or
    "1403636584763555584.0000000000" as ORB-SLAM3's ground truth writes them); a fraction is
    rounded to the nearest nanosecond. ``where`` (file:line) names the place in the message."""
    try:
        d = Decimal(text.strip())
    except InvalidOperation:
        raise SequenceError(f"{where}: timestamp {text.strip()!r} is not a number; the first column is "
                            f"the time in integer nanoseconds") from None
    if not d.is_finite() or d < 0:
        raise SequenceError(f"{where}: timestamp {text.strip()!r} is not a time; give integer nanoseconds")
    return _in_int64(int(d.to_integral_value()), text, where)


#: The largest stamp, ns: what int64 holds (about 292 years).
MAX_NS = 2**63 - 1


def _in_int64(ns: int, text: str, where: str) -> int:
    if abs(ns) > MAX_NS:
        raise SequenceError(f"{where}: timestamp {text.strip()!r} is beyond {MAX_NS / NS_PER_S:.3g} s, more than "
                            f"int64 nanoseconds hold; give the time in seconds (e.g. since the recording began)")
    return ns


def parse_seconds_ns(text: str, where: str) -> int:
    """Integer nanoseconds from a decimal string of seconds ("1.038752e-01", "1403636584.763555584"),
    exactly (decimal arithmetic, rounded to the nearest nanosecond)."""
    try:
        d = Decimal(text.strip())
    except InvalidOperation:
        raise SequenceError(f"{where}: timestamp {text.strip()!r} is not a number; give seconds") from None
    if not d.is_finite():
        raise SequenceError(f"{where}: timestamp {text.strip()!r} is not finite; give seconds")
    return _in_int64(int((d * NS_PER_S).to_integral_value()), text, where)


def ns_to_text(ns: int) -> str:
    """Exact seconds text of integer nanoseconds: 1403636584763555584 -> "1403636584.763555584"."""
    ns = int(ns)
    sign, ns = ("-", -ns) if ns < 0 else ("", ns)
    return f"{sign}{ns // NS_PER_S}.{ns % NS_PER_S:09d}"


def ns_to_seconds(ns) -> np.ndarray:
    """(N,) int nanoseconds -> (N,) float64 seconds, correctly rounded: the very floats that
    reading the exact text (:func:`ns_to_text`) gives, so a converted sequence's float times equal
    the directly read ones."""
    return np.array([float(ns_to_text(n)) for n in np.asarray(ns, dtype=np.int64).ravel()], dtype=np.float64)


def read_stamps_ns(path: str | Path) -> np.ndarray:
    """The first column of a TUM-layout text file (rgb.txt, groundtruth.txt, imu.txt, depth.txt)
    as exact int64 nanoseconds: the way back from a converted sequence to the data set's stamps."""
    path = Path(path)
    out = []
    for n, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append(parse_seconds_ns(s.split()[0], f"{path}:{n}"))
    return np.array(out, dtype=np.int64)


def check_increasing(ns: list[int], lines: list[int], path: Path) -> None:
    """Refuse nanosecond stamps that do not strictly increase, naming the first bad line."""
    for i in range(1, len(ns)):
        if ns[i] <= ns[i - 1]:
            raise SequenceError(f"{path}:{lines[i]}: timestamp {ns[i]} ns is not after {ns[i - 1]} ns on line "
                                f"{lines[i - 1]}; the rows must be in increasing time order (sort the file by "
                                f"its first column and drop repeated rows)")


def data_rows(path: Path, what: str, sep: str | None = ","):
    """(line number, fields) of every row of a CSV (sep ",") or whitespace (sep None) file that is
    not blank or a '#' comment."""
    if not path.is_file():
        raise SequenceError(f"{path}: no such file; give the {what}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise SequenceError(f"{path}: cannot read ({e}); give the {what} as plain text") from None
    for n, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield n, [f.strip() for f in (s.split(sep) if sep else s.split())]


def numbers(fields_: list[str], where: str, layout: str) -> list[float]:
    """Finite floats from text fields, or an error naming the line and the expected layout."""
    try:
        v = [float(x) for x in fields_]
    except ValueError:
        raise SequenceError(f"{where}: {', '.join(fields_)!r} holds a field that is not a number; each row is "
                            f"'{layout}'") from None
    if not all(np.isfinite(v)):
        raise SequenceError(f"{where}: a field is not finite; each row is '{layout}' with finite numbers")
    return v


# ---------------------------------------------------------------------------------------------
# Rigid transforms
# ---------------------------------------------------------------------------------------------

def rigid(T, where: str) -> np.ndarray:
    """A (4, 4) (or (3, 4)) rigid transform read from a file, its rotation re-orthonormalised
    (nearest rotation, SVD) when printed digits left it within ROTATION_TOL of one; else an error."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise SequenceError(f"{where}: not a finite 4x4 transform; give 16 numbers, row by row")
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9:
        raise SequenceError(f"{where}: the last row is {T[3].tolist()}, not [0, 0, 0, 1]; give a rigid transform")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOL or np.linalg.det(R) <= 0:
        raise SequenceError(f"{where}: the rotation block is not a rotation (R^T R != I or det <= 0); check "
                            f"the numbers and their row order")
    U, _, Vt = np.linalg.svd(R)
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def rigid_batch(T: np.ndarray, where) -> np.ndarray:
    """(N, 4, 4) rigid transforms, each as :func:`rigid` (``where(i)`` names row i)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero(~(err <= ROTATION_TOL) | ~(np.linalg.det(R) > 0))
    if bad.size:
        raise SequenceError(f"{where(int(bad[0]))}: the rotation is not a rotation (R^T R != I or det <= 0); "
                            f"check the 12 numbers (a 3x4 matrix, row by row)")
    U, _, Vt = np.linalg.svd(R)
    out = T.copy()
    out[:, :3, :3] = U @ Vt
    return out


# ---------------------------------------------------------------------------------------------
# The sequence the readers return
# ---------------------------------------------------------------------------------------------

@dataclass
class DatasetSequence(Sequence):
    """A :class:`runtime.sequence.Sequence` read from a public layout (or our own), with the
    data set's exact stamps. Everything that takes a Sequence (``wvr slam``) takes it.

    source : "euroc", "kitti" or "tum" (our layout).
    stamps_ns : (N,) int64, each frame's exact time, ns (``timestamps`` are these in float s).
    groundtruth_ns, imu_ns : (M,) int64 exact times of the ground truth and IMU rows, or None.
    notes : what the reader adapted (one line each), for the user to see.
    """

    source: str = "tum"
    stamps_ns: np.ndarray | None = None
    groundtruth_ns: np.ndarray | None = None
    imu_ns: np.ndarray | None = None
    notes: tuple[str, ...] = ()

    def ns_at(self, t: float) -> int:
        """The exact ns stamp of the frame nearest ``t`` seconds (the map back from float times)."""
        return int(self.stamps_ns[int(np.argmin(np.abs(self.timestamps - float(t))))])


def as_dataset_sequence(seq: Sequence, **extra) -> DatasetSequence:
    """A base Sequence's fields plus ``extra`` (the DatasetSequence fields)."""
    return DatasetSequence(**{f.name: getattr(seq, f.name) for f in fields(Sequence)}, **extra)


# ---------------------------------------------------------------------------------------------
# Writing our layout
# ---------------------------------------------------------------------------------------------

def _refuse_existing(folder: Path) -> None:
    if (folder / "rgb.txt").exists():
        raise SequenceError(f"{folder / 'rgb.txt'}: already exists; convert into a new folder, or delete "
                            f"{folder} first")


def write_layout(seq: DatasetSequence, dst: str | Path, copy: bool = False, note: str = "") -> Path:
    """Write ``seq`` as a sequence folder in our TUM layout (shared/formats.md): rgb.txt,
    rgb/<the data set's file names>, camera.toml, groundtruth.txt and imu.txt where it has them.

    Images are symbolic links to the data set's files (absolute targets), or copies with
    ``copy=True`` (a folder that stands alone). Stamps are written from the exact nanoseconds
    (9 decimals of seconds), so :func:`read_stamps_ns` gives them back; values with 9 decimals,
    quaternions 12 (as runtime.sequence writes). The folder is marked INCOMPLETE until it is
    whole (kinematics.outdir), so an interrupted conversion is refused by readers.
    """
    dst = Path(dst)
    with output_folder(dst, check=_refuse_existing) as out:
        (out / "rgb").mkdir(exist_ok=True)
        names = [p.name for p in seq.paths]
        if len(set(names)) != len(names):  # e.g. images from several folders with one name
            names = [f"{i:06d}{p.suffix}" for i, p in enumerate(seq.paths)]
        rows = []
        for ns, src, name in zip(seq.stamps_ns, seq.paths, names):
            link = out / "rgb" / name
            link.unlink(missing_ok=True)
            if copy:
                shutil.copyfile(src, link)
            else:
                os.symlink(Path(src).resolve(), link)
            rows.append(f"{ns_to_text(ns)} rgb/{name}")
        head = [f"# {line}" for line in note.splitlines()] if note else []
        _write(out / "rgb.txt", head + ["# timestamp filename"], rows)
        save_camera(seq.camera, out / "camera.toml")
        if seq.groundtruth is not None:
            gt = seq.groundtruth
            rows = [" ".join([ns_to_text(ns)] + [_FMT_VALUE % v for v in p] + [_FMT_QUAT % v for v in q])
                    for ns, p, q in zip(seq.groundtruth_ns, gt.p_world_cam, gt.q_xyzw)]
            _write(out / "groundtruth.txt", head + ["# timestamp tx ty tz qx qy qz qw  (camera-to-world, m)"], rows)
        if seq.imu is not None:
            rows = [" ".join([ns_to_text(ns)] + [_FMT_VALUE % v for v in np.r_[w, a]])
                    for ns, w, a in zip(seq.imu_ns, seq.imu.gyro, seq.imu.accel)]
            _write(out / "imu.txt", head + ["# timestamp wx wy wz ax ay az  (rad/s, m/s^2, camera frame)"], rows)
    return dst


def _write(path: Path, header: list[str], rows: list[str]) -> None:
    path.write_text("\n".join(header + rows) + "\n")
