"""TUM RGB-D folders (our own layout): exact stamps, every listed depth image checked at open
(runtime.sequence.depth), and, for a folder as the TUM RGB-D benchmark ships it (no camera.toml),
the published calibration of the Freiburg camera that recorded it."""

from __future__ import annotations

import re
from pathlib import Path

from kinematics.camera import CameraIntrinsics
from runtime.sequence import open_sequence
from runtime.sequence.depth import check_depth_png, read_depth
from runtime.sequence.types import SequenceError

from .common import DatasetSequence, as_dataset_sequence, read_stamps_ns

__all__ = ["FREIBURG_CAMERAS", "check_depth_png", "freiburg_camera", "open_tum", "read_depth"]

#: The colour cameras of the TUM RGB-D benchmark, as its site publishes them ("File formats",
#: intrinsic calibration; the same values as ORB-SLAM's TUM1-3.yaml): 640x480, OpenCV's
#: radial-tangential terms (d0..d4 = k1 k2 p1 p2 k3). Freiburg 3's images are already undistorted.
FREIBURG_CAMERAS = {
    1: CameraIntrinsics(640, 480, 517.306408, 516.469215, 318.643040, 255.313989, model="brown",
                        k1=0.262383, k2=-0.953104, p1=-0.005358, p2=0.002628, k3=1.163314),
    2: CameraIntrinsics(640, 480, 520.908620, 521.007327, 325.141442, 249.701764, model="brown",
                        k1=0.231222, k2=-0.784899, p1=-0.003257, p2=-0.000105, k3=0.917205),
    3: CameraIntrinsics(640, 480, 535.4, 539.2, 320.1, 247.6),
}

# The benchmark's files name their recording ("# file: 'rgbd_dataset_freiburg1_xyz.bag'"), and
# its folders are called after it.
_FREIBURG = re.compile(r"rgbd_dataset_freiburg([123])_")


def freiburg_camera(root: str | Path) -> tuple[int, CameraIntrinsics] | None:
    """(N, camera) when the folder ``root`` is a TUM RGB-D sequence recorded by Freiburg camera N
    (named in rgb.txt's header or the folder's name), else None."""
    root = Path(root)
    header = ""
    try:
        with open(root / "rgb.txt", encoding="utf-8", errors="replace") as f:
            for line in f:
                if not line.startswith("#"):
                    break
                header += line
    except OSError:
        return None
    m = _FREIBURG.search(header) or _FREIBURG.search(root.resolve().name + "_")
    return (int(m.group(1)), FREIBURG_CAMERAS[int(m.group(1))]) if m else None


def open_tum(path: str | Path, check_depth: bool = True) -> DatasetSequence:
    """Open a sequence folder in our layout (runtime.sequence.open_sequence) with its exact
    stamps, and check every depth image listed in depth.txt from its PNG header (``check_depth``
    False: leave a bad one to be skipped and counted where it is read, as scoring does). A TUM
    RGB-D folder as shipped (no camera.toml) takes its Freiburg camera's published calibration
    (its ``notes`` say so); a camera.toml in the folder comes first."""
    root = Path(path)
    shipped = root.is_dir() and not (root / "camera.toml").is_file()
    fr = freiburg_camera(root) if shipped else None
    try:
        seq = open_sequence(root, camera=fr[1] if fr else None)
    except SequenceError:
        if shipped and fr is None and (root / "rgb.txt").is_file():
            raise SequenceError(f"{root / 'camera.toml'}: missing, and the folder is not a TUM RGB-D recording "
                                f"whose camera is known (rgbd_dataset_freiburg1/2/3_...); write a camera.toml "
                                f"with a [camera] table (width, height, fx, fy, cx, cy; see shared/formats.md)"
                                ) from None
        raise
    stamps_ns = read_stamps_ns(seq.root / "rgb.txt")
    if check_depth and seq.depth_paths is not None:
        for p in seq.depth_paths:
            check_depth_png(p, seq.camera)
    return as_dataset_sequence(seq, source="tum", stamps_ns=stamps_ns,
                               groundtruth_ns=read_stamps_ns(seq.root / "groundtruth.txt")
                               if seq.groundtruth is not None else None,
                               imu_ns=read_stamps_ns(seq.root / "imu.txt") if seq.imu is not None else None,
                               notes=(f"{seq.root}: no camera.toml; the camera is TUM RGB-D's Freiburg {fr[0]} "
                                      f"(its published calibration)",) if fr else ())
