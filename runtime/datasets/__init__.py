"""Public benchmarks read as they are shipped (shared/formats.md, "Public layouts read as shipped").

- :mod:`.euroc`: EuRoC / ASL ``mav0/`` folders (cam0, imu0 through the camera-IMU extrinsics,
  the body's ground truth made the camera's), nanosecond stamps kept exact.
- :mod:`.kitti`: KITTI odometry sequences (image_0/, times.txt, calib.txt's P0, poses/NN.txt).
- :mod:`.tum`: our own (TUM RGB-D) layout, with checked 16-bit depth images; a TUM RGB-D folder as
  shipped (no camera.toml) takes its Freiburg camera's published calibration.

:func:`open_any` recognises each and returns a :class:`DatasetSequence` (a
:class:`runtime.sequence.Sequence`, so ``wvr slam`` runs on it directly); ``convert_euroc`` and
``convert_kitti`` write our layout (``wvr convert``).
"""

from __future__ import annotations

from pathlib import Path

from .common import DatasetSequence, ns_to_seconds, ns_to_text, read_stamps_ns
from .euroc import convert_euroc, find_mav0, open_euroc
from .kitti import convert_kitti, is_kitti, open_kitti
from .tum import FREIBURG_CAMERAS, check_depth_png, freiburg_camera, open_tum, read_depth

__all__ = ["DatasetSequence", "open_any", "dataset_kind", "open_euroc", "open_kitti", "open_tum", "convert_euroc",
           "convert_kitti", "read_depth", "check_depth_png", "FREIBURG_CAMERAS", "freiburg_camera", "read_stamps_ns",
           "ns_to_text", "ns_to_seconds"]


def dataset_kind(path: str | Path) -> str:
    """"tum" for a folder with rgb.txt (our layout), "euroc" for a mav0 folder (or the folder
    holding mav0), "kitti" for a KITTI odometry sequence folder, else "tum" (which
    open_sequence then refuses with its own message)."""
    if (Path(path) / "rgb.txt").is_file():
        return "tum"
    if find_mav0(path) is not None:
        return "euroc"
    if is_kitti(path):
        return "kitti"
    return "tum"


def open_any(path: str | Path) -> DatasetSequence:
    """Open a sequence in any layout wvr reads: EuRoC, KITTI odometry, or ours (TUM RGB-D).

    The public layouts are read as shipped with their own ground truth (EuRoC's
    state_groundtruth_estimate0, KITTI's poses/NN.txt); to use another ground truth, convert
    with it (convert_euroc(groundtruth=...), convert_kitti(poses=...)) or call the reader.
    """
    kind = dataset_kind(path)
    if kind == "euroc":
        return open_euroc(path)
    if kind == "kitti":
        return open_kitti(path)
    return open_tum(path)
