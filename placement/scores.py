"""Camera placement scores for every polygon of the body (paper, section 2.1 and Fig. 3).

A simulated camera sits at each polygon's centroid, ``standoff_m`` out along its normal, and
moves rigidly with the polygon's segment. Three scores, then a combined one:

``fov``
    Absolute field of view: the fraction of the full 4 pi solid angle around the camera that
    the body does not block, from rays on a Fibonacci sphere (nearly uniform, so each ray
    stands for the same solid angle), averaged over a set of poses.
``handling_view``
    View of the handling space: the fraction of sample points filling the space in front of
    the torso that the hands reach (within an arm's length of a shoulder, from the hips to
    just above the shoulders, at least ``handling_clearance_m`` in front of the torso; it
    moves with the abdomen) that the camera sees with a clear line of sight and within
    ``cone_deg`` of the polygon's normal, averaged over the poses. The default cone, 90
    degrees, is the half-space outside the polygon: an active head can turn to look anywhere
    its mount does not hide; a smaller cone models a fixed camera's field of view.
``motion_mm``, ``motion_deg``
    Resilience to wearer motion (lower is better): the mean distance of the camera from its
    time-averaged position, and the mean angle of its orientation from its time-averaged
    orientation, over the motion set. "World" figures are taken in a frame moving with the
    wearer's progression (:func:`progression`: the straight-line fit of the pelvis's path, bent
    to follow its slow departures from a straight line when the feet travel too, so that
    walking is not counted as motion, steady or not, straight or curving, but bounce, sway and
    turning are);
    ``motion_pelvis_mm`` and ``motion_pelvis_deg`` are relative to the pelvis.
``combined``
    ``w_fov fov + w_handling handling_view + w_motion / (1 + motion_mm / motion_scale_mm)``,
    weights normalised to sum to one (default equal; ``motion_scale_mm`` 100 mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation
from kinematics.progress import progress_bar

from kinematics.rays import RayCaster
from kinematics.summary import fibonacci_sphere
from kinematics.transforms import nearest_rotation

from .body import SEGMENT_INDEX, SEGMENTS, Body, Motion, Pose

SCORE_COLUMNS = ("fov", "handling_view", "motion_mm", "motion_deg", "motion_pelvis_mm", "motion_pelvis_deg",
                 "combined")


@dataclass(frozen=True)
class ScoreSettings:
    rays: int = 2048
    standoff_m: float = 0.02
    cone_deg: float = 90.0
    handling_points: int = 400
    handling_clearance_m: float = 0.10
    motion_frames: int = 30          # frames sampled from each motion
    w_fov: float = 1.0
    w_handling: float = 1.0
    w_motion: float = 1.0
    motion_scale_mm: float = 100.0

    def __post_init__(self):
        if self.rays < 16:
            raise ValueError(f"rays = {self.rays}: use at least 16 (2048 is the default)")
        if not 0 <= self.standoff_m < 0.5:
            raise ValueError(f"standoff {self.standoff_m} m: give metres between 0 and 0.5 (default 0.02)")
        if min(self.w_fov, self.w_handling, self.w_motion) < 0 or self.w_fov + self.w_handling + self.w_motion <= 0:
            raise ValueError("score weights must be >= 0 with a positive sum")


@dataclass
class ScoreTable:
    """Per-polygon results: arrays of length F (faces), plus the settings that made them."""

    polygon: np.ndarray
    segment: np.ndarray          # segment names
    centroid: np.ndarray         # (F, 3) rest pose, body frame, m
    normal: np.ndarray           # (F, 3) rest pose
    scores: dict                 # name -> (F,) array, SCORE_COLUMNS
    settings: ScoreSettings
    poses: tuple[str, ...]
    motions: tuple[str, ...]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.scores[name]


def camera_points(body: Body, pose: Pose | None, standoff_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3) camera positions (centroid + standoff along the normal) and (F, 3) normals, posed."""
    c, n = body.face_frames(pose)
    return c + standoff_m * n, n


def fov_fraction(occluder: RayCaster, cameras: np.ndarray, rays: int = 2048, chunk_rays: int = 1 << 21) -> np.ndarray:
    """(n,) fraction of the full sphere of directions around each camera (n, 3) that the
    occluder's mesh does not block, from ``rays`` directions on a Fibonacci sphere."""
    dirs = fibonacci_sphere(rays)
    per_chunk = max(1, chunk_rays // rays)
    out = np.empty(len(cameras))
    for s in range(0, len(cameras), per_chunk):
        c = cameras[s:s + per_chunk]
        o = np.repeat(c, rays, axis=0)
        d = np.tile(dirs, (len(c), 1))
        out[s:s + per_chunk] = 1.0 - occluder.blocked(o, d).reshape(len(c), rays).mean(axis=1)
    return out


def fov_scores(body: Body, poses: dict[str, Pose], rays: int = 2048, standoff_m: float = 0.02,
               progress: bool = False) -> np.ndarray:
    """(F,) mean over poses of the unblocked fraction of the sphere of directions around each camera."""
    total = np.zeros(body.face_count)
    with progress_bar(total=len(poses), desc="field of view", unit="pose", disable=not progress) as bar:
        for pose in poses.values():
            cams, _ = camera_points(body, pose, standoff_m)
            total += fov_fraction(RayCaster(body.posed_vertices(pose), body.faces), cams, rays)
            bar.update(1)
    return total / len(poses)


def handling_space(body: Body, n_points: int = 400, clearance_m: float = 0.10) -> np.ndarray:
    """(n, 3) points (rest pose, body frame) filling the space in front of the torso the hands reach."""
    j = body.joints
    sh = j[[SEGMENT_INDEX["upper_arm_l"], SEGMENT_INDEX["upper_arm_r"]]]
    reach = body.arm_length_m
    front = body.vertices[np.isin(body.vertex_segment, [SEGMENT_INDEX[s] for s in ("chest", "abdomen", "pelvis")]), 1].min()
    z_lo = j[SEGMENT_INDEX["thigh_l"], 2]
    z_hi = sh[:, 2].max() + 0.1
    y_hi = front - clearance_m
    y_lo = sh[:, 1].min() - reach
    x_lo, x_hi = sh[:, 0].min() - reach * 0.6, sh[:, 0].max() + reach * 0.6
    # A lattice whose spacing leaves about n_points inside the reach (two refinements suffice).
    box = np.array([[x_lo, x_hi], [y_lo, y_hi], [z_lo, z_hi]])
    h = (np.prod(box[:, 1] - box[:, 0]) / n_points) ** (1 / 3)
    for _ in range(4):
        axes = [np.arange(lo + h / 2, hi, h) for lo, hi in box]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        inside = np.min(np.linalg.norm(g[:, None, :] - sh[None], axis=2), axis=1) <= reach
        h *= (max(inside.sum(), 1) / n_points) ** (1 / 3)
    return g[inside]


def handling_scores(body: Body, poses: dict[str, Pose], points_rest: np.ndarray, cone_deg: float = 80.0,
                    standoff_m: float = 0.02, progress: bool = False) -> np.ndarray:
    """(F,) mean over poses of the fraction of handling-space points seen in the cone, unblocked."""
    F = body.face_count
    total = np.zeros(F)
    cos_cone = math.cos(math.radians(cone_deg))
    ab = SEGMENT_INDEX["abdomen"]
    per_chunk = max(1, (1 << 20) // len(points_rest))
    with progress_bar(total=F * len(poses), desc="handling view", unit="place", disable=not progress) as bar:
        for pose in poses.values():
            G = body.segment_transforms(pose)[ab]
            pts = points_rest @ G[:3, :3].T + G[:3, 3]
            occ = RayCaster(body.posed_vertices(pose), body.faces)
            cams, normals = camera_points(body, pose, standoff_m)
            for s in range(0, F, per_chunk):
                c, n = cams[s:s + per_chunk], normals[s:s + per_chunk]
                v = pts[None, :, :] - c[:, None, :]
                dist = np.linalg.norm(v, axis=2)
                d = v / dist[..., None]
                in_cone = np.einsum("fpk,fk->fp", d, n) >= cos_cone
                seen = np.zeros_like(in_cone)
                idx = np.nonzero(in_cone)
                if len(idx[0]):
                    seen[idx] = ~occ.blocked(c[idx[0]], d[idx], dist[idx])
                total[s:s + per_chunk] += seen.mean(axis=1)
                bar.update(len(c))
    return total / len(poses)


def _dispersion(p: np.ndarray, R: Rotation) -> tuple[np.ndarray, np.ndarray]:
    """Mean distance (F,) of positions p (T, F, 3) from their time mean, and mean angle (F,) of
    rotations R (T*F, row-major T then F) from their mean, radians."""
    T, F = p.shape[:2]
    dist = np.linalg.norm(p - p.mean(axis=0), axis=2).mean(axis=0)
    Rm = R.as_matrix().reshape(T, F, 3, 3)
    Rbar = nearest_rotation(Rm.mean(axis=0))          # the chordal L2 mean rotation per face
    rel = np.einsum("fji,tfjk->tfik", Rbar, Rm)                  # Rbar^T R(t)
    cos = np.clip((np.trace(rel, axis1=2, axis2=3) - 1) / 2, -1, 1)
    ang = np.arccos(cos).mean(axis=0)
    return dist, ang


#: The wearer's progression is the pelvis's horizontal path smoothed over about a stride (a
#: Gaussian of this standard deviation, s, applied twice): it follows starting, stopping and
#: curving, not the sway of the steps.
PROGRESSION_SMOOTHING_S = 0.5


def _path_length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def progression(body: Body, motion: Motion, G: np.ndarray | None = None) -> np.ndarray:
    """(T, 3) where the wearer is going, body frame, metres, at each frame of ``motion``.

    The straight-line fit (in time) of the pelvis joint's path, bent by the slow part of the
    pelvis's horizontal departures from that line (smoothed over a stride,
    :data:`PROGRESSION_SMOOTHING_S`) in the measure that the feet travel with it: fully for a
    walk, steady or not, straight or curving (an imported walk starts, stops and veers), not at
    all when the feet stay put while the hips move (sitting down), which is camera motion.
    A steady straight walk (the procedural one) is its straight line either way.
    G : the motion's segment transforms (T, 16, 4, 4) if already computed.
    """
    G = body.segment_transforms(motion) if G is None else G
    t = np.asarray(motion.t, float)
    A = np.column_stack([np.ones(len(t)), t - t[0]])

    def line(p):
        coef, *_ = np.linalg.lstsq(A, p, rcond=None)
        return A @ coef

    pelvis = np.einsum("tij,j->ti", G[:, 0, :3, :3], body.joints[0]) + G[:, 0, :3, 3]
    path = line(pelvis)
    dt = float(np.median(np.diff(t))) if len(t) > 2 else 0.0
    if not dt > 0:
        return path
    # "Twicing" (Tukey): smoothing, then smoothing the residue, keeps the slow part without the
    # bias one smoothing leaves where the speed changes (it would round every ramp off).
    smooth = partial(gaussian_filter1d, sigma=PROGRESSION_SMOOTHING_S / dt, axis=0, mode="nearest")

    def slow(p):
        s1 = smooth(p)
        return s1 + smooth(p - s1)

    feet = [SEGMENT_INDEX["foot_l"], SEGMENT_INDEX["foot_r"]]
    Gk = G[:, feet]
    ankles = (np.einsum("tkij,kj->tki", Gk[..., :3, :3], body.joints[feet]) + Gk[..., :3, 3]).mean(axis=1)
    travel = _path_length(slow(pelvis[:, :2]))
    share = min(1.0, _path_length(slow(ankles[:, :2])) / travel) if travel > 1e-6 else 0.0
    path[:, :2] += share * slow(pelvis[:, :2] - path[:, :2])
    return path


def motion_scores(body: Body, motions: list[Motion], standoff_m: float = 0.02, frames: int = 30,
                  progress: bool = False) -> dict[str, np.ndarray]:
    """Mean camera displacement (mm) and rotation (deg) over the motions, world and pelvis frames."""
    F = body.face_count
    c0, n0 = body.face_frames()
    cam_rest = c0 + standoff_m * n0
    seg = body.face_segment
    out = {k: np.zeros(F) for k in ("motion_mm", "motion_deg", "motion_pelvis_mm", "motion_pelvis_deg")}
    for m in progress_bar(motions, desc="motion", unit="motion", disable=not progress):
        # The progression from every frame (the smoothing needs them), the cameras from a few.
        keep = m.subsample_indices(frames)
        travel = progression(body, m)[keep]
        m = m.subsample(frames)
        G = body.segment_transforms(m)                     # (T, 16, 4, 4)
        Gf = G[:, seg]                                     # (T, F, 4, 4)
        p = np.einsum("tfij,fj->tfi", Gf[..., :3, :3], cam_rest) + Gf[..., :3, 3]
        d, a = _dispersion(p - travel[:, None, :], Rotation.from_matrix(Gf[..., :3, :3].reshape(-1, 3, 3)))
        out["motion_mm"] += 1000 * d
        out["motion_deg"] += np.degrees(a)
        Gp_inv = np.linalg.inv(G[:, 0])                    # pelvis frame
        Gr = Gp_inv[:, None] @ Gf
        p_pel = np.einsum("tfij,fj->tfi", Gr[..., :3, :3], cam_rest) + Gr[..., :3, 3]
        d, a = _dispersion(p_pel, Rotation.from_matrix(Gr[..., :3, :3].reshape(-1, 3, 3)))
        out["motion_pelvis_mm"] += 1000 * d
        out["motion_pelvis_deg"] += np.degrees(a)
    return {k: v / len(motions) for k, v in out.items()}


def combined_score(fov, handling_view, motion_mm, s: ScoreSettings) -> np.ndarray:
    """Weighted sum of field of view, handling view and motion resilience 1 / (1 + mm / scale)."""
    w = np.array([s.w_fov, s.w_handling, s.w_motion], float)
    w = w / w.sum()
    return w[0] * fov + w[1] * handling_view + w[2] / (1.0 + motion_mm / s.motion_scale_mm)


def score_body(body: Body, poses: dict[str, Pose], motions: list[Motion], settings: ScoreSettings = ScoreSettings(),
               progress: bool = False) -> ScoreTable:
    """All scores for every polygon of the body."""
    fov = fov_scores(body, poses, settings.rays, settings.standoff_m, progress)
    pts = handling_space(body, settings.handling_points, settings.handling_clearance_m)
    hv = handling_scores(body, poses, pts, settings.cone_deg, settings.standoff_m, progress)
    mo = motion_scores(body, motions, settings.standoff_m, settings.motion_frames, progress)
    scores = {"fov": fov, "handling_view": hv, **mo}
    scores["combined"] = combined_score(fov, hv, mo["motion_mm"], settings)
    c, n = body.face_frames()
    return ScoreTable(polygon=np.arange(body.face_count), segment=np.array([SEGMENTS[i] for i in body.face_segment]),
                      centroid=c, normal=n, scores={k: scores[k] for k in SCORE_COLUMNS}, settings=settings,
                      poses=tuple(poses), motions=tuple(m.name for m in motions))
