"""TUM RGB-D folders (our own layout): exact stamps, and every listed depth image checked at
open (runtime.datasets.depth)."""

from __future__ import annotations

import math
from pathlib import Path

from kinematics.tomlfile import read_toml
from runtime.sequence import DEPTH_SCALE, SequenceError, open_sequence

from .common import DatasetSequence, as_dataset_sequence, read_stamps_ns
from .depth import check_depth_png, read_depth

__all__ = ["check_depth_png", "depth_scale_of", "open_tum", "read_depth"]


def depth_scale_of(camera_toml: str | Path) -> float:
    """camera.toml's [camera].depth_scale (depth image units per metre), DEPTH_SCALE (5000) if absent."""
    path = Path(camera_toml)
    doc = read_toml(path, SequenceError, "the path of a camera.toml")
    v = doc.get("camera", {}).get("depth_scale", DEPTH_SCALE) if isinstance(doc.get("camera"), dict) else DEPTH_SCALE
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise SequenceError(f"{path}: [camera].depth_scale = {v!r} must be a positive number (depth image units per "
                            f"metre; TUM RGB-D: 5000)")
    return float(v)


def open_tum(path: str | Path) -> DatasetSequence:
    """Open a sequence folder in our layout (runtime.sequence.open_sequence) with its exact
    stamps, and check every depth image listed in depth.txt from its PNG header."""
    seq = open_sequence(path)
    stamps_ns = read_stamps_ns(seq.root / "rgb.txt")
    if seq.depth_paths is not None:
        for p in seq.depth_paths:
            check_depth_png(p, seq.camera)
    return as_dataset_sequence(seq, source="tum", stamps_ns=stamps_ns,
                               depth_scale=depth_scale_of(seq.root / "camera.toml"),
                               groundtruth_ns=read_stamps_ns(seq.root / "groundtruth.txt")
                               if seq.groundtruth is not None else None,
                               imu_ns=read_stamps_ns(seq.root / "imu.txt") if seq.imu is not None else None)
