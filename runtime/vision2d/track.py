"""Run a 2D tracker over an image sequence folder (the TUM layout of shared/formats.md) and
write what it found: polygons.csv, annotated frames and stats.json.

    track_sequence(seq_path, out_dir, init=(x, y, w, h), method="hyperplane" | "meanshift")

The tracker starts on the first readable frame from ``init``. Unreadable frames are skipped,
counted and listed (a row with an empty polygon and lost = 1 keeps polygons.csv aligned with
rgb.txt); frames where the tracker reports a loss are counted as lost.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from kinematics.progress import progress_bar

from kinematics.outdir import output_folder
from runtime.sequence import Sequence, open_sequence

from .hyperplane import HyperplaneConfig, HyperplaneTracker
from .meanshift import MeanShiftConfig, MeanShiftTracker
from .tracker import Tracker, TrackResult

#: Every 2D tracker by name: its class and its configuration class.
TRACKERS: dict[str, tuple[type, type]] = {
    "hyperplane": (HyperplaneTracker, HyperplaneConfig),
    "meanshift": (MeanShiftTracker, MeanShiftConfig),
}
METHODS = tuple(TRACKERS)
COLUMNS = ["t", "x0", "y0", "x1", "y1", "x2", "y2", "x3", "y3", "lost", "residual"]


def _check_method(method: str) -> None:
    if method not in TRACKERS:
        raise ValueError(f"tracking method {method!r} unknown; use one of {', '.join(METHODS)}")


def make_tracker(method: str, image: np.ndarray, init, config=None) -> Tracker:
    """A tracker learned on ``image`` from ``init`` ((x, y, w, h) px; the hyperplane tracker
    also takes 4 corners (4, 2)). ``config``: the method's configuration (HyperplaneConfig or
    MeanShiftConfig); another method's, or None, gives the defaults."""
    _check_method(method)
    cls, config_cls = TRACKERS[method]
    return cls(image, init, config if isinstance(config, config_cls) else None)


@dataclass(frozen=True)
class SkippedFrame:
    index: int       # in rgb.txt
    problem: str


@dataclass(frozen=True)
class TrackSummary:
    """What :func:`track_sequence` found (stats.json holds the same).

    frames : rgb.txt entries. tracked : frames tracked (not lost). lost_frames : rows with
    lost = 1, skipped frames included; lost_readable_frames : the losses the tracker reported.
    skipped_unreadable (= skipped) and skipped_frames : the frames that could not be read.
    init : the start region. learn_seconds : learning time; tracking_fps : tracking rate
    (learning excluded; None with a single frame).
    """

    method: str
    frames: int
    tracked: int
    lost_frames: int
    lost_readable_frames: int
    skipped_unreadable: int
    skipped_frames: tuple[SkippedFrame, ...]
    init: list
    learn_seconds: float
    tracking_fps: float | None

    @property
    def skipped(self) -> int:
        return self.skipped_unreadable

    def stats(self) -> dict:
        """stats.json's contents."""
        d = asdict(self)
        d["skipped"] = self.skipped
        d["skipped_frames"] = [asdict(s) for s in self.skipped_frames]
        order = ("method", "frames", "tracked", "lost_frames", "lost_readable_frames", "skipped_unreadable", "skipped",
                 "skipped_frames", "init", "learn_seconds", "tracking_fps")
        return {k: d[k] for k in order}


def _annotate(image: np.ndarray, r: TrackResult, t: float) -> np.ndarray:
    """BGR copy of ``image`` with the polygon (green when tracked, red when lost)."""
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    colour = (0, 0, 255) if r.lost else (0, 220, 0)
    if np.all(np.isfinite(r.polygon)):
        pts = np.round(r.polygon * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(bgr, [pts], True, colour, 2, cv2.LINE_AA, shift=4)
        c = tuple(int(v) for v in np.round(r.centre * 16))
        cv2.circle(bgr, c, 3 * 16, colour, -1, cv2.LINE_AA, shift=4)
    label = f"t={t:.3f}  " + ("LOST: " + (r.reason or "") if r.lost else f"residual {r.residual:.3f}")
    cv2.putText(bgr, label[:80], (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return bgr


def _row(t: float, r: TrackResult | None) -> list:
    """polygons.csv's row: a skipped frame (None) has an empty polygon and lost = 1."""
    if r is None:
        return [f"{t:.6f}"] + [""] * 8 + [1, ""]
    return ([f"{t:.6f}"] + [f"{v:.3f}" for v in r.polygon.ravel()]
            + [int(r.lost), f"{r.residual:.4f}" if math.isfinite(r.residual) else ""])


def _track_frames(seq: Sequence, out: Path, init, method: str, config, annotate: bool, progress: bool):
    """Run the tracker over every frame: (results per rgb.txt entry, None for skipped frames;
    the skipped frames; learning and tracking seconds)."""
    tracker = None
    results: list[TrackResult | None] = []
    skipped: list[SkippedFrame] = []
    learn_s = track_s = 0.0
    for frame in progress_bar(seq.frames(), total=len(seq), desc=f"track ({method})", unit="frame", disable=not progress):
        if not frame.ok:
            skipped.append(SkippedFrame(frame.index, frame.problem))
            results.append(None)
            continue
        t0 = time.perf_counter()
        if tracker is None:
            tracker = make_tracker(method, frame.image, init, config)   # ValueError on bad init
            r = tracker.start_result()
            learn_s = time.perf_counter() - t0
        else:
            r = tracker.track(frame.image)
            track_s += time.perf_counter() - t0
        results.append(r)
        if annotate:
            (out / "annotated").mkdir(exist_ok=True)
            cv2.imwrite(str(out / "annotated" / f"{frame.index:06d}.png"), _annotate(frame.image, r, frame.t))
    if tracker is None:
        raise ValueError(f"{seq.root}: no readable frame to start tracking from ({len(skipped)} unreadable)")
    return results, skipped, learn_s, track_s


def track_sequence(seq_path, out_dir, init, method: str = "hyperplane", progress: bool = True,
                   config=None, annotate: bool = True) -> TrackSummary:
    """Track a region through the sequence at ``seq_path`` and write to ``out_dir`` (an output
    folder of kinematics.outdir: checked before tracking, INCOMPLETE until written):

    polygons.csv : one row per rgb.txt entry: t (s), x0 y0 ... x3 y3 (the region's corners, px;
        empty for skipped frames), lost (0/1), residual (the tracker's loss criterion: hyperplane,
        RMS normalised intensity error; mean shift, object-colour mass relative to the start).
    annotated/NNNNNN.png : each readable frame (NNNNNN its index in rgb.txt) with the polygon.
    stats.json : the summary returned (:meth:`TrackSummary.stats`).

    init : (x, y, w, h) px in the first readable frame (hyperplane: or 4 corners (4, 2)).
    Bad init or method raises ValueError; bad frames never do.
    """
    _check_method(method)
    seq = open_sequence(seq_path)
    with output_folder(out_dir, kind="track") as out:
        results, skipped, learn_s, track_s = _track_frames(seq, out, init, method, config, annotate, progress)
        with open(out / "polygons.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(COLUMNS)
            for t, r in zip(seq.timestamps, results):
                w.writerow(_row(float(t), r))
        readable = [r for r in results if r is not None]
        lost = sum(int(r.lost) for r in readable)
        n_tracked_frames = len(readable) - 1   # frames after the first readable one
        summary = TrackSummary(
            method=method, frames=len(seq), tracked=len(readable) - lost, lost_frames=lost + len(skipped),
            lost_readable_frames=lost, skipped_unreadable=len(skipped), skipped_frames=tuple(skipped),
            init=np.asarray(init, float).tolist(), learn_seconds=round(learn_s, 4),
            tracking_fps=round(n_tracked_frames / track_s, 2) if track_s > 0 else None)
        (out / "stats.json").write_text(json.dumps(summary.stats(), indent=2))
    return summary
