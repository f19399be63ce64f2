"""Running MonoSLAM over a sequence folder: trajectory.tum, map.csv, stats.json, video frames."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..sequence import SequenceError, open_sequence, write_trajectory
from .measurement import h_and_jacobians_many
from .filter import innovation_covariances
from .state import DEFAULT_CONFIG, SlamConfig, feature_slice
from .system import MapSettings, MonoSLAM, SlamStartError


def _annotate(image: np.ndarray, slam: MonoSLAM) -> np.ndarray:
    """Every mapped feature at its predicted position with its 3-sigma search ellipse (target
    points red, others green) and the particles of initialising features (yellow dots), as in
    the paper's Fig. 7 and 8."""
    img = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    st = slam.state
    if st.n_features:
        uv, S, valid = innovation_covariances(st, np.arange(st.n_features), slam.cam, slam.cfg.R_pix)
        for k in np.flatnonzero(valid):
            w, V = np.linalg.eigh(S[k])
            ang = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
            axes = tuple(int(max(3 * np.sqrt(max(x, 0)), 1)) for x in w[::-1])
            colour = (0, 0, 255) if slam.features[k].known else (0, 200, 0)
            c = tuple(int(round(x)) for x in uv[k])
            if abs(c[0]) < 10000 and abs(c[1]) < 10000:
                cv2.ellipse(img, c, axes, ang, 0, 360, colour, 1)
                cv2.circle(img, c, 2, colour, -1)
    for _, p, *_ in slam.rays:
        uv, _, _, valid = h_and_jacobians_many(st.x_v, p.points(), slam.cam)
        for q in uv[valid]:
            if np.all(np.abs(q) < 10000):
                cv2.circle(img, tuple(int(round(x)) for x in q), 1, (0, 220, 255), -1)
    return img


def run_slam(seq_path: str | Path, out: str | Path, max_frames: int | None = None, video: bool = False,
             cfg: SlamConfig = DEFAULT_CONFIG, settings: MapSettings = MapSettings(), progress: bool = True) -> dict:
    """Run over a sequence; returns the totals written to stats.json."""
    seq = open_sequence(seq_path)
    if seq.target is None:
        raise SequenceError(f"{seq.root}: no target.toml; SLAM starts from known points that fix the world frame")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    writer = None
    if video:
        (out / "video").mkdir(exist_ok=True)
    slam = MonoSLAM(seq.camera, cfg, settings)
    times, poses = [], []
    skipped = 0
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    frames = seq.frames()
    for i in tqdm(range(n), desc="slam", unit="frame", disable=not progress):
        f = next(frames)
        if slam.state is None:
            if f.image is None:
                raise SlamStartError(f"{f.path}: the first frame cannot be read ({f.problem}); SLAM needs it to start")
            slam.start(f.image, f.t, seq.target)
            if seq.imu is not None:
                slam.add_imu(np.column_stack([seq.imu.t, seq.imu.gyro, seq.imu.accel]))
        elif f.image is None:
            slam.skip(f.t, f.problem or "unreadable")
            skipped += 1
        else:
            st = slam.process(f.image, f.t)
            if st.lost and (len(slam.stats) < 2 or not slam.stats[-2].lost):
                tqdm.write(f"slam: track lost at frame {st.frame} (t = {st.t:.3f} s): fewer than 3 matches "
                           f"for {slam.s.lost_after} frames; searching wider as uncertainty grows")
        times.append(f.t)
        poses.append(slam.T_world_cam())
        if video and f.image is not None:
            frame = _annotate(f.image, slam)
            cv2.imwrite(str(out / "video" / f"{i:06d}.png"), frame)
            if writer is None:
                # One playable file besides the frames, at the sequence's own rate.
                fps = (n - 1) / max(seq.timestamps[n - 1] - seq.timestamps[0], 1e-6) if n > 1 else 30.0
                writer = cv2.VideoWriter(str(out / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                         (frame.shape[1], frame.shape[0]))
            writer.write(frame)
    if writer is not None:
        writer.release()
    write_trajectory(out / "trajectory.tum", np.array(times), np.array(poses),
                     header="MonoSLAM camera-to-world poses (optical frame), TUM order")
    with open(out / "map.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x", "y", "z", *[f"P{i}{j}" for i in range(3) for j in range(3)], "first_frame",
                    "known", "measured", "attempted"])
        for k, feat in enumerate(slam.features):
            y = slam.state.feature(k)
            P = slam.state.P[feature_slice(k), feature_slice(k)]
            w.writerow([feat.id, *map(repr, map(float, y)), *map(repr, map(float, P.ravel())), feat.first_frame,
                        int(feat.known), feat.successes, feat.attempts])
    per_frame = [asdict(s) for s in slam.stats]
    proc = [s for s in slam.stats[1:] if not s.skipped]
    totals = {
        "frames": len(slam.stats), "skipped": skipped, "features": len(slam.features),
        "added": sum(s.added for s in slam.stats), "deleted": sum(s.deleted for s in slam.stats),
        "lost_frames": sum(1 for s in slam.stats if s.lost), "lost": any(s.lost for s in slam.stats),
        "mean_matched": float(np.mean([s.matched for s in proc])) if proc else 0.0,
        "mean_ms_per_frame": 1000 * float(np.mean([s.seconds for s in proc])) if proc else 0.0,
        "median_ms_per_frame": 1000 * float(np.median([s.seconds for s in proc])) if proc else 0.0,
    }
    (out / "stats.json").write_text(json.dumps({"totals": totals, "frames": per_frame}, indent=1))
    return totals
