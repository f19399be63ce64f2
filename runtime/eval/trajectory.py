"""Trajectory metrics: absolute trajectory error (metric, no alignment, since the target fixes
the frame; after a rigid SE(3) alignment; and after a similarity Sim(3), for a run whose scale
is arbitrary), relative pose error, as evo reports them, and rotation errors. The alignments are
evo's Umeyama. For scoring runs against ground truth; nothing on the control path uses it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from evo.core.geometry import GeometryException, umeyama_alignment
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
    ate_sim3_rmse_m: float = float("nan")   # after the similarity that best maps the estimate onto the truth
    ate_sim3_max_m: float = float("nan")
    sim3_scale: float = float("nan")        # that similarity's scale: truth units per estimate unit

    def ate(self, align: str) -> tuple[float, float]:
        """(RMSE, max), m, of the ATE after ``align``: "none", "se3" or "sim3"."""
        return {"none": (self.ate_rmse_m, self.ate_max_m), "se3": (self.ate_aligned_rmse_m, self.ate_aligned_max_m),
                "sim3": (self.ate_sim3_rmse_m, self.ate_sim3_max_m)}[align]


#: The alignments an ATE can be taken after.
ALIGNMENTS = ("none", "se3", "sim3")


def associate(est: Trajectory, gt: Trajectory, max_dt: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i_est, i_gt) of poses within ``max_dt`` seconds of each other (nearest)."""
    if len(gt.t) == 0 or len(est.t) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    if len(gt.t) == 1:
        ok = np.abs(gt.t[0] - est.t) <= max_dt
        return np.flatnonzero(ok), np.zeros(int(ok.sum()), int)
    j = np.clip(np.searchsorted(gt.t, est.t), 1, len(gt.t) - 1)
    j = np.where(np.abs(gt.t[j - 1] - est.t) < np.abs(gt.t[j] - est.t), j - 1, j)
    ok = np.abs(gt.t[j] - est.t) <= max_dt
    return np.flatnonzero(ok), j[ok]


def align_sim3(A: np.ndarray, B: np.ndarray, with_scale: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimising sum |s R A_i + t - B_i|^2 (Umeyama, evo's; s = 1 without scale).
    A, B : (n, 3). Points all on one spot or line give R as best it can (evo refuses them)."""
    try:
        R, t, s = umeyama_alignment(np.asarray(A, float).T, np.asarray(B, float).T, with_scale)
    except GeometryException:
        R, s = np.eye(3), 1.0
        t = B.mean(axis=0) - A.mean(axis=0)
    return R, np.asarray(t, float), float(s)


def align_se3(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising sum |R A_i + t - B_i|^2 (Umeyama without scale). A, B : (n, 3)."""
    R, t, _ = align_sim3(A, B, with_scale=False)
    return R, t


def trajectory_errors(est: Trajectory, gt: Trajectory, rpe_delta_s: float = 1.0) -> TrajectoryErrors:
    for traj, what in ((est, "the estimated trajectory"), (gt, "the ground truth")):
        if len(traj.t) < 2:
            raise ValueError(f"{what} has {len(traj.t)} pose{'' if len(traj.t) == 1 else 's'}; at least two are "
                             f"needed to compare trajectories")
    ie, ig = associate(est, gt)
    if len(ie) < 2:
        raise ValueError("fewer than two estimated poses have a ground-truth pose within 5 ms; "
                         "are the timestamps of the same clock?")
    pe, pg = est.p_world_cam[ie], gt.p_world_cam[ig]
    e = np.linalg.norm(pe - pg, axis=1)
    R, t = align_se3(pe, pg)
    ea = np.linalg.norm(pe @ R.T + t - pg, axis=1)
    Rs, ts, scale = align_sim3(pe, pg)
    es = np.linalg.norm(scale * pe @ Rs.T + ts - pg, axis=1)
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
                            rpe_delta_s, rms(es), float(es.max()), scale)


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """(n,) the angle of ``R_a^T R_b`` for (n, 3, 3) or (3, 3) rotations: how far apart they are."""
    R_a, R_b = np.asarray(R_a, float), np.asarray(R_b, float)
    return np.linalg.norm(Rotation.from_matrix(np.swapaxes(R_a, -1, -2) @ R_b).as_rotvec(), axis=-1)


def rotation_errors_deg(t: np.ndarray, R_prev_cur: np.ndarray, groundtruth: Trajectory) -> np.ndarray:
    """Angle (degrees) of R_est^T R_gt per frame pair, R_gt = R_world_prev^T R_world_cur.

    t : (N,) s of the frames; R_prev_cur : (N, 3, 3), row i relating frame i-1 to i (row 0 is
    ignored). Returns (N - 1,) degrees; NaN where the ground truth does not cover both times.
    """
    t = np.asarray(t, float)
    err = np.full(len(t) - 1, np.nan)
    cover = (t >= groundtruth.t[0]) & (t <= groundtruth.t[-1])
    if cover.sum() < 2:
        return err
    idx = np.flatnonzero(cover)
    R_w = np.full((len(t), 3, 3), np.nan)
    R_w[idx] = groundtruth.interpolate(t[idx]).R_world_cam()
    R_gt = np.einsum("nji,njk->nik", R_w[:-1], R_w[1:])
    ok = np.isfinite(R_gt).all(axis=(1, 2))
    D = np.einsum("nji,njk->nik", R_prev_cur[1:][ok], R_gt[ok])
    err[ok] = np.degrees(Rotation.from_matrix(D).magnitude())
    return err
