"""KITTI odometry sequences read as shipped, and converted to our layout.

::

    sequences/NN/
      image_0/NNNNNN.png   the left grey camera; the number is the frame's row in times.txt
      times.txt            one time per frame, seconds from the sequence's start
      calib.txt            "P0: " + 12 numbers, the left camera's 3x4 projection [K | 0]
    poses/NN.txt           optional: 12 numbers per frame, the 3x4 camera-to-world pose of
                           camera 0 in the first frame's camera frame (the ground truth)

The poses file is taken from ``poses=`` if given, else the sequence folder's ``poses/NN.txt``
(or its only ``poses/*.txt``), else the data set's own place, ``../../poses/NN.txt``.
Images may be a subset of the frames (a folder holding 000000-000159 of a 1101-frame
times.txt): each image's number picks its row; times.txt (and poses) must cover every image,
and poses must have one row per times.txt row.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraFileError, CameraIntrinsics
from runtime.sequence import SequenceError, Trajectory

from .common import DatasetSequence, check_increasing, data_rows, ns_to_seconds, numbers, parse_seconds_ns, \
    rigid_batch, write_layout

_IMAGE_NAME = re.compile(r"^(\d+)\.png$")


def is_kitti(path: str | Path) -> bool:
    """Whether ``path`` looks like a KITTI odometry sequence folder (image_0/ and times.txt)."""
    path = Path(path)
    return (path / "image_0").is_dir() and (path / "times.txt").is_file()


def read_calib(path: str | Path) -> tuple[float, float, float, float]:
    """calib.txt's P0 line -> (fx, fy, cx, cy), pixels. P0 must be [K | 0] with K upper
    triangular, zero skew and K[2] = [0, 0, 1] (a rectified camera)."""
    path = Path(path)
    P0 = None
    for n, f in data_rows(path, "KITTI calib.txt (lines 'P0: ' + 12 numbers)", sep=None):
        if f[0] == "P0:":
            if len(f) != 13:
                raise SequenceError(f"{path}:{n}: P0 has {len(f) - 1} numbers, expected 12 (a 3x4 projection, row "
                                    f"by row); fix the line")
            P0 = np.array(numbers(f[1:], f"{path}:{n}", "P0: 12 numbers"), dtype=np.float64).reshape(3, 4)
            break
    if P0 is None:
        raise SequenceError(f"{path}: no 'P0:' line; calib.txt needs the left camera's projection, 'P0: fx 0 cx 0 "
                            f"0 fy cy 0 0 0 1 0' (copy it from the data set's calib.txt)")
    fx, fy, cx, cy = P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2]
    K_like = np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0]])
    if not np.allclose(P0, K_like, rtol=0, atol=1e-9):
        raise SequenceError(f"{path}: P0 is not [K | 0] with zero skew (got {P0.ravel().tolist()}); P0 is camera "
                            f"0's own projection, 'fx 0 cx 0 0 fy cy 0 0 0 1 0'")
    return float(fx), float(fy), float(cx), float(cy)


def read_times(path: str | Path) -> np.ndarray:
    """times.txt -> (N,) int64 ns, exact from the decimal text, strictly increasing."""
    path = Path(path)
    ns, lines = [], []
    for n, f in data_rows(path, "KITTI times.txt (one time in seconds per line)", sep=None):
        if len(f) != 1:
            raise SequenceError(f"{path}:{n}: {len(f)} fields, expected one time in seconds; fix the line")
        ns.append(parse_seconds_ns(f[0], f"{path}:{n}"))
        lines.append(n)
    check_increasing(ns, lines, path)
    return np.array(ns, dtype=np.int64)


def read_poses(path: str | Path) -> np.ndarray:
    """A KITTI poses file -> (N, 4, 4) camera-to-world transforms, rotations re-orthonormalised
    (the file's 7 digits leave them about 1e-7 off)."""
    path = Path(path)
    rows, lines = [], []
    for n, f in data_rows(path, "KITTI poses file (12 numbers per line)", sep=None):
        if len(f) != 12:
            raise SequenceError(f"{path}:{n}: {len(f)} numbers, expected 12 (the 3x4 camera-to-world pose, row by "
                                f"row); fix the line")
        rows.append(numbers(f, f"{path}:{n}", "12 numbers, a 3x4 pose row by row"))
        lines.append(n)
    T = np.zeros((len(rows), 4, 4))
    T[:, :3, :] = np.array(rows, dtype=np.float64).reshape(-1, 3, 4)
    T[:, 3, 3] = 1.0
    return rigid_batch(T, lambda i: f"{path}:{lines[i]}")


def find_poses(root: Path) -> Path | None:
    """The sequence's poses file: root/poses/<name>.txt, root/poses' only .txt, or the data set's
    ../../poses/<name>.txt; None if there is none."""
    own = root / "poses" / f"{root.name}.txt"
    if own.is_file():
        return own
    found = sorted((root / "poses").glob("*.txt")) if (root / "poses").is_dir() else []
    if len(found) == 1:
        return found[0]
    shipped = root.resolve().parent.parent / "poses" / f"{root.resolve().name}.txt"
    return shipped if shipped.is_file() else None


def open_kitti(path: str | Path, poses: str | Path | None = None) -> DatasetSequence:
    """Read a KITTI odometry sequence folder (image_0/, times.txt, calib.txt; poses where found)
    as a sequence of the left grey camera. Errors (calib.txt without P0, times.txt or poses not
    covering the images, times out of order) raise SequenceError naming the file and the fix."""
    root = Path(path)
    if not is_kitti(root):
        raise SequenceError(f"{root}: not a KITTI odometry sequence; give the folder holding image_0/, times.txt "
                            f"and calib.txt")
    fx, fy, cx, cy = read_calib(root / "calib.txt")
    times_path = root / "times.txt"
    times_ns = read_times(times_path)
    index, paths = [], []
    for p in sorted((root / "image_0").iterdir()):
        m = _IMAGE_NAME.match(p.name)
        if m:
            index.append(int(m.group(1)))
            paths.append(p)
    if not paths:
        raise SequenceError(f"{root / 'image_0'}: no NNNNNN.png images; put the left camera's frames there")
    order = np.argsort(index, kind="stable")
    index = np.array(index)[order]
    paths = [paths[i] for i in order]
    if index[-1] >= len(times_ns):
        raise SequenceError(f"{times_path}: {len(times_ns)} times, but image_0 holds {paths[-1].name} (frame "
                            f"{index[-1]}); times.txt needs one line per frame, so use the sequence's own times.txt")
    first = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise SequenceError(f"{paths[0]}: not a readable image; the first frame gives the image size")
    try:
        cam = CameraIntrinsics(width=first.shape[1], height=first.shape[0], fx=fx, fy=fy, cx=cx, cy=cy)
    except CameraFileError as e:
        raise SequenceError(f"{root / 'calib.txt'}: {e}") from None
    gt = None
    poses_path = Path(poses) if poses is not None else find_poses(root)
    if poses_path is not None:
        T_world_cam = read_poses(poses_path)
        if len(T_world_cam) != len(times_ns):
            raise SequenceError(f"{poses_path}: {len(T_world_cam)} poses but {times_path} has {len(times_ns)} times; "
                                f"give the poses file of this sequence (one pose per line of times.txt)")
        R = T_world_cam[:, :3, :3]
        gt = Trajectory(ns_to_seconds(times_ns), T_world_cam[:, :3, 3], Rotation.from_matrix(R).as_quat())
    stamps_ns = times_ns[index]
    return DatasetSequence(root=root, camera=cam, timestamps=ns_to_seconds(stamps_ns), paths=paths, groundtruth=gt,
                           source="kitti", stamps_ns=stamps_ns, groundtruth_ns=times_ns if gt is not None else None)


def convert_kitti(src: str | Path, dst: str | Path, poses: str | Path | None = None,
                  copy: bool = False) -> DatasetSequence:
    """Write a KITTI odometry sequence as a sequence folder in our layout (rgb.txt with links to,
    or with ``copy`` copies of, image_0's frames; camera.toml from P0; groundtruth.txt from the
    poses). Returns the sequence as read from ``src``."""
    seq = open_kitti(src, poses)
    write_layout(seq, dst, copy=copy,
                 note=f"converted from the KITTI odometry sequence {Path(src).resolve()} by wvr convert kitti")
    return seq
