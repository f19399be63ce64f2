"""16-bit depth images (TUM RGB-D's): checked from their PNG header, and read to metres.

A depth PNG holds the depth along the optic axis in units of 1/depth_scale metre (TUM: 5000
per metre, 0.2 mm steps, 0 = no depth), registered to the colour image, so of its size. An
8-bit PNG (an export that lost the range) or one of another size is refused with one line
naming the file, at open (from the PNG header alone) and on read.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics

from .types import DEPTH_SCALE, SequenceError

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_FIX_16BIT = "depth images are 16-bit PNGs of metres x depth_scale (TUM: 5000); export them as uint16"


def _size_problem(path: Path, w: int, h: int, camera: CameraIntrinsics) -> str | None:
    if (w, h) != (camera.width, camera.height):
        return (f"{path}: depth image is {w}x{h} but camera.toml says {camera.width}x{camera.height}; give depth "
                f"registered to the colour images, at their size")
    return None


def check_depth_png(path: str | Path, camera: CameraIntrinsics) -> None:
    """Check a depth PNG from its header (no decoding): it exists, is a 16-bit single-channel PNG,
    and is of camera.toml's size; else SequenceError naming the file and the fix."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(29)
    except FileNotFoundError:
        raise SequenceError(f"{path}: no such file; depth.txt lists it, so add the image or remove its line") from None
    except OSError as e:
        raise SequenceError(f"{path}: cannot read ({e.strerror or e}); check the file's permissions") from None
    if len(head) < 29 or head[:8] != _PNG_MAGIC or head[12:16] != b"IHDR":
        raise SequenceError(f"{path}: not a PNG; {_FIX_16BIT}")
    w, h, bits, colour = *struct.unpack(">II", head[16:24]), head[24], head[25]
    if bits != 16 or colour != 0:
        kind = f"{bits}-bit" + ("" if colour == 0 else " colour")
        raise SequenceError(f"{path}: the PNG is {kind}, not a 16-bit grey depth image; {_FIX_16BIT}")
    problem = _size_problem(path, w, h, camera)
    if problem:
        raise SequenceError(problem)


def read_depth(path: str | Path, camera: CameraIntrinsics, depth_scale: float = DEPTH_SCALE) -> np.ndarray:
    """A depth PNG -> (H, W) float32 metres along the optic axis, NaN where the image holds 0.

    Refuses (SequenceError, naming the file and the fix) an unreadable file, an 8-bit or colour
    image, and an image whose size is not camera.toml's.
    """
    path = Path(path)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SequenceError(f"{path}: missing or not a readable image; {_FIX_16BIT}")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        kind = f"{raw.dtype.itemsize * 8}-bit" + ("" if raw.ndim == 2 else f" {raw.shape[2]}-channel")
        raise SequenceError(f"{path}: the image is {kind}, not a 16-bit grey depth image; {_FIX_16BIT}")
    problem = _size_problem(path, raw.shape[1], raw.shape[0], camera)
    if problem:
        raise SequenceError(problem)
    d = raw.astype(np.float32) / np.float32(depth_scale)
    d[raw == 0] = np.nan
    return d
