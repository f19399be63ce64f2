"""Opening a sequence folder (shared/formats.md): rgb.txt and camera.toml, the optional files,
and its images one at a time (a bad image is a frame with a problem, never an exception)."""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from kinematics.camera import CameraFileError, CameraIntrinsics
from kinematics.outdir import OutputFolderError, check_complete
from kinematics.tomlfile import read_toml

from .depth import read_depth
from .textfiles import _read_lines, load_target, read_imu, read_joints, read_trajectory
from .types import DEPTH_SCALE, Frame, ImuLog, JointLog, SequenceError, Target, Trajectory

_SEQUENCE_FILES = "see shared/formats.md"


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_fault(data: bytes) -> str | None:
    """Why a PNG's chunks are damaged (cut short, a CRC that does not match), or None (also for
    other formats). Checked before decoding: libpng prints its complaints about such a file
    straight to the process's stderr, around the one-line problem the frame carries."""
    if not data.startswith(_PNG_SIGNATURE):
        return None
    mv, i = memoryview(data), len(_PNG_SIGNATURE)
    while i + 12 <= len(data):
        n = int.from_bytes(mv[i:i + 4], "big")
        end = i + 12 + n
        if end > len(data):
            break
        if zlib.crc32(mv[i + 4:i + 8 + n]) != int.from_bytes(mv[i + 8 + n:end], "big"):
            return f"its {bytes(mv[i + 4:i + 8]).decode('latin-1')!r} chunk fails its CRC"
        if mv[i + 4:i + 8] == b"IEND":
            return None
        i = end
    return "truncated"


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
    fault = _png_fault(data)
    if fault is not None:
        return None, f"{path}: not a readable image (a damaged PNG: {fault})"
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
    depth_timestamps, depth_paths : depth.txt's, None when absent.
    depth_scale : depth image units per metre (camera.toml's depth_scale; TUM: 5000).
    depth_max_dt_s : a depth image belongs to the frame whose time is nearest, within this.
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
    depth_scale: float = DEPTH_SCALE
    # TUM RGB-D's depth and colour stamps differ by up to ~15 ms; 0.02 s is its associate.py's default.
    depth_max_dt_s: float = 0.02

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
        none), or None if no depth image is within ``depth_max_dt_s`` of the frame's time; a depth
        PNG that is 8-bit or of another size than camera.toml's raises SequenceError naming the file."""
        if self.depth_paths is None:
            return None
        t = self.timestamps[index]
        j = int(np.argmin(np.abs(self.depth_timestamps - t)))
        if abs(self.depth_timestamps[j] - t) > self.depth_max_dt_s:
            return None
        return read_depth(self.depth_paths[j], self.camera, self.depth_scale)

    def frames(self) -> Iterator[Frame]:
        """Every frame in rgb.txt order, loaded one at a time; never raises for bad images."""
        for i in range(len(self)):
            yield self.frame(i)


def open_sequence(path: str | Path, allow_incomplete: bool = False,
                  camera: CameraIntrinsics | None = None) -> Sequence:
    """Open a sequence folder: rgb.txt and camera.toml (required) and the optional
    target.toml, groundtruth.txt, imu.txt, joints.txt and depth.txt.

    ``camera``: the camera to use when the folder has no camera.toml (a public data set's
    published calibration, runtime.datasets.tum); a camera.toml in the folder comes first.

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
    if cam_path.is_file():
        # One read: the lens for the camera, and the depth images' units per metre (the camera's
        # reader has checked depth_scale, and leaves it out of the lens).
        doc = read_toml(cam_path, CameraFileError, "the path of a camera.toml")
        camera = CameraIntrinsics.from_dict(doc, source=str(cam_path))
        depth_scale = float(doc["camera"].get("depth_scale", DEPTH_SCALE))
    elif camera is not None:
        depth_scale = DEPTH_SCALE
    else:
        raise SequenceError(f"{cam_path}: missing; every sequence needs a camera.toml with a [camera] "
                            f"table (width, height, fx, fy, cx, cy; {_SEQUENCE_FILES})")
    times, paths = _read_rgb_list(root / "rgb.txt")

    def optional(name, reader):
        p = root / name
        return reader(p) if p.exists() else None

    d_times, d_paths = _read_rgb_list(root / "depth.txt", "depth.txt") if (root / "depth.txt").exists() \
        else (None, None)
    return Sequence(root=root, camera=camera, timestamps=times, paths=paths,
                    depth_timestamps=d_times, depth_paths=d_paths, depth_scale=depth_scale,
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
