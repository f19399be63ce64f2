"""TUM RGB-D folders (our own layout): exact stamps, and every listed depth image checked at
open (runtime.sequence.depth)."""

from __future__ import annotations

from pathlib import Path

from runtime.sequence import open_sequence
from runtime.sequence.depth import check_depth_png, read_depth

from .common import DatasetSequence, as_dataset_sequence, read_stamps_ns

__all__ = ["check_depth_png", "open_tum", "read_depth"]


def open_tum(path: str | Path) -> DatasetSequence:
    """Open a sequence folder in our layout (runtime.sequence.open_sequence) with its exact
    stamps, and check every depth image listed in depth.txt from its PNG header."""
    seq = open_sequence(path)
    stamps_ns = read_stamps_ns(seq.root / "rgb.txt")
    if seq.depth_paths is not None:
        for p in seq.depth_paths:
            check_depth_png(p, seq.camera)
    return as_dataset_sequence(seq, source="tum", stamps_ns=stamps_ns,
                               groundtruth_ns=read_stamps_ns(seq.root / "groundtruth.txt")
                               if seq.groundtruth is not None else None,
                               imu_ns=read_stamps_ns(seq.root / "imu.txt") if seq.imu is not None else None)
