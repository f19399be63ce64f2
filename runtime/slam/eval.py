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
