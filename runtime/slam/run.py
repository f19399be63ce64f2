"""Running MonoSLAM over a sequence folder: trajectory.tum, map.csv, stats.json, and optionally
annotated frames, video.mp4 and a saved map."""

from __future__ import annotations

import csv
import itertools
import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from kinematics.progress import progress_bar

from kinematics.camera import CameraIntrinsics, undistort

from ..datasets import open_any
from ..sequence import SequenceError, write_trajectory
from .config import DEFAULT_CONFIG, MapSettings, SlamConfig
from .corners import grey
from .features import FEATURE_NAMES, INVERSE_DEPTH, inverse_depth
from .filter import innovation_covariances
from .measurement import predict, predict_points
from .state import G_SLICE, SCALE_INDEX, TD_INDEX
from .system import MonoSLAM, SlamStartError
from .imu_scale import gravity_aligned


@dataclass(frozen=True)
class SlamRun:
    """What a run over a sequence gives (also written to stats.json's totals)."""

    frames: int
    skipped: int
    features: int
    added: int
    deleted: int
    converted: int
    lost_frames: int
    lost: bool
    relocalised: int
    reacquired: int                     # times the camera was put back at the target's pose
    first_localised_s: float | None     # when the camera was first placed in the map (a saved map's session)
    mean_searched: float
    mean_matched: float
    mean_outliers: float
    mean_ms_per_frame: float
    median_ms_per_frame: float
    imu_frames: int
    #: Intervals between images longer than 1.5 frames (the median interval): frames the recorder
    #: dropped; the prediction spans them (motion.py). The longest interval, s.
    frame_gaps: int = 0
    longest_interval_s: float = 0.0
    #: Frames whose ellipses were mostly over the search cap (the camera's motion uncertain), the
    #: smallest then searched to guide the rest (stats' per-frame ``over_cap``).
    over_cap_frames: int = 0
    imu: dict = field(default_factory=dict)
    messages: tuple = ()
    #: The IMU's clock offset the filter ended with and its standard deviation, s (None without
    #: that state): an IMU sample stamped t was taken at camera time t - offset.
    imu_clock_offset_s: float | None = None
    imu_clock_offset_sd_s: float | None = None
    #: What fixed the map's unit: "target", "map", "depth" or "arbitrary" (wvr eval's default alignment).
    scale: str = "target"
    #: Frames before the start (natural features: no view to start from yet), given no pose, and why.
    frames_before_start: int = 0
    start_waits: dict = field(default_factory=dict)
    #: The IMU's estimate of a natural start's scale (metres per map unit) and gravity, over the
    #: first 3 s of the run and over all of it, after the run (scale_from_imu); where the IMU was
    #: handed the map (imu_handover.py), ``filter``: when, and the filter's scale then, 3 s after
    #: the start and at the end, which is the one used.
    imu_scale: dict | None = None


def _clock_offset(state) -> dict:
    if state is None or not state.has_time_offset:
        return {}
    return {"imu_clock_offset_s": state.t_d, "imu_clock_offset_sd_s": float(np.sqrt(state.P[TD_INDEX, TD_INDEX]))}


def check_lens_invertible(cam: CameraIntrinsics) -> None:
    """Refuse a camera whose distortion has no inverse over the whole image (as the twin's
    recorder does): SLAM unprojects every pixel it starts a feature at."""
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 33), np.linspace(0, cam.height - 1, 25))
    xy = undistort(cam, np.column_stack([u.ravel(), v.ravel()]))
    if not np.isfinite(xy).all():
        raise SequenceError("camera.toml: the lens model's distortion has no inverse over the whole image; "
                            "check the distortion terms (a calibration's k1..k4 or kd1)")


def _annotate(image: np.ndarray, slam: MonoSLAM) -> np.ndarray:
    """Every mapped feature at its predicted position with its 3-sigma search ellipse (target
    points red, points green, inverse-depth features yellow) and the particles of initialising
    rays (yellow dots), as in the paper's Fig. 7 and 8."""
    img = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if not slam.localised:
        return img
    st = slam.state
    if st.n_features:
        pred = predict(st, np.arange(st.n_features), slam.cam)
        S = innovation_covariances(st, pred, slam.cfg.sigma_pixel**2)
        for k in np.flatnonzero(pred.valid):
            w, V = np.linalg.eigh(S[k])
            ang = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
            axes = tuple(int(min(max(3 * np.sqrt(max(x, 0)), 1), 2000)) for x in w[::-1])
            colour = (0, 0, 255) if slam.features[k].known else ((0, 220, 255) if st.kinds[k] == INVERSE_DEPTH
                                                                 else (0, 200, 0))
            c = tuple(int(round(x)) for x in pred.uv[k])
            if abs(c[0]) < 10000 and abs(c[1]) < 10000:
                cv2.ellipse(img, c, axes, ang, 0, 360, colour, 1)
                cv2.circle(img, c, 2, colour, -1)
    for _, p, *_ in slam.rays:
        uv, _, valid = predict_points(st.x_v, p.points(), slam.cam)
        for q in uv[valid]:
            if np.all(np.abs(q) < 10000):
                cv2.circle(img, tuple(int(round(x)) for x in q), 1, (0, 220, 255), -1)
    return img


def write_map_csv(path: Path, slam: MonoSLAM, R_out_world: np.ndarray = np.eye(3), scale: float = 1.0) -> None:
    """One row per map feature: its id, kind, point (world, m) and the point's 3x3 covariance
    (an inverse-depth feature's through its conversion Jacobian), first frame, whether a target
    point, inlier matches and searches. ``R_out_world``, ``scale``: the similarity (about the
    origin) that takes the filter's world to the one written (an IMU's scale and gravity)."""
    st = slam.state
    similar = scale != 1.0 or not np.array_equal(R_out_world, np.eye(3))
    Y = scale * slam.world_points() @ R_out_world.T if similar else slam.world_points()
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "kind", "x", "y", "z", *[f"P{i}{j}" for i in range(3) for j in range(3)], "first_frame",
                    "known", "measured", "attempted"])
        for k, feat in enumerate(slam.features):
            sl = st.feature_slice(k)
            P = st.P[sl, sl]
            if st.kinds[k] == INVERSE_DEPTH:
                _, J = inverse_depth.to_point(st.feature(k), st.anchors[k])
                P = J @ P @ J.T
            if similar:
                P = scale**2 * R_out_world @ P @ R_out_world.T
            w.writerow([feat.id, FEATURE_NAMES[st.kinds[k]], *map(repr, map(float, Y[k])), *map(repr, map(float, P.ravel())),
                        feat.first_frame, int(feat.known), feat.successes, feat.attempts])


#: The IMU's scale is used when the camera accelerated this much (RMS, m/s^2) and the estimate's
#: relative standard deviation is under IMU_SCALE_MAX_SIGMA.
IMU_SCALE_MIN_EXCITATION = 0.2
IMU_SCALE_MAX_SIGMA = 0.03
IMU_SCALE_EARLY_S = 3.0
#: The scale has settled once every estimate over a longer start of the run is within this of the whole run's.
IMU_SCALE_SETTLED_REL = 0.02


def scale_from_imu(t: np.ndarray, T_world_cam: np.ndarray, imu) -> dict | None:
    """The scale and gravity of a natural start's map from the camera's poses (n,) s, (n, 4, 4) and
    the sequence's IMU (imu_scale.estimate_scale): over the first IMU_SCALE_EARLY_S seconds and over
    the whole run; the whole run's is used when observable. How it converged while the camera
    moved: the estimate over the run's first 1, 2, 4, ... s (``history``), and from how many
    seconds on every such estimate lies within IMU_SCALE_SETTLED_REL of the whole run's
    (``settled_s``; None if only the whole run's does). None when the run is too short."""
    from .imu_scale import estimate_scale

    R, p = T_world_cam[:, :3, :3], T_world_cam[:, :3, 3]
    full = estimate_scale(t, p, R, imu.t, imu.gyro, imu.accel)
    if full is None:
        return None
    early = t <= t[0] + IMU_SCALE_EARLY_S
    first = estimate_scale(t[early], p[early], R[early], imu.t, imu.gyro, imu.accel)
    history = []
    span = 1.0
    while span < t[-1] - t[0]:
        k = t <= t[0] + span
        e = estimate_scale(t[k], p[k], R[k], imu.t, imu.gyro, imu.accel)
        history.append({"seconds": span, "scale": e.scale if e is not None else None,
                        "sigma_rel": e.sigma_rel if e is not None else None})
        span *= 2.0
    history.append({"seconds": float(t[-1] - t[0]), "scale": full.scale, "sigma_rel": full.sigma_rel})
    settled_s = None
    for h in reversed(history[:-1]):
        if h["scale"] is None or abs(h["scale"] / full.scale - 1.0) > IMU_SCALE_SETTLED_REL:
            break
        settled_s = h["seconds"]
    usable = full.excitation >= IMU_SCALE_MIN_EXCITATION and full.sigma_rel <= IMU_SCALE_MAX_SIGMA
    said = (f"scale from the IMU: {full.scale:.4g} m per map unit (+- {100 * full.sigma_rel:.1f}%, the camera's "
            f"acceleration {full.excitation:.2f} m/s^2 RMS" +
            (f"; within {100 * IMU_SCALE_SETTLED_REL:.0f}% of it from the run's first {settled_s:g} s on)"
             if settled_s is not None else ")") +
            ("" if usable else "; too weakly observed, the scale stays arbitrary"))
    return {"usable": bool(usable), "scale": full.scale, "sigma_rel": full.sigma_rel, "excitation_m_s2": full.excitation,
            "g_world": full.g_world.tolist(), "accel_bias": full.accel_bias.tolist(),
            "R_up_world": gravity_aligned(full.g_world).tolist(),
            "scale_first_3s": first.scale if first is not None else None,
            "sigma_rel_first_3s": first.sigma_rel if first is not None else None,
            "history": history, "settled_s": settled_s, "said": said}


def filter_scale(slam: MonoSLAM, handed) -> dict:
    """The scale state's history after the IMU's hand-over (imu_handover.Handover): metres per
    map unit when the IMU took the map, IMU_SCALE_EARLY_S after the start and at the end, with
    the filter's relative standard deviation at the end."""
    t0 = slam.stats[0].t
    early = next((s.map_units_per_m for s in slam.stats
                  if s.map_units_per_m is not None and s.t >= t0 + IMU_SCALE_EARLY_S), None)
    st = slam.state
    return {"handover_after_s": handed.t - t0, "scale_at_handover": 1.0 / handed.k,
            "scale_first_3s": 1.0 / early if early else None, "scale": 1.0 / st.k,
            "sigma_rel": float(np.sqrt(max(st.P[SCALE_INDEX, SCALE_INDEX], 0.0))) / st.k,
            "g_world_at_handover": np.asarray(handed.estimate.g_world, float).tolist(),
            "g_world": st.gravity.tolist(),
            "g_sigma_deg": gravity_direction_sigma_deg(st.gravity, st.P[G_SLICE, G_SLICE])}


def gravity_direction_sigma_deg(g: np.ndarray, P_g: np.ndarray) -> float:
    """The standard deviation, degrees, of gravity's direction ``g`` (3,) m/s^2 with covariance
    ``P_g`` (3, 3): its spread across ``g`` (both axes together), over its length; the magnitude's
    variance along ``g`` is left out."""
    u = g / np.linalg.norm(g)
    A = np.eye(3) - np.outer(u, u)
    return float(np.degrees(np.sqrt(max(np.trace(A @ P_g @ A), 0.0)) / np.linalg.norm(g)))


def wait_for_natural_start(slam: MonoSLAM, seq, f, frames, n: int, waits: dict[str, int], progress: bool):
    """Feed frames (the first, ``f``, then ``frames``: an iterator of (index, Frame)) to a natural
    start-up: the depth start where the sequence has depth images, else the two-view start.
    Returns (NaturalStart, [(index, Frame)] from its reference frame to the accepting one).
    Counts each reason it waited in ``waits``. Raises SlamStartError when the frames run out."""
    from .natural_start import StartWait, TwoViewStart, depth_start

    two_view = TwoViewStart(slam.cam)
    kept: list = []
    said = None
    entry = (0, f)
    while True:
        i, f = entry
        if f.image is None:
            waits["unreadable frame"] = waits.get("unreadable frame", 0) + 1
            kept.append(entry)                      # replayed as a skipped frame
        else:
            g = grey(f.image)
            depth = seq.depth(i) if getattr(seq, "depth_paths", None) is not None else None
            if depth is not None:
                r = depth_start(slam.cam, g, depth, i)
                kept = [entry]
            else:
                r = two_view.add(g, i, f.t)
                kept = [e for e in kept if two_view.ref_frame is not None and e[0] >= two_view.ref_frame] + [entry]
            if not isinstance(r, StartWait):
                return r, [e for e in kept if e[0] >= r.frame]
            key = r.reason.split(" (")[0].split(":")[0]
            waits[key] = waits.get(key, 0) + 1
            if progress and key != said and key != "reference frame taken; waiting for parallax":
                print(f"slam: waiting to start at frame {i}: {r.reason}")
                said = key
        try:
            entry = next(frames)
        except StopIteration:
            entry = None
        if entry is None or entry[0] >= n:
            why = max(waits, key=waits.get) if waits else "no frames"
            raise SlamStartError(f"{seq.root}: no start could be made from natural features in {i + 1} frames "
                                 f"(mostly: {why}); give a target.toml or a saved map (--map), or record the camera "
                                 "moving sideways over a textured scene")


def imu_notes(seq, slam: MonoSLAM) -> None:
    """Count the rows imu.txt's reader dropped with the filter's own (stats.json's ``imu``) and
    say them; say when the IMU's samples cover none of the frames (another clock, or another
    recording), so that the run goes on camera only knowingly."""
    imu, c = seq.imu, slam.imu.counts
    d = imu.dropped
    if d:
        c.rows += sum(d.values())
        c.non_finite += d.get("non_finite", 0)
        c.out_of_order += d.get("duplicate", 0) + d.get("out_of_order", 0)
        slam.messages.append("slam: imu.txt: " + ", ".join(f"{v} {k.replace('_', ' ')} rows" for k, v in d.items())
                             + " dropped")
    t = seq.timestamps
    if not len(imu.t):
        slam.messages.append(f"slam: {seq.root}/imu.txt holds no samples: camera only")
    elif imu.t[-1] < t[0] or imu.t[0] > t[-1]:
        slam.messages.append(f"slam: imu.txt's samples ({imu.t[0]:.3f}-{imu.t[-1]:.3f} s) cover none of the frames "
                             f"({t[0]:.3f}-{t[-1]:.3f} s): camera only; check that both are stamped by one clock")


def run_slam(seq_path: str | Path, out: str | Path, max_frames: int | None = None, video: bool = False,
             cfg: SlamConfig = DEFAULT_CONFIG, settings: MapSettings = MapSettings(), progress: bool = True,
             save_map: str | Path | None = None, map_path: str | Path | None = None, seed: int = 0,
             session_log: bool = True) -> SlamRun:
    """Run over a sequence and write trajectory.tum, map.csv, stats.json (and video/ with
    ``video``) into ``out``; ``save_map`` : also save the final map there (map_io.py);
    ``map_path`` : start from a saved map instead of the target (re-localise in its frame);
    ``session_log`` : also session.mcap (images, poses, covariance, map; runtime.session_log)."""
    from ..session_log import MAP_EVERY, SESSION_FILE, SessionLog, pose_covariance
    from . import map_io

    if max_frames is not None and max_frames < 1:
        raise ValueError(f"--max-frames {max_frames}: give at least 1 frame")
    seq = open_any(seq_path)    # EuRoC and KITTI folders as shipped, or our layout
    if len(seq) == 0:
        raise SequenceError(f"{seq.root}/rgb.txt lists no images; a sequence needs at least one frame")
    check_lens_invertible(seq.camera)
    if progress:
        for note in seq.notes:
            print(f"slam: note: {note}")
    saved = map_io.load_map(map_path, seq.camera) if map_path is not None else None
    natural = saved is None and seq.target is None
    if natural and seq.imu is not None and settings.imu.use_imu and (getattr(seq, "depth_paths", None) is not None
                                                                     or not settings.imu.imu_handover):
        # The depth's map is metric, but its frame the first camera's, which the IMU's gravity
        # does not know: camera only. (Without depth the IMU is handed the map once it has seen
        # its scale: imu_handover.py.)
        settings = replace(settings, imu=replace(settings.imu, use_imu=False))
        if progress:
            print("slam: natural start" + (" from depth" if settings.imu.imu_handover else "") +
                  ": the IMU does not drive the filter (camera only)")
    out = Path(out)
    writer = None
    slam = MonoSLAM(seq.camera, cfg, settings, imu=seq.imu is not None, seed=seed)
    if seq.imu is not None:
        imu_notes(seq, slam)
        slam.add_imu(np.column_stack([seq.imu.t, seq.imu.gyro, seq.imu.accel]))
    times, poses = [], []
    skipped = 0
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    frames = enumerate(seq.frames())
    said = 0
    waits: dict[str, int] = {}
    # The start comes before the progress bar: a target that cannot start SLAM is one line.
    i0, f = next(frames)
    if saved is not None:
        slam.start_from_map(saved, f.t)
        if f.image is not None:
            slam.process(f.image, f.t)
    elif natural:
        # Frames are taken until a start can be made; those from the start's reference frame on
        # are replayed, those before it get no pose.
        start, replay = wait_for_natural_start(slam, seq, f, frames, n, waits, progress)
        i0, f = replay[0]
        slam.start_natural(f.image, f.t, start)
        frames = itertools.chain(replay[1:], frames)
        if progress:
            print(f"slam: started at frame {i0} (t = {f.t:.3f} s) from {len(slam.features)} natural features, "
                  f"scale: {start.scale}" + (f"; {i0} frames before it" if i0 else ""))
    else:
        if f.image is None:
            raise SlamStartError(f"{f.path}: the first frame cannot be read ({f.problem}); SLAM needs it to start")
        slam.start(f.image, f.t, seq.target)
        moved = slam.refined_target.moved_px
        if progress:
            print(f"slam: target corners found {np.round(moved, 1).tolist()} px from their clicks")
    out.mkdir(parents=True, exist_ok=True)          # after the start: a refused start writes nothing
    if video:
        (out / "video").mkdir(exist_ok=True)
    log = SessionLog(out / SESSION_FILE) if session_log else None
    imu_logged_to = -np.inf
    bar = progress_bar(total=n, initial=i0 + 1, desc="slam", unit="frame", disable=not progress)
    for i in range(i0, n):
        if i > i0:
            _, f = next(frames)
            bar.update(1)
            if f.image is None:
                slam.skip(f.t, f.problem or "unreadable")
                skipped += 1
                progress_bar.write(f"slam: frame {i} ({f.path.name}, t = {f.t:.3f} s) skipped: {f.problem or 'unreadable'}")
            else:
                prev_lost = slam.lost
                st = slam.process(f.image, f.t)
                if st.lost and not prev_lost:
                    progress_bar.write(f"slam: track lost at frame {st.frame} (t = {st.t:.3f} s): fewer than 3 inliers for "
                               f"{slam.settings.relocalisation.lost_after} frames; re-localising against the map")
                if prev_lost and not st.lost:
                    progress_bar.write(f"slam: camera located in the map at frame {st.frame} (t = {st.t:.3f} s)")
        for msg in slam.messages[said:]:
            progress_bar.write(msg)
        said = len(slam.messages)
        T = slam.T_world_cam()
        if np.isfinite(T).all():
            times.append(f.t)
            poses.append(T)
        if log is not None:
            if seq.imu is not None:             # the IMU's samples up to this frame, each at its stamp
                k0, k1 = np.searchsorted(seq.imu.t, [imu_logged_to, f.t], side="right")
                log.imu(np.column_stack([seq.imu.t[k0:k1], seq.imu.gyro[k0:k1], seq.imu.accel[k0:k1]]))
                imu_logged_to = f.t
            if f.image is not None:
                log.image(f.t, f.image)
            st = slam.state
            log.pose(f.t, T, pose_covariance(st.x_v, st.P[:st.cam_dim, :st.cam_dim]) if st is not None else None)
            if (i - i0) % MAP_EVERY == 0 or i == n - 1:
                log.map(f.t, slam.world_points())
        if video and f.image is not None:
            frame = _annotate(f.image, slam)
            cv2.imwrite(str(out / "video" / f"{i:06d}.png"), frame)
            if writer is None:
                fps = (n - 1) / max(seq.timestamps[n - 1] - seq.timestamps[0], 1e-6) if n > 1 else 30.0
                writer = cv2.VideoWriter(str(out / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                         (frame.shape[1], frame.shape[0]))
            writer.write(frame)
    slam.finish()
    bar.close()
    if writer is not None:
        writer.release()
    # A natural start's arbitrary unit, made metric (and the frame turned upright) by the IMU.
    R_out, s_out, imu_scale = np.eye(3), 1.0, None
    handed = slam.handover.done if slam.handover is not None else None
    if natural and slam.scale_source in ("arbitrary", "imu") and seq.imu is not None and len(times) > 2:
        imu_scale = scale_from_imu(np.array(times), np.array(poses), seq.imu)
        if handed is not None:
            R_out, s_out = gravity_aligned(slam.state.gravity), 1.0 / slam.state.k
            imu_scale = dict(imu_scale or {}, filter=filter_scale(slam, handed))
            if progress:
                f = imu_scale["filter"]
                print(f"slam: scale from the IMU in the filter: {s_out:.4g} m per map unit (+- "
                      f"{100 * f['sigma_rel']:.1f}%; {f['scale_at_handover']:.4g} when the IMU took the map "
                      f"{f['handover_after_s']:.1f} s after the start)")
        elif imu_scale is not None and imu_scale["usable"]:
            R_out, s_out = np.array(imu_scale["R_up_world"]), imu_scale["scale"]
            slam.scale_source = "imu"
        if progress and handed is None:
            print("slam: " + imu_scale["said"] if imu_scale is not None else
                  "slam: the IMU cannot give the scale (too short a run): the scale stays arbitrary")
    if times:
        T = map_io.similar_poses(np.array(poses), R_out, s_out) if slam.scale_source == "imu" else np.array(poses)
        write_trajectory(out / "trajectory.tum", np.array(times), T,
                         header="MonoSLAM camera-to-world poses (optical frame), TUM order")
        if log is not None:
            log.trajectory(times[-1], T)
    else:
        (out / "trajectory.tum").write_text("# MonoSLAM: the camera was never localised in the map\n")
    similarity = (R_out, s_out) if slam.scale_source == "imu" else ()
    write_map_csv(out / "map.csv", slam, *similarity)
    if save_map is not None:
        map_io.save_map(save_map, slam, *similarity)
    per_frame = [asdict(s) for s in slam.stats]
    proc = [s for s in slam.stats[1:] if not s.skipped]
    mean = lambda v: float(np.mean(v)) if len(v) else 0.0  # noqa: E731
    first = next((s.t for s in slam.stats if not s.lost), None)     # first frame in the map
    lost_frames = sum(1 for s in slam.stats if s.lost and first is not None and s.t > first) if first is not None \
        else len(slam.stats)
    dt = np.diff(seq.timestamps[i0:n])
    gaps = int((dt > 1.5 * np.median(dt)).sum()) if len(dt) else 0
    result = SlamRun(
        frames=len(slam.stats), skipped=skipped, features=len(slam.features),
        added=sum(s.added for s in slam.stats), deleted=sum(s.deleted for s in slam.stats),
        converted=sum(s.converted for s in slam.stats), lost_frames=lost_frames, lost=lost_frames > 0,
        relocalised=sum(1 for s in slam.stats if s.relocalised),
        reacquired=sum(1 for s in slam.stats if s.reacquired),
        first_localised_s=(first - slam.stats[0].t) if first is not None else None,
        mean_searched=mean([s.searched for s in proc]), mean_matched=mean([s.matched for s in proc]),
        mean_outliers=mean([s.outliers for s in proc]),
        mean_ms_per_frame=1000 * mean([s.seconds for s in proc]),
        median_ms_per_frame=1000 * float(np.median([s.seconds for s in proc])) if proc else 0.0,
        imu_frames=sum(1 for s in proc if s.imu), frame_gaps=gaps, longest_interval_s=float(dt.max()) if len(dt) else 0.0,
        over_cap_frames=sum(1 for s in proc if s.over_cap),
        imu=asdict(slam.imu.counts), messages=tuple(slam.messages),
        **_clock_offset(slam.state), scale=slam.scale_source, frames_before_start=i0, start_waits=waits,
        imu_scale={k: v for k, v in imu_scale.items() if k != "said"} if imu_scale else None)
    (out / "stats.json").write_text(json.dumps({"totals": asdict(result), "frames": per_frame}, indent=1))
    if log is not None:
        log.close()
    return result
