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
from pathlib import Path

import cv2
import numpy as np

from runtime.sequence import open_sequence

from .hyperplane import HyperplaneConfig, HyperplaneTracker, TrackResult
from .meanshift import MeanShiftConfig, MeanShiftTracker

METHODS = ("hyperplane", "meanshift")
COLUMNS = ["t", "x0", "y0", "x1", "y1", "x2", "y2", "x3", "y3", "lost", "residual"]


def make_tracker(method: str, image: np.ndarray, init, config=None):
    """A tracker learned on ``image`` from ``init`` ((x, y, w, h) px; the hyperplane tracker
    also takes 4 corners (4, 2)). ``config``: HyperplaneConfig or MeanShiftConfig (or None)."""
    if method == "hyperplane":
        return HyperplaneTracker(image, init, config if isinstance(config, HyperplaneConfig) else None)
    if method == "meanshift":
        return MeanShiftTracker(image, init, config if isinstance(config, MeanShiftConfig) else None)
    raise ValueError(f"tracking method {method!r} unknown; use one of {', '.join(METHODS)}")


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


def track_sequence(seq_path, out_dir, init, method: str = "hyperplane", progress: bool = True,
                   config=None, annotate: bool = True) -> dict:
    """Track a region through the sequence at ``seq_path`` and write to ``out_dir``:

    polygons.csv : one row per rgb.txt entry: t (s), x0 y0 ... x3 y3 (the region's corners, px;
        empty for skipped frames), lost (0/1), residual (the tracker's loss criterion: hyperplane,
        RMS normalised intensity error; mean shift, object-colour mass relative to the start).
    annotated/NNNNNN.png : each readable frame (NNNNNN its index in rgb.txt) with the polygon.
    stats.json : the totals returned.

    init : (x, y, w, h) px in the first readable frame (hyperplane: or 4 corners (4, 2)).
    Returns {"frames" (rgb.txt entries), "tracked", "lost_frames" (rows with lost = 1, skipped
    frames included), "lost_readable_frames" (losses the tracker reported), "skipped_unreadable"
    (= "skipped"), "skipped_frames": [{"index", "problem"}], "method", "init", "learn_seconds",
    "tracking_fps" (tracking only, learning excluded)}.
    Bad init or method raises ValueError; bad frames never do.
    """
    if method not in METHODS:
        raise ValueError(f"tracking method {method!r} unknown; use one of {', '.join(METHODS)}")
    seq = open_sequence(seq_path)
    out = Path(out_dir)
    tracker = None
    rows, skipped, lost_frames, tracked = [], [], 0, 0
    learn_s, track_s = 0.0, 0.0
    wrote_dir = False
    bar = None
    if progress:
        try:
            from tqdm import tqdm
            bar = tqdm(total=len(seq), desc=f"track ({method})", unit="frame")
        except ImportError:
            bar = None
    try:
        for frame in seq.frames():
            if bar is not None:
                bar.update(1)
            if not frame.ok:
                skipped.append({"index": frame.index, "problem": frame.problem})
                rows.append([frame.t] + [""] * 8 + [1, ""])
                continue
            if tracker is None:
                t0 = time.perf_counter()
                tracker = make_tracker(method, frame.image, init, config)   # ValueError on bad init
                learn_s = time.perf_counter() - t0
                poly = tracker.polygon if method == "hyperplane" else cv2.boxPoints(tracker.box)
                centre = np.mean(poly, axis=0)
                r = TrackResult(np.asarray(poly, float), centre, False, 0.0 if method == "hyperplane" else 1.0)
            else:
                t0 = time.perf_counter()
                r = tracker.track(frame.image)
                track_s += time.perf_counter() - t0
            lost_frames += int(r.lost)
            tracked += int(not r.lost)
            rows.append([frame.t] + [f"{v:.3f}" for v in r.polygon.ravel()] + [int(r.lost),
                                                                            f"{r.residual:.4f}" if math.isfinite(r.residual) else ""])
            if annotate:
                if not wrote_dir:
                    (out / "annotated").mkdir(parents=True, exist_ok=True)
                    wrote_dir = True
                cv2.imwrite(str(out / "annotated" / f"{frame.index:06d}.png"), _annotate(frame.image, r, frame.t))
    finally:
        if bar is not None:
            bar.close()
    if tracker is None:
        raise ValueError(f"{seq_path}: no readable frame to start tracking from ({len(skipped)} unreadable)")
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "polygons.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for row in rows:
            w.writerow([f"{row[0]:.6f}"] + row[1:])
    n_tracked_frames = tracked + lost_frames - 1   # frames after the first readable one
    totals = {
        "method": method,
        "frames": len(seq),
        "tracked": tracked,
        "lost_frames": lost_frames + len(skipped),
        "lost_readable_frames": lost_frames,
        "skipped_unreadable": len(skipped),
        "skipped": len(skipped),
        "skipped_frames": skipped,
        "init": np.asarray(init, float).tolist(),
        "learn_seconds": round(learn_s, 4),
        "tracking_fps": round(n_tracked_frames / track_s, 2) if track_s > 0 else None,
    }
    (out / "stats.json").write_text(json.dumps(totals, indent=2))
    return totals
