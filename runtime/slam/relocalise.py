"""Re-acquiring the track after it is lost: the mapped features' templates are searched over
the whole image, and a camera pose is fitted to the 2D-3D matches by PnP inside RANSAC
(OpenCV), as Williams, Klein and Reid's relocaliser does for MonoSLAM, with the target's
corners and the most reliable natural features as candidates.

PnP-RANSAC's inliers are few (a map made from a still camera holds points whose depth is known to
a few per cent, some pixels off from a new view, beyond its 2 px gate), and a minimal set's pose
can be several centimetres and degrees off. So, given the points' covariances, the pose is then
refined over every feature's match (:func:`refine_pose`): each weighted by its pixel noise and
its point's uncertainty projected into the image, gated by the Mahalanobis distance that also
counts the pose's own uncertainty, until the set of matches no longer changes.

The filter is then restarted at that pose: the camera block's mean is replaced, its velocity
set to zero, and its covariance reset to ``P_cam`` with no correlation to the map (the map's own
covariance is kept).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, project, undistort
from kinematics.transforms import so3_exp

from .appearance.search import global_matches
from .startup import pose_jacobians


CHI2_2DOF_99 = 9.21      # a match's gate in refine_pose: chi-square, 2 dof, 99%


@dataclass(frozen=True)
class Relocalisation:
    """R_world_cam : (3, 3), r : (3,) optical centre, world, m; inliers : feature indices used."""

    R_world_cam: np.ndarray
    r: np.ndarray
    inliers: np.ndarray


@dataclass(frozen=True)
class RefinedPose:
    """R_world_cam : (3, 3), r : (3,) m; cov : (6, 6) of (small rotation in the camera frame,
    rad; position, m); used : (k,) the features whose matches it was fitted to, uv : (k, 2) px
    their matches."""

    R_world_cam: np.ndarray
    r: np.ndarray
    cov: np.ndarray
    used: np.ndarray
    uv: np.ndarray


def refine_pose(cam: CameraIntrinsics, Y: np.ndarray, Y_cov: np.ndarray, uv: np.ndarray, owner: np.ndarray,
                R_world_cam: np.ndarray, r: np.ndarray, sigma_px: float, start: np.ndarray,
                gate: float = CHI2_2DOF_99, rounds: int = 6, steps: int = 10) -> RefinedPose | None:
    """The camera pose by weighted least squares over whole-image matches, from a first pose.

    Y : (m, 3) world points, m, and Y_cov (m, 3, 3) their covariances; uv : (j, 2) px candidate
    matches, owner (j,) the point each is of (several per point allowed); start : the points
    the first pose was fitted to (each takes its match nearest that pose). Each point's residual
    is weighted by ``sigma_px^2 I + J_y Y_cov J_y^T``; a round fits the pose to the chosen
    matches by Gauss-Newton, then chooses again, for every point, its match nearest in
    Mahalanobis distance with the pose's covariance added, within ``gate``; it stops when the
    choice repeats. Correlations between the points are ignored. Returns None when fewer than 4
    points hold or the fit fails.
    """
    points = np.unique(owner)
    ks = np.unique(start)
    obs = np.array([_nearest(cam, uv[owner == k], Y[k], R_world_cam, r) for k in ks]).reshape(-1, 2)
    for _ in range(rounds):
        if len(ks) < 4:
            return None
        for _ in range(steps):
            pred, J, J_y = pose_jacobians(cam, Y[ks], R_world_cam, r)
            if not np.isfinite(pred).all():
                return None
            W = np.linalg.inv(sigma_px**2 * np.eye(2) + J_y @ Y_cov[ks] @ np.swapaxes(J_y, 1, 2))
            JtW = np.swapaxes(J, 1, 2) @ W
            H = np.einsum("nij,njk->ik", JtW, J)
            try:
                d = np.linalg.solve(H, np.einsum("nij,nj->i", JtW, obs - pred))
            except np.linalg.LinAlgError:
                return None
            R_world_cam, r = R_world_cam @ so3_exp(d[:3]), r + d[3:]
            if np.abs(d).max() < 1e-9:
                break
        cov = np.linalg.inv(H)
        pred, J, J_y = pose_jacobians(cam, Y[points], R_world_cam, r)
        S_inv = np.linalg.inv(sigma_px**2 * np.eye(2) + J_y @ Y_cov[points] @ np.swapaxes(J_y, 1, 2)
                              + J @ cov @ np.swapaxes(J, 1, 2))
        chosen_k, chosen_uv = [], []
        for i, k in enumerate(points):
            c = uv[owner == k]
            e = c - pred[i]
            d2 = np.einsum("ni,ij,nj->n", e, S_inv[i], e)
            if np.isfinite(d2).any() and np.nanmin(d2) < gate:
                chosen_k.append(k)
                chosen_uv.append(c[int(np.nanargmin(d2))])
        chosen_k, chosen_uv = np.array(chosen_k, np.intp), np.array(chosen_uv).reshape(-1, 2)
        if np.array_equal(chosen_k, ks) and np.array_equal(chosen_uv, obs):
            break
        fitted = RefinedPose(R_world_cam, r, cov, ks, obs)
        ks, obs = chosen_k, chosen_uv
    else:
        return fitted          # the choice still changing: the last fit
    return RefinedPose(R_world_cam, r, cov, ks, obs)


def _nearest(cam: CameraIntrinsics, c: np.ndarray, y: np.ndarray, R_world_cam: np.ndarray, r: np.ndarray) -> np.ndarray:
    p = project(cam, ((y - r) @ R_world_cam)[None])[0]
    return c[int(np.argmin(np.linalg.norm(c - p, axis=1)))]


def relocalise(image: np.ndarray, templates: list[np.ndarray], Y: np.ndarray, cam: CameraIntrinsics,
               max_score: float = 0.2, reprojection_px: float = 2.0, min_inliers: int = 4,
               Y_cov: np.ndarray | None = None, sigma_px: float = 1.0) -> Relocalisation | None:
    """A camera pose from whole-image matches of mapped features, or None.

    templates : the features' 15 x 15 templates; Y : (m, 3) their world positions, m.
    A pose needs at least ``min_inliers`` matches within ``reprojection_px`` of their
    reprojection. With ``Y_cov`` (m, 3, 3), the points' covariances, the pose is then refined
    over every point's matches (:func:`refine_pose`, pixel noise ``sigma_px``).
    """
    uv, owner = global_matches(image, templates, max_score)
    xy = undistort(cam, uv) if len(uv) else uv
    good = np.isfinite(xy).all(axis=1)
    uv, owner, xy = uv[good], owner[good], xy[good]
    if len(np.unique(owner)) < max(min_inliers, 4):
        return None
    try:
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            Y[owner].astype(np.float64), xy.astype(np.float64), np.eye(3), None,
            reprojectionError=reprojection_px / max(cam.fx, cam.fy), iterationsCount=5000, confidence=0.999,
            flags=cv2.SOLVEPNP_AP3P)   # minimal 4-point sets: fewest draws
    except cv2.error:
        return None
    if not found or inl is None:
        return None
    inl = inl.ravel()
    # One image point per feature: a feature with two inlier peaks keeps the better fitting one.
    keep = {}
    R_cw, _ = cv2.Rodrigues(rvec)
    Pc = Y[owner[inl]] @ R_cw.T + tvec.ravel()
    res = np.linalg.norm(Pc[:, :2] / Pc[:, 2:3] - xy[inl], axis=1)
    for j, e in zip(inl, res):
        if owner[j] not in keep or e < keep[owner[j]][1]:
            keep[owner[j]] = (j, e)
    inl = np.array([j for j, _ in keep.values()])
    if len(inl) < min_inliers:
        return None
    inl = inl.ravel()
    X, x = Y[owner[inl]].astype(np.float64), xy[inl].astype(np.float64)
    # Re-solve on the inliers: coplanar points (the target alone) have a two-fold ambiguity that
    # the minimal solver can pick wrongly; IPPE takes the better of the two, SQPnP the rest.
    c = X - X.mean(axis=0)
    planar = np.linalg.svd(c, compute_uv=False)[-1] < 1e-3 * max(np.linalg.norm(c, axis=1).max(), 1e-9)
    try:
        ok, rvec, tvec = cv2.solvePnP(X, x, np.eye(3), None,
                                      flags=cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP)
    except cv2.error:        # degenerate inliers (nearly coincident points): no pose from them
        return None
    if not ok or not np.isfinite(tvec).all():
        return None
    R_cam_world, _ = cv2.Rodrigues(rvec)
    Pc = X @ R_cam_world.T + tvec.ravel()
    err = np.linalg.norm(Pc[:, :2] / Pc[:, 2:3] - x, axis=1) * max(cam.fx, cam.fy)
    if np.any(Pc[:, 2] <= 0) or err.max() > 2 * reprojection_px:
        return None
    R_world_cam = R_cam_world.T
    found = Relocalisation(R_world_cam, -R_world_cam @ tvec.ravel(), owner[inl])
    if Y_cov is None:
        return found
    ref = refine_pose(cam, Y, Y_cov, uv, owner, found.R_world_cam, found.r, sigma_px, found.inliers)
    if ref is None or len(ref.used) < len(found.inliers):
        return found
    return Relocalisation(ref.R_world_cam, ref.r, ref.used)
