"""Trajectory evaluation: absolute trajectory error (metric, no alignment, since the target
fixes the frame; and after a rigid SE(3) alignment) and relative pose error, as evo reports."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..sequence import Trajectory


@dataclass(frozen=True)
class TrajectoryErrors:
    matched: int
    ate_rmse_m: float
    ate_max_m: float
    ate_aligned_rmse_m: float
    ate_aligned_max_m: float
    rpe_trans_rmse_m: float       # over ``rpe_delta_s``
    rpe_rot_rmse_deg: float
    rpe_delta_s: float


def associate(est: Trajectory, gt: Trajectory, max_dt: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i_est, i_gt) of poses within ``max_dt`` seconds of each other (nearest)."""
    j = np.clip(np.searchsorted(gt.t, est.t), 1, len(gt.t) - 1)
    j = np.where(np.abs(gt.t[j - 1] - est.t) < np.abs(gt.t[j] - est.t), j - 1, j)
    ok = np.abs(gt.t[j] - est.t) <= max_dt
    return np.flatnonzero(ok), j[ok]


def align_se3(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising sum |R A_i + t - B_i|^2 (Umeyama without scale). A, B : (n, 3)."""
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((B - cb).T @ (A - ca))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return R, cb - R @ ca


def trajectory_errors(est: Trajectory, gt: Trajectory, rpe_delta_s: float = 1.0) -> TrajectoryErrors:
    ie, ig = associate(est, gt)
    if len(ie) < 2:
        raise ValueError("fewer than two estimated poses have a ground-truth pose within 5 ms; "
                         "are the timestamps of the same clock?")
    pe, pg = est.p_world_cam[ie], gt.p_world_cam[ig]
    e = np.linalg.norm(pe - pg, axis=1)
    R, t = align_se3(pe, pg)
    ea = np.linalg.norm(pe @ R.T + t - pg, axis=1)
    Te, Tg = est.T_world_cam()[ie], gt.T_world_cam()[ig]
    te = est.t[ie]
    k = np.searchsorted(te, te + rpe_delta_s)
    ok = k < len(te)
    dt_err, dr_err = [], []
    for i, j in zip(np.flatnonzero(ok), k[ok]):
        de = np.linalg.inv(Te[i]) @ Te[j]
        dg = np.linalg.inv(Tg[i]) @ Tg[j]
        E = np.linalg.inv(dg) @ de
        dt_err.append(np.linalg.norm(E[:3, 3]))
        dr_err.append(np.degrees(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec())))
    rms = lambda v: float(np.sqrt(np.mean(np.square(v)))) if len(v) else float("nan")  # noqa: E731
    return TrajectoryErrors(len(ie), rms(e), float(e.max()), rms(ea), float(ea.max()), rms(dt_err), rms(dr_err),
                            rpe_delta_s)


@dataclass(frozen=True)
class MapErrors:
    """Map points against the true surfaces (a sequence with depth images).

    ids : (n,) feature ids evaluated; errors_m : (n,) distance from each point to the surface
    point seen through its projection in its first frame (ground-truth pose and depth), m.
    """

    ids: np.ndarray
    errors_m: np.ndarray

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.errors_m**2))) if len(self.errors_m) else float("nan")

    @property
    def median_m(self) -> float:
        return float(np.median(self.errors_m)) if len(self.errors_m) else float("nan")


def map_errors(seq, map_csv) -> MapErrors:
    """Each mapped feature of ``map_csv`` (run.py's map.csv) against the sequence's true depth:
    the feature is projected with the ground-truth pose of its first frame, the depth image
    there gives the true surface point on that pixel's ray, and the error is the distance
    between the two. Features whose pixel falls outside the image or has no depth are left out.
    ``seq`` : an opened sequence (runtime.sequence.open_sequence) with groundtruth.txt and depth.txt."""
    import csv

    from kinematics.camera import project, unproject

    if seq.groundtruth is None or seq.depth_paths is None:
        raise ValueError(f"{seq.root}: map errors need groundtruth.txt and depth.txt (record with --depth)")
    T = seq.groundtruth.T_world_cam()
    ids, errs, cache = [], [], {}
    with open(map_csv, newline="") as fh:
        for row in csv.DictReader(fh):
            i = int(row["first_frame"])
            y = np.array([float(row["x"]), float(row["y"]), float(row["z"])])
            j = int(np.argmin(np.abs(seq.groundtruth.t - seq.timestamps[i])))
            R, r = T[j][:3, :3], T[j][:3, 3]
            uv = project(seq.camera, ((y - r) @ R)[None])[0]
            if not np.all(np.isfinite(uv)):
                continue
            u, v = int(round(uv[0])), int(round(uv[1]))
            if not (0 <= u < seq.camera.width and 0 <= v < seq.camera.height):
                continue
            if i not in cache:
                cache[i] = seq.depth(i)
            d = None if cache[i] is None else cache[i][v, u]
            if d is None or not np.isfinite(d):
                continue
            ray = unproject(seq.camera, uv[None])[0]           # z = 1 in the optical frame
            X = r + R @ (d * ray / ray[2])
            ids.append(int(row["id"]))
            errs.append(float(np.linalg.norm(y - X)))
    return MapErrors(np.array(ids, dtype=int), np.array(errs))
