"""Stabilising a whole sequence folder: every frame through :class:`.estimator.Stabiliser`,
scored by the background's residual image motion in the raw frames and in the fovea, and
written out (rotations.tum, fovea/NNNNNN.png, fovea.csv, stats.json, report.md)."""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from kinematics.progress import progress_bar

from kinematics.outdir import output_folder

from ...sequence import ImuLog, open_sequence, write_trajectory
from .estimator import StabiliseSettings, Stabiliser, check_fovea, detect_corners, to_grey, track_points


# ---------------------------------------------------------------------------------------------
# Residual image motion (the figure of merit)
# ---------------------------------------------------------------------------------------------

def residual_motion(prev_grey: np.ndarray, cur_grey: np.ndarray, settings: StabiliseSettings) -> float:
    """Median optical-flow magnitude (pixels) of background corners between two images.

    Corners of prev_grey tracked into cur_grey (LK, forward-backward checked, no prediction);
    the median makes it the motion of the background when independently moving things are a
    minority. NaN if fewer than settings.min_corners tracks survive. Raw frames and fovea crops
    are measured by this same function.
    """
    uv = detect_corners(prev_grey, settings)
    if len(uv) < settings.min_corners:
        return float("nan")
    uv_cur, ok = track_points(prev_grey, cur_grey, uv, settings.flow)
    if ok.sum() < settings.min_corners:
        return float("nan")
    return float(np.median(np.linalg.norm(uv_cur[ok] - uv[ok], axis=1)))


# ---------------------------------------------------------------------------------------------
# A whole sequence
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class StabiliseResult:
    """What :func:`stabilise_sequence` measured (stats.json holds the same; None fields are left
    out of it: they need clamp-free pairs, the IMU or ground truth).

    frames : frames processed. flagged : passed through (too few corners, tracks or inliers).
    clamped : the fovea at the image edge. skipped_unreadable : frames that could not be read.
    fovea : (width, height) px. mean_inliers : rotation inliers per frame. processing_fps :
    frames per second of the stabiliser alone. raw_motion_px, fovea_motion_px,
    centre_crop_motion_px : the background's mean residual motion, px/frame, in the raw frames,
    the fovea and a fixed central crop; motion_ratio = raw / fovea (and the same over the pairs
    where the fovea was not clamped). imu_rotation_mean_deg, vision_remainder_mean_deg : the gyro's
    rotation per frame and what vision changed of it. rotation_rms_error_deg,
    rotation_max_error_deg : inter-frame rotation against the ground truth. first_problem : the
    first unreadable frame's problem.
    """

    frames: int
    flagged: int
    clamped: int
    skipped_unreadable: int
    fovea: tuple[int, int]
    use_imu: bool
    mean_inliers: float
    processing_fps: float
    raw_motion_px: float
    fovea_motion_px: float
    centre_crop_motion_px: float
    motion_ratio: float
    fovea_motion_unclamped_px: float | None = None
    raw_motion_unclamped_px: float | None = None
    motion_ratio_unclamped: float | None = None
    imu_rotation_mean_deg: float | None = None
    vision_remainder_mean_deg: float | None = None
    rotation_rms_error_deg: float | None = None
    rotation_max_error_deg: float | None = None
    first_problem: str | None = None

    def stats(self) -> dict:
        """stats.json's contents: every field that was measured."""
        d = {k: v for k, v in asdict(self).items() if v is not None}
        d["fovea"] = list(self.fovea)
        return d


@dataclass
class _Pass:
    """What one pass over the frames collected (per processed frame, and the motion pairs)."""

    t: list = field(default_factory=list)
    R_prev_cur: list = field(default_factory=list)
    R_cam0_cam: list = field(default_factory=list)
    rows: list = field(default_factory=list)          # (t, x, y, clamped, flagged, inliers)
    problems: list = field(default_factory=list)
    raw_motion: list = field(default_factory=list)
    fovea_motion: list = field(default_factory=list)
    centre_motion: list = field(default_factory=list)
    imu_rotation: list = field(default_factory=list)
    vision_remainder: list = field(default_factory=list)
    elapsed_s: float = 0.0


def _stabilise_frames(seq, out: Path, stab: "Stabiliser", imu: ImuLog | None, settings: StabiliseSettings,
                      progress: bool) -> _Pass:
    """Every frame through the stabiliser, writing fovea/NNNNNN.png as it goes."""
    cam, fsize = seq.camera, stab.fovea_size
    c0 = ((cam.width - fsize[0]) // 2, (cam.height - fsize[1]) // 2)
    centre = (slice(c0[1], c0[1] + fsize[1]), slice(c0[0], c0[0] + fsize[0]))
    run = _Pass()
    prev_grey = prev_fov = prev_t = None
    for fr in progress_bar(seq.frames(), total=len(seq), desc="stabilise", unit="frame", disable=not progress):
        if not fr.ok:
            run.problems.append(fr.problem)
            continue
        tic = time.perf_counter()
        gyro = None
        if imu is not None:
            t_from = min([fr.t] + [x for x in (prev_t, stab.reference_t) if x is not None])
            sel = (imu.t >= t_from - 0.05) & (imu.t <= fr.t + 0.05)  # a margin for interpolation
            gyro = (imu.t[sel], imu.gyro[sel])
        r = stab.step(fr.t, fr.image, gyro)
        run.elapsed_s += time.perf_counter() - tic
        grey = to_grey(fr.image)
        fgrey = to_grey(r.fovea)
        if prev_grey is not None:
            run.raw_motion.append(residual_motion(prev_grey, grey, settings))
            run.fovea_motion.append(residual_motion(prev_fov, fgrey, settings))
            # The same region of the raw image, not moved: separates "smaller window" from "moved".
            run.centre_motion.append(residual_motion(prev_grey[centre], grey[centre], settings))
            if r.R_imu is not None and not r.flagged:
                run.imu_rotation.append(math.degrees(Rotation.from_matrix(r.R_imu).magnitude()))
                run.vision_remainder.append(math.degrees(Rotation.from_matrix(r.R_imu.T @ r.R_prev_cur).magnitude()))
        prev_grey, prev_fov, prev_t = grey, fgrey, fr.t
        cv2.imwrite(str(out / "fovea" / f"{fr.index:06d}.png"),
                    cv2.cvtColor(r.fovea, cv2.COLOR_RGB2BGR) if r.fovea.ndim == 3 else r.fovea)
        run.t.append(fr.t)
        run.R_prev_cur.append(r.R_prev_cur)
        run.R_cam0_cam.append(r.R_cam0_cam)
        run.rows.append((fr.t, r.window.centre[0], r.window.centre[1], int(r.window.clamped), int(r.flagged),
                         r.inliers))
    return run


def _summarise(run: _Pass, seq, fsize: tuple[int, int], use_imu: bool) -> StabiliseResult:
    n = len(run.t)
    raw_m, fov_m, cen_m = np.array(run.raw_motion), np.array(run.fovea_motion), np.array(run.centre_motion)
    clamped = np.array([row[3] for row in run.rows], bool)
    extra: dict = {}
    if n > 1:
        # Pairs whose both fovea positions were free (not clamped): the fovea's own performance.
        free = ~clamped[1:] & ~clamped[:-1]
        extra["fovea_motion_unclamped_px"] = _nanmean(fov_m[free])
        extra["raw_motion_unclamped_px"] = _nanmean(raw_m[free])
        extra["motion_ratio_unclamped"] = _ratio(extra["raw_motion_unclamped_px"], extra["fovea_motion_unclamped_px"])
    if run.imu_rotation:
        extra["imu_rotation_mean_deg"] = float(np.mean(run.imu_rotation))
        extra["vision_remainder_mean_deg"] = float(np.mean(run.vision_remainder))
    if seq.groundtruth is not None and n > 1:
        from ...eval import rotation_errors_deg   # scoring only: the per-frame stabiliser never needs it

        err = rotation_errors_deg(np.array(run.t), np.array(run.R_prev_cur), seq.groundtruth)
        if np.isfinite(err).any():
            extra["rotation_rms_error_deg"] = float(np.sqrt(np.nanmean(err ** 2)))
            extra["rotation_max_error_deg"] = float(np.nanmax(err))
    if run.problems:
        extra["first_problem"] = run.problems[0]
    return StabiliseResult(
        frames=n, flagged=int(sum(row[4] for row in run.rows)), clamped=int(clamped.sum()),
        skipped_unreadable=len(run.problems), fovea=tuple(fsize), use_imu=bool(use_imu),
        mean_inliers=float(np.mean([row[5] for row in run.rows[1:]])) if n > 1 else 0.0,
        processing_fps=n / run.elapsed_s if run.elapsed_s > 0 else float("nan"),
        raw_motion_px=_nanmean(raw_m), fovea_motion_px=_nanmean(fov_m), centre_crop_motion_px=_nanmean(cen_m),
        motion_ratio=_ratio(_nanmean(raw_m), _nanmean(fov_m)), **extra)


def stabilise_sequence(seq_path, out_dir, fovea=(320, 240), use_imu: bool = False, progress: bool = True,
                       settings: StabiliseSettings | None = None) -> StabiliseResult:
    """Stabilise a sequence folder (shared/formats.md) and write the results to out_dir.

    seq_path : the sequence. out_dir : an output folder (kinematics.outdir: checked before any
    work, INCOMPLETE until written). fovea : (width, height) pixels. use_imu : integrate
    imu.txt's gyro to pre-warp the flow search (the sequence must have one). settings :
    StabiliseSettings (defaults if None).

    Writes rotations.tum (camera orientation relative to the first frame per processed frame,
    position zero), fovea/NNNNNN.png (NNNNNN the frame's index in rgb.txt), fovea.csv
    (t, x, y, clamped, flagged, inliers), stats.json and report.md (the residual background
    motion of the raw frames and of the fovea, and with ground truth the rotation error).
    Unreadable frames are skipped (no output line) and counted; the next frame is measured
    against the last processed one. Returns what stats.json holds.
    """
    settings = settings or StabiliseSettings()
    seq = open_sequence(seq_path)
    fsize = check_fovea(fovea, seq.camera)
    if use_imu and seq.imu is None:
        raise ValueError(f"{Path(seq_path) / 'imu.txt'}: missing, so the IMU cannot be used; "
                         f"run without use_imu (--imu) or add imu.txt (timestamp wx wy wz ax ay az)")
    if len(seq) == 0:                       # before the folder is made: a refusal leaves nothing
        raise ValueError(f"{Path(seq_path) / 'rgb.txt'}: lists no frames; give a sequence with images "
                         f"(lines 'timestamp path' in rgb.txt)")
    with output_folder(out_dir, kind="stabilise") as out:
        (out / "fovea").mkdir(exist_ok=True)
        run = _stabilise_frames(seq, out, Stabiliser(seq.camera, fsize, settings), seq.imu if use_imu else None,
                                settings, progress)
        if not run.t:
            raise ValueError(f"{seq_path}: none of the {len(seq)} images could be read "
                             f"(first problem: {run.problems[0] if run.problems else 'no frames in rgb.txt'}); "
                             f"check the rgb/ folder")
        T = np.tile(np.eye(4), (len(run.t), 1, 1))
        T[:, :3, :3] = np.array(run.R_cam0_cam)
        write_trajectory(out / "rotations.tum", np.array(run.t), T,
                         header="camera orientation relative to the first frame (position zero), wvr stabilise")
        with open(out / "fovea.csv", "w") as fh:
            fh.write("t,x,y,clamped,flagged,inliers\n")
            for t, x, y, c, f, k in run.rows:
                fh.write(f"{t:.9f},{x:.3f},{y:.3f},{c},{f},{k}\n")
        result = _summarise(run, seq, fsize, use_imu)
        (out / "stats.json").write_text(json.dumps(result.stats(), indent=2) + "\n")
        (out / "report.md").write_text(_report(seq_path, result, settings))
    return result


def _nanmean(a: np.ndarray) -> float:
    a = np.asarray(a, float)
    return float(np.nanmean(a)) if np.isfinite(a).any() else float("nan")


def _ratio(a: float, b: float) -> float:
    return float(a / b) if (math.isfinite(a) and math.isfinite(b) and b > 0) else float("nan")


def _report(seq_path, result: StabiliseResult, settings: StabiliseSettings) -> str:
    s = result.stats()
    lines = [
        "# Stabilisation with a software fovea",
        "",
        f"Sequence `{seq_path}`, fovea {s['fovea'][0]}x{s['fovea'][1]}, "
        f"IMU {'used' if s['use_imu'] else 'not used'}, "
        f"reference {'held still' if settings.leak_per_s == 0 else f'followed at {settings.leak_per_s:g}/s'}, "
        f"{'derotating' if settings.derotate else 'sliding'} window.",
        "",
        "| | |",
        "|---|---|",
        f"| frames processed | {s['frames']} |",
        f"| flagged (too few corners, tracks or inliers; passed through) | {s['flagged']} |",
        f"| fovea clamped at the image edge | {s['clamped']} |",
        f"| unreadable frames skipped | {s['skipped_unreadable']} |",
        f"| mean rotation inliers per frame | {s['mean_inliers']:.0f} |",
        f"| processing rate | {s['processing_fps']:.1f} frames/s |",
        "",
        "## Residual image motion of the background",
        "",
        "Median optical-flow magnitude of background corners between consecutive images (Shi-Tomasi",
        "corners, Lucas-Kanade, forward-backward checked), averaged over the frame pairs; raw frames",
        "and fovea crops measured the same way.",
        "",
        "| | pixels/frame |",
        "|---|---|",
        f"| raw frames | {s['raw_motion_px']:.3f} |",
        f"| fixed central {s['fovea'][0]}x{s['fovea'][1]} crop of the raw frames | "
        f"{s['centre_crop_motion_px']:.3f} |",
        f"| fovea | {s['fovea_motion_px']:.3f} |",
        f"| ratio raw / fovea | {s['motion_ratio']:.2f} |",
    ]
    if "motion_ratio_unclamped" in s:
        lines.append(f"| ratio raw / fovea, pairs where the fovea was not clamped | "
                     f"{s['motion_ratio_unclamped']:.2f} |")
    if "imu_rotation_mean_deg" in s:
        lines += ["", f"The gyro predicted {s['imu_rotation_mean_deg']:.3f} deg of rotation per frame on average; "
                  f"vision's rotation differed from it by {s['vision_remainder_mean_deg']:.3f} deg per frame (the "
                  f"remainder vision removes: gyro error, and the parallax a rotation-only fit reads as rotation)."]
    if "rotation_rms_error_deg" in s:
        lines += ["", "## Against ground truth", "",
                  f"Inter-frame rotation error (angle of R_est^T R_gt): RMS {s['rotation_rms_error_deg']:.4f} deg, "
                  f"max {s['rotation_max_error_deg']:.4f} deg. The model is rotation-only: camera translation "
                  f"with near scenery shows up as parallax that the fit partly reads as rotation."]
    return "\n".join(lines) + "\n"
