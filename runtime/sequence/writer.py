"""Recording a sequence folder as it happens: :class:`SequenceWriter` appends whole lines and
whole images, inside :func:`kinematics.outdir.output_folder` so an unfinished recording is
refused by :func:`~runtime.sequence.open_sequence`."""

from __future__ import annotations

import math
import os
from contextlib import ExitStack
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, save_camera
from kinematics.outdir import OutputFolderError, check_folder, output_folder, writing

from .textfiles import (_FMT_IMAGE_NAME, _FMT_QUAT, _FMT_TIME, _FMT_VALUE, _IMU_UNITS, _format_row, _header_lines,
                        save_target)
from .types import (DEPTH_SCALE, IMU_COLUMNS, JOINT_COLUMNS, RECORDING, TRAJECTORY_COLUMNS, SequenceError, Target,
                    _as_columns, _rotations_from_T)


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
