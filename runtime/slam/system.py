"""MonoSLAM for the wearable (paper, section 4): the per-frame loop over the EKF.

Each frame: predict with the constant-velocity model; predict which map features are visible
(projection well inside the image, viewing angle and range close enough to the first view for
the template to be valid); measure them one at a time, most uncertain first, each searched
only inside its 3-sigma ellipse and each update shrinking the ellipses of those after it;
refine the depth particles of features still being initialised and promote those whose depth
pdf has become Gaussian; delete features whose long-term ratio of successful to attempted
measurements falls below 1:2; and, when 5 or fewer features were measured, start new ones on
Shi-Tomasi corners in empty parts of the image. Start-up: the known target points fix the world
frame and scale (their pose by PnP, then inserted as features with small covariance).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import cv2
import numpy as np

from kinematics.camera import (CameraIntrinsics, in_image, lens_kernel_args, project_point_kernel,
                               undistort, unproject)
from kinematics.camera import project as project_points
from scipy.spatial.transform import Rotation

from ..sequence import Target
from . import depth_init
from .features import grey, new_features
from .filter import FeatureNotMeasurable, SequentialUpdate, add_point_feature, innovation_covariances
from .measurement import h_and_jacobians_many, ray_from_pixel
from .relocalise import relocalise
from .inertial import predict_imu
from .motion import f_and_dfdx, predict
from .search import HALF as HALF_T
from .search import extract_template, search
from .state import (CAMERA_DIM, DEFAULT_CONFIG, SlamConfig, SlamNumericalError, State, check_covariance,
                    compiled_kernel, quat_conjugate, quat_multiply, quat_to_rotation, quat_to_rotvec)


@dataclass(frozen=True)
class MapSettings:
    """Map management and initialisation parameters (paper, sections 4.2 and 4.3)."""

    particles: int = 100
    depth_near_m: float = 0.5
    depth_far_m: float = 5.0
    # Promote a ray when std(depth) < gauss_ratio mean(depth) after at least min_init_frames
    # frames. MonoSLAM's 0.3 promoted after 2 frames on the twin, with depths 2-4 sigma off when
    # the camera estimate was slightly wrong (the frames' likelihoods share its error); 0.15 and
    # 5 frames took sit-down from 10 cm to 4.5 cm ATE.
    gauss_ratio: float = 0.15
    prune: float = 0.001              # drop particles below 0.1% of the strongest
    max_init_frames: int = 30         # give up on a ray that has not converged by then
    min_init_frames: int = 5
    # New features only where the motion model keeps them in view for lookahead_s (at 1 m):
    # a ray needs >= 5 frames to become a point and should then serve for a while. On twin
    # recordings it took the wide-angle sequence from 1.02 to 0.78 cm and workbench-static
    # from 0.29 to 0.42; walk stayed tracked at 0.6 s but not at 0.3, 0.8 or 1.0 s.
    lookahead_s: float = 0.6
    lookahead_depth_m: float = 1.0
    # The particles' spread understates the depth's uncertainty: each frame's likelihood is
    # treated as independent, yet all share the camera estimate's error. Promoting with twice
    # the spread took sit-down from 1.64 to 1.26 cm and kept walk tracked from 4.0 s to 10.6 s.
    promote_std_gain: float = 2.0
    outlier: float = 0.1              # chance that a ray's match is wrong (uniform over the band)
    add_below: int = 6                # add features when fewer than 6 (5 or fewer) were measured
    max_initialising: int = 6         # rays in flight: 3 left walk and sit-down short of features
    delete_min_attempts: int = 10
    delete_ratio: float = 0.5         # successful : attempted below 1:2 deletes
    max_view_angle_deg: float = 45.0
    max_range_ratio: float = 1.4
    # The target's corners, predicted through the target's known plane, stay valid over larger
    # changes of view: walking up to a fixated target they were otherwise dropped at 1.4x closer
    # and the camera drifted off (walk-ahead closed loop: ATE 14 cm -> 0.7 cm). Natural
    # features keep the tighter limits: their fitted planes are not good enough (walk was lost
    # at 7 s with 2.5 for them too).
    max_view_angle_known_deg: float = 60.0
    max_range_ratio_known: float = 2.5
    margin_px: float = 12.0
    outlier_px: float = 3.0           # a posteriori residual making a match an outlier
    # Zero-mean normalised SSD accepting a match (2 (1 - ZNCC)): 0.2, i.e. ZNCC >= 0.9; at 0.4
    # patches on occluding contours kept matching as their background slid (sit-down 2.2 cm
    # against 1.7).
    match_score: float = 0.2
    lost_after: int = 10              # frames with fewer than 3 matches before "lost"
    lost_noise_gain: float = 2.0      # while lost, impulse standard deviations grow by this
    reloc_candidates: int = 30        # target points and most reliable features tried
    reloc_every: int = 3              # frames between whole-image attempts while lost
    reloc_min_inliers: int = 4         # PnP inliers; the active search must then confirm it
    reloc_min_confirmed: int = 4       # with this many matches, and half those searched, at the new pose
    reloc_sigma_m: float = 0.02       # camera uncertainty after re-acquiring, m
    reloc_sigma_q: float = 0.01       # and per quaternion component
    target_sigma_m: float = 0.001
    init_sigma_v: float = 0.3         # initial velocity uncertainty, m/s
    init_sigma_w: float = 0.5         # initial angular velocity uncertainty, rad/s
    # Predict templates by the plane-induced homography: "known" warps the target's corners,
    # whose plane is known; "neighbours" (default) also warps a natural feature once its map
    # neighbours fit a plane through it (a bench top, a wall, a box face); "all" warps every
    # feature, natural ones on MonoSLAM's fronto-parallel guess. On twin recordings (seed 0):
    # workbench-static 12 s 0.92 cm "known" -> 0.30 cm "neighbours"; sit-down 1.26 -> 1.31;
    # the 1000-frame wide-angle sequence 1.57 -> 1.00; "all" lost workbench-static (the guess
    # is wrong for a bench seen at 45 degrees).
    warp: str = "neighbours"
    plane_radius_m: float = 0.25      # map neighbours a natural feature's plane is fitted to
    plane_tol_m: float = 0.01         # their RMS distance from the plane, at most
    normals_every: int = 10           # frames between refits while the map is unchanged
    warp_fallback: bool = True        # search with the first-view template if the warped one fails
    # Integrate the IMU between frames when the sequence has one (inertial.py).
    use_imu: bool = True
    # IMU bias estimates from the vision corrections (time constant, s; 0 = off: the IMU is
    # taken as calibrated). With MEMS-sized biases (5 mrad/s, 0.05 m/s^2) added to the twin's
    # IMU, walk was lost at 7.5 s with it off and gave 1.5 cm with 10 s; on the twin's own
    # (unbiased) IMU, 10 s costs accuracy (walk 0.68 -> 0.97 cm), hence off by default.
    bias_time_s: float = 0.0
    bias_min_matches: int = 4         # frames with fewer matches teach the biases nothing

    def __post_init__(self):
        if self.warp not in ("known", "neighbours", "all"):
            raise ValueError(f"MapSettings.warp = {self.warp!r}: give 'known', 'neighbours' or 'all'")


@dataclass
class MapFeature:
    id: int
    template: np.ndarray
    first_frame: int
    r0: np.ndarray                 # camera centre at the first view
    known: bool = False            # a target point
    attempts: int = 0
    successes: int = 0
    # For predicting the template's appearance from the current viewpoint: the first view's
    # larger patch, pixel, camera orientation (world from camera), and the patch's plane normal.
    patch: np.ndarray | None = None
    uv0: np.ndarray | None = None
    R0: np.ndarray | None = None
    normal: np.ndarray | None = None
    normal_from_map: bool = False  # normal fitted to neighbouring map points (warp="neighbours")
    rays0: np.ndarray | None = None  # (4, 3) world rays of the first view's patch corners (cache)


PATCH_HALF = 20   # the stored first-view patch is 41 x 41, room to warp a 15 x 15 template


def _patch(image: np.ndarray, uv) -> np.ndarray | None:
    u, v = int(round(float(uv[0]))), int(round(float(uv[1])))
    h, w = image.shape[:2]
    if u - PATCH_HALF < 0 or v - PATCH_HALF < 0 or u + PATCH_HALF >= w or v + PATCH_HALF >= h:
        return None
    return image[v - PATCH_HALF:v + PATCH_HALF + 1, u - PATCH_HALF:u + PATCH_HALF + 1].copy()


def warped_template(f: MapFeature, x_v: np.ndarray, y: np.ndarray, cam: CameraIntrinsics) -> np.ndarray:
    """The feature's template as the current camera should see it: the first-view patch warped
    by the homography its plane (through y, normal ``f.normal``) induces between the two views
    (computed through the lens model at the patch's corners). Falls back to the stored template
    when the feature has no patch or the warp degenerates."""
    if f.patch is None or f.normal is None:
        return f.template
    h = HALF_T
    c0 = np.round(f.uv0)
    src = c0 + np.array([[-h, -h], [h, -h], [h, h], [-h, h]], float)
    if f.rays0 is None:
        # The first view's world rays through the patch corners never change: unproject once.
        f.rays0 = unproject(cam, src) @ f.R0.T
    model, params = lens_kernel_args(cam)
    uvc = _plane_corners_in_view(f.rays0, f.normal, f.r0, y, x_v[:3], quat_to_rotation(x_v[3:7]), model, params)
    if not np.all(np.isfinite(uvc)):
        return f.template
    uv, centre = uvc[:4], uvc[4]
    side = np.linalg.norm(uv[1] - uv[0]) / (2 * h)
    if not 0.5 < side < 2.0:                              # the template is no longer valid
        return f.template
    src_p = (src - (c0 - PATCH_HALF)).astype(np.float32)
    dst_t = (uv - (centre - h)).astype(np.float32)
    M = cv2.getPerspectiveTransform(src_p, dst_t)
    return cv2.warpPerspective(f.patch, M, (2 * h + 1, 2 * h + 1), flags=cv2.INTER_LINEAR)


@compiled_kernel(project_point_kernel)
def _plane_corners_in_view(rays0, normal, r0, y, r, R, model, params):
    """Pixels (5, 2) in the current view of the first view's patch corners on the plane through
    ``y`` with ``normal`` (the corners' world rays ``rays0`` (4, 3) from ``r0``), and of ``y``
    itself (row 4); NaN rows make the whole warp invalid (a ray parallel to the plane, a corner
    behind either camera)."""
    out = np.full((5, 2), np.nan)
    c = normal[0] * (y[0] - r0[0]) + normal[1] * (y[1] - r0[1]) + normal[2] * (y[2] - r0[2])
    for i in range(5):
        if i < 4:
            den = normal[0] * rays0[i, 0] + normal[1] * rays0[i, 1] + normal[2] * rays0[i, 2]
            if abs(den) < 1e-6:
                return np.full((5, 2), np.nan)
            lam = c / den
            if not lam > 0:
                return np.full((5, 2), np.nan)
            X0, X1, X2 = r0[0] + lam * rays0[i, 0], r0[1] + lam * rays0[i, 1], r0[2] + lam * rays0[i, 2]
        else:
            X0, X1, X2 = y[0], y[1], y[2]
        d0, d1, d2 = X0 - r[0], X1 - r[1], X2 - r[2]
        # Optical-frame point R^T (X - r).
        px = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        py = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        pz = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        res = project_point_kernel(model, params, px, py, pz)
        out[i, 0], out[i, 1] = res[0], res[1]
    return out


def local_plane_normal(Y: np.ndarray, k: int, radius: float, tol: float, min_points: int = 4) -> np.ndarray | None:
    """Unit normal (3,) of the plane fitted (least squares) to point ``k`` of ``Y`` (n, 3), m,
    and the points within ``radius`` m of it, if there are at least ``min_points`` of them and
    they are coplanar: RMS distance from the plane at most ``tol`` m, and spread along two
    directions (the second singular value at least 3 times the smallest). Otherwise None."""
    near = np.flatnonzero(np.linalg.norm(Y - Y[k], axis=1) < radius)
    if len(near) < min_points:
        return None
    _, sv, Vt = np.linalg.svd(Y[near] - Y[near].mean(axis=0), full_matrices=False)
    if sv[-1] / math.sqrt(len(near)) > tol or sv[1] < 3 * sv[-1]:
        return None
    return Vt[-1]


@dataclass
class FrameStats:
    frame: int
    t: float
    predicted: int = 0
    searched: int = 0
    matched: int = 0
    added: int = 0
    deleted: int = 0
    outliers: int = 0
    initialising: int = 0
    seconds: float = 0.0
    lost: bool = False
    relocalised: bool = False
    skipped: str = ""


class SlamStartError(ValueError):
    """The target cannot start SLAM (not in view, degenerate); the message says why."""


def _pinhole_normalised(cam: CameraIntrinsics, uv: np.ndarray) -> np.ndarray:
    return undistort(cam, np.asarray(uv, float).reshape(-1, 2))


class MonoSLAM:
    """Single-camera EKF SLAM over a sequence of images."""

    def __init__(self, camera: CameraIntrinsics, cfg: SlamConfig = DEFAULT_CONFIG, settings: MapSettings = MapSettings()):
        self.cam = camera
        self.cfg = cfg
        # Within a frame the filter keeps P finite and symmetric after every step; the full
        # positive-semi-definiteness check (a Cholesky of all of P) runs once per frame, where
        # it costs one factorisation instead of one per measured feature.
        self._step_cfg = replace(cfg, check_psd=False)
        self._lost_cfg = replace(self._step_cfg, sigma_a=cfg.sigma_a * settings.lost_noise_gain,
                                 sigma_alpha=cfg.sigma_alpha * settings.lost_noise_gain)
        self.s = settings
        self.state: State | None = None
        self.features: list[MapFeature] = []
        self.rays: list[tuple[int, depth_init.DepthParticles]] = []
        self.next_id = 0
        self.frame = -1
        self.t_prev = None
        self.low_matches = 0
        self._normals_n = -1
        self.stats: list[FrameStats] = []
        self._imu: np.ndarray | None = None
        # IMU biases (camera frame), estimated from what vision corrects in each frame.
        self.bias_gyro = np.zeros(3)
        self.bias_accel = np.zeros(3)
        self._prior = None

    # -------------------------------------------------------------- start-up
    def start(self, image: np.ndarray, t: float, target: Target) -> None:
        """Fix the world frame from the known target in the first image."""
        g = grey(image)
        xy = _pinhole_normalised(self.cam, target.uv)
        if not np.all(np.isfinite(xy)):
            raise SlamStartError("target.toml: a target point's pixel has no ray through the lens model")
        ok, rvec, tvec = cv2.solvePnP(target.xyz.astype(np.float64), xy.astype(np.float64), np.eye(3), None,
                                      flags=cv2.SOLVEPNP_IPPE if len(target.xyz) == 4 else cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise SlamStartError("target.toml: PnP found no camera pose for the target points; check xyz and uv")
        R_cw, _ = cv2.Rodrigues(rvec)
        R_wc = R_cw.T
        r = -R_wc @ tvec.ravel()
        x_v, P = self._camera_prior(R_wc, r, 1e-3, 1e-3)
        self.state = State.from_camera(x_v, P)
        # Reprojection check: the target must be in front and where the file says.
        uv, _, _, valid = h_and_jacobians_many(x_v, target.xyz, self.cam)
        err = np.linalg.norm(uv - target.uv, axis=1)
        if not valid.all() or err.max() > 5.0:
            raise SlamStartError(f"target.toml: the target points do not fit one camera pose (reprojection error "
                                 f"{np.nanmax(err):.1f} px); check that uv are their pixels in the first frame")
        # The target is planar: its normal (towards the camera) lets its corners' templates be
        # predicted from any viewpoint.
        c = target.xyz.mean(axis=0)
        _, _, Vt = np.linalg.svd(target.xyz - c)
        normal = Vt[2] if Vt[2] @ (r - c) > 0 else -Vt[2]
        for X, p in zip(target.xyz, target.uv):
            tpl = extract_template(g, p)
            if tpl is None:
                raise SlamStartError(f"target point at pixel {p.round(1).tolist()} is too close to the image border "
                                     "to take its template; the target must be in view at the start")
            self.state.add_feature(X, np.eye(3) * self.s.target_sigma_m**2, np.zeros((3, self.state.n)), self.cfg)
            self.features.append(MapFeature(self.next_id, tpl, 0, r.copy(), known=True, patch=_patch(g, p),
                                            uv0=np.asarray(p, float), R0=R_wc.copy(), normal=normal))
            self.next_id += 1
        self.frame = 0
        self.t_prev = t
        self.stats.append(FrameStats(0, t, matched=len(target.xyz)))

    # -------------------------------------------------------------- per frame
    def add_imu(self, rows) -> None:
        """Queue IMU rows (k, 7) ``[t, wx, wy, wz, ax, ay, az]`` (camera frame; imu.txt); from
        then on the prediction between frames integrates them (inertial.py) instead of assuming
        constant velocity. Rows must arrive in time order."""
        rows = np.asarray(rows, float).reshape(-1, 7)
        rows = rows[np.isfinite(rows).all(axis=1)]        # a corrupt sample is dropped
        if len(rows) and self.s.use_imu:
            self._imu = rows if self._imu is None else np.vstack([self._imu, rows])

    def _predict(self, t_prev: float, t: float, lost: bool) -> None:
        imu = self._imu
        self._prior = None
        if imu is not None and imu[0, 0] <= t_prev and imu[-1, 0] >= t - 0.05:
            unbiased = imu - np.r_[0.0, self.bias_gyro, self.bias_accel]
            predict_imu(self.state, unbiased, t_prev, t, self._step_cfg,
                        noise_gain=self.s.lost_noise_gain if lost else 1.0)
            self._prior = (self.state.q.copy(), self.state.v.copy(), t - t_prev)
            # Keep the sample that holds over the next interval, and those after it.
            k = max(int(np.searchsorted(imu[:, 0], t, side="right")) - 1, 0)
            self._imu = imu[k:]
        else:
            predict(self.state, t - t_prev, self._lost_cfg if lost else self._step_cfg)

    def process(self, image: np.ndarray, t: float, imu=None) -> FrameStats:
        """One frame at time t (s); ``imu`` : optional IMU rows since the last frame (add_imu)."""
        t0 = time.perf_counter()
        if imu is not None:
            self.add_imu(imu)
        self.frame += 1
        st = FrameStats(self.frame, t)
        g = grey(image)
        t_prev = self.t_prev
        self.t_prev = t
        lost = self.low_matches >= self.s.lost_after
        # Lost: the motion model's impulses grow (wider search ellipses), the map is frozen,
        # and the pose is sought again from whole-image matches (relocalise.py).
        self._predict(t_prev, t, lost)
        if lost:
            # Failed searches while lost say nothing about the features: their records are kept.
            counts = [(f.attempts, f.successes) for f in self.features]
            saved_camera = (self.state.x.copy(), self.state.P.copy())
            # A whole-image search costs tens of ms: one frame in reloc_every tries it.
            if (self.low_matches - self.s.lost_after) % self.s.reloc_every == 0:
                st.relocalised = self._relocalise(g)
        if self.s.warp == "neighbours" and (self.frame % self.s.normals_every == 0
                                            or self.state.n_features != self._normals_n):
            # Neighbours' planes change slowly: refit when the map changes, else every few frames.
            self._normals_from_map()
            self._normals_n = self.state.n_features
        self._measure(g, st)
        if lost and st.relocalised and st.matched < max(self.s.reloc_min_confirmed, st.searched / 2):
            # The active search at the new pose did not confirm it: stay lost, restore.
            self.state.x, self.state.P = saved_camera
            st.relocalised = False
            st.matched = 0                            # those matches were undone with the pose
        if lost and not st.relocalised:
            for f, (a, b) in zip(self.features, counts):
                f.attempts, f.successes = a, b
        if self.s.bias_time_s > 0 and not lost and self._prior is not None \
                and st.matched >= self.s.bias_min_matches:
            self._update_biases()
        if not lost or st.relocalised:
            self._refine_rays(g, st)
            self._delete(st)
            if st.matched < self.s.add_below and len(self.rays) < self.s.max_initialising:
                self._start_rays(g, st)
        self.state.P = check_covariance(self.state.P, f"frame {self.frame}", self.cfg)
        self.low_matches = self.low_matches + 1 if st.matched < 3 else 0
        st.lost = self.low_matches >= self.s.lost_after
        st.initialising = len(self.rays)
        st.seconds = time.perf_counter() - t0
        self.stats.append(st)
        return st

    def skip(self, t: float, why: str) -> FrameStats:
        """A frame that could not be read: predict through it, count it."""
        self.frame += 1
        self._predict(self.t_prev, t, self.low_matches >= self.s.lost_after)
        self.t_prev = t
        st = FrameStats(self.frame, t, skipped=why, lost=self.low_matches >= self.s.lost_after)
        self.stats.append(st)
        return st

    def _visible(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ks = np.arange(self.state.n_features)
        if len(ks) == 0:
            return ks, np.empty((0, 2)), np.empty((0, 2, 2))
        uv, S, valid = innovation_covariances(self.state, ks, self.cam, self.cfg.R_pix)
        ok = valid & in_image(self.cam, np.nan_to_num(uv, nan=-1e9), margin=self.s.margin_px)
        # The template is valid while the view is close to its first one: viewing angle and
        # range change against the first view's camera centre r0.
        Y = self.state.features
        a = Y - self.state.r
        b = Y - np.array([f.r0 for f in self.features])
        na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(na * nb, 1e-12)
        ratio = na / np.maximum(nb, 1e-9)
        known = np.array([f.known and self._warped(f) for f in self.features])
        angle = np.where(known, self.s.max_view_angle_known_deg, self.s.max_view_angle_deg)
        rmax = np.where(known, self.s.max_range_ratio_known, self.s.max_range_ratio)
        ok &= (cos >= np.cos(np.radians(angle))) & (ratio >= 1 / rmax) & (ratio <= rmax)
        return ks[ok], uv[ok], S[ok]

    def _update_biases(self) -> None:
        """Fold this frame's vision correction into the IMU bias estimates.

        Over a frame of d seconds a gyro bias b_g turns the predicted orientation by b_g d and an
        accelerometer bias b_a moves the predicted velocity by R b_a d; the measurements then
        correct them. Averaging those corrections with time constant ``bias_time_s`` estimates
        the biases, which are taken out of the samples before the next prediction. (A slow
        complementary estimate rather than bias states in the filter: the layout stays the
        MonoSLAM camera block.)"""
        q_prior, v_prior, d = self._prior
        if d <= 0:
            return
        k = min(d / self.s.bias_time_s, 1.0)
        # The rotation the update applied, in the camera frame: q_post = q_prior * dq.
        dq = quat_multiply(quat_conjugate(q_prior), self.state.q)
        dtheta = quat_to_rotvec(dq)
        self.bias_gyro -= k * dtheta / d
        dv_cam = quat_to_rotation(self.state.q).T @ (self.state.v - v_prior)
        self.bias_accel -= k * dv_cam / d

    def _warped(self, f: MapFeature) -> bool:
        """Whether the feature's template is predicted through its plane (MapSettings.warp)."""
        return self.s.warp == "all" or (self.s.warp == "known" and f.known) or \
            (self.s.warp == "neighbours" and (f.known or f.normal_from_map))

    def _measure(self, g: np.ndarray, st: FrameStats) -> None:
        ks, uv, S = self._visible()
        st.predicted = len(ks)
        order = ks[np.argsort(-np.linalg.det(S), kind="stable")] if len(ks) else ks
        # The frame's updates accumulate in su and reach the state at commit; until then the
        # state is the prior (kept for the outlier check).
        su = SequentialUpdate(self.state, self.cam, self.cfg.R_pix, self._step_cfg)
        used = []
        for k in map(int, order):
            # This feature's ellipse at the current estimate: the updates before it have shrunk it.
            uv_k, S_k, valid = su.innovation(k)
            if not valid:
                continue
            f = self.features[k]
            st.searched += 1
            f.attempts += 1
            warp = self._warped(f)
            tpl = warped_template(f, su.x_v, su.feature(k), self.cam) if warp else f.template
            m = search(g, tpl, uv_k, S_k, max_score=self.s.match_score)
            if not m.found and tpl is not f.template and self.s.warp_fallback:
                # The plane guess can be wrong (a natural feature's true surface): try as first seen.
                m = search(g, f.template, uv_k, S_k, max_score=self.s.match_score)
            if not m.found:
                continue
            try:
                su.update(k, m.uv)
            except (FeatureNotMeasurable, SlamNumericalError):
                continue
            used.append((k, m.uv))
        self._reject_outliers(su, used, st)

    def _camera_prior(self, R_world_cam: np.ndarray, r: np.ndarray, sigma_r: float, sigma_q: float
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Camera block (13,) at a pose known from PnP (rotation, optical centre, world), at rest,
        and its diagonal covariance: ``sigma_r`` m per position axis, ``sigma_q`` per quaternion
        component, the settings' initial velocity uncertainties."""
        x, y, z, w = Rotation.from_matrix(R_world_cam).as_quat()
        x_v = np.concatenate([r, [w, x, y, z], np.zeros(6)])
        P = np.diag(np.r_[np.full(3, sigma_r**2), np.full(4, sigma_q**2), np.full(3, self.s.init_sigma_v**2),
                          np.full(3, self.s.init_sigma_w**2)])
        return x_v, P

    def _relocalise(self, g: np.ndarray) -> bool:
        """Try to re-acquire the camera pose from the target and the most reliable mapped
        features (relocalise.py); on success restart the camera block there."""
        if self.state.n_features < self.s.reloc_min_inliers:
            return False
        rank = sorted(range(len(self.features)), key=lambda k: (not self.features[k].known,
                                                               -self.features[k].successes))
        ks = np.array(rank[:self.s.reloc_candidates])
        found = relocalise(g, [self.features[k].template for k in ks], self.state.features[ks], self.cam,
                           self.s.match_score, min_inliers=self.s.reloc_min_inliers)
        if found is None:
            return False
        x_v, P_vv = self._camera_prior(found.R_world_cam, found.r, self.s.reloc_sigma_m, self.s.reloc_sigma_q)
        self.state.x[:CAMERA_DIM] = x_v
        P = self.state.P.copy()
        P[:CAMERA_DIM, :] = 0.0
        P[:, :CAMERA_DIM] = 0.0
        P[:CAMERA_DIM, :CAMERA_DIM] = P_vv
        self.state.P = P
        return True

    def _reject_outliers(self, su: SequentialUpdate, used: list, st: FrameStats) -> None:
        """Matches the updated camera cannot explain (a posteriori residual above
        ``outlier_px``) are outliers: an occluding contour whose background slid, a repeated
        pattern. If there are any, the frame's updates are redone from the prior without them
        (the matches are kept, not searched again) and they count as failed attempts. Then the
        frame's update is committed to the state."""
        bad = np.zeros(len(used), bool)
        if used:
            ks = np.array([k for k, _ in used])
            z = np.array([uv for _, uv in used])
            uv, _, _, valid = h_and_jacobians_many(su.x_v, su.features[ks], self.cam)
            bad = ~valid | (np.linalg.norm(z - uv, axis=1) > self.s.outlier_px)
            if bad.any() and (~bad).sum() >= 3:
                su = SequentialUpdate(self.state, self.cam, self.cfg.R_pix, self._step_cfg)
                for i, (k, zk) in enumerate(used):
                    if bad[i]:
                        continue
                    try:
                        su.update(k, zk)
                    except (FeatureNotMeasurable, SlamNumericalError):
                        bad[i] = True
            else:
                bad[:] = False
        su.commit()
        for (k, _), b in zip(used, bad):
            if not b:
                self.features[k].successes += 1
                st.matched += 1
        st.outliers = int(bad.sum())

    def _normals_from_map(self) -> None:
        """Give each natural feature the normal of the plane through it and its map neighbours
        (:func:`local_plane_normal`), facing its first view."""
        Y = self.state.features
        for k, f in enumerate(self.features):
            if not f.known:
                n = local_plane_normal(Y, k, self.s.plane_radius_m, self.s.plane_tol_m)
                if n is not None:
                    f.normal, f.normal_from_map = (n if n @ (f.r0 - Y[k]) > 0 else -n), True

    def _refine_rays(self, g: np.ndarray, st: FrameStats) -> None:
        x_v = self.state.x_v
        P_vv = self.state.P[:CAMERA_DIM, :CAMERA_DIM]
        R = self.cfg.R_pix
        keep = []
        for fid, p, R0, patch in self.rays:
            def project(points):
                uv, H_x, _, valid = h_and_jacobians_many(x_v, points, self.cam)
                S = np.full((len(points), 2, 2), np.nan)
                S[valid] = H_x[valid] @ P_vv @ np.swapaxes(H_x[valid], 1, 2) + R
                return uv, S

            def match(uv, S):
                ok = np.isfinite(uv).all(axis=1) & np.isfinite(S).all(axis=(1, 2))
                if not ok.any():
                    return None
                # One search over the box the particles' ellipses cover (the epipolar band).
                lo = (uv[ok] - 3 * np.sqrt(S[ok][:, [0, 1], [0, 1]])).min(axis=0)
                hi = (uv[ok] + 3 * np.sqrt(S[ok][:, [0, 1], [0, 1]])).max(axis=0)
                c = (lo + hi) / 2
                half = (hi - lo) / 2
                m = search(g, p.template, c, np.diag((half / 3) ** 2) + 1e-9, n_sigma=3.0,
                           max_score=self.s.match_score, max_area=120_000)
                return (m.uv, float(np.prod(2 * half + 1))) if m.found else None

            depth_init.step(p, project, match, self.s.prune, self.s.outlier)
            if p.is_gaussian(self.s.gauss_ratio) and p.frames >= self.s.min_init_frames:
                self._promote(fid, p, R0, patch, st)
            elif p.frames < self.s.max_init_frames and p.failures < 10 and len(p.depths) > 0:
                keep.append((fid, p, R0, patch))
        self.rays = keep

    def _promote(self, fid: int, p: depth_init.DepthParticles, R0: np.ndarray, patch, st: FrameStats) -> None:
        y = p.origin + p.mean * p.direction
        x_v = self.state.x_v
        uv, _, _, valid = h_and_jacobians_many(x_v, y[None], self.cam)
        if not valid[0]:
            return
        depth = float(np.linalg.norm(y - self.state.r))
        try:
            add_point_feature(self.state, uv[0], depth, (self.s.promote_std_gain * p.std)**2, self.cfg.R_pix, self.cam,
                              self._step_cfg)
        except SlamNumericalError:
            return
        # Assume the patch faces the camera that first saw it (MonoSLAM's fronto-parallel guess).
        normal = (p.origin - y) / np.linalg.norm(p.origin - y)
        self.features.append(MapFeature(fid, p.template, self.frame, p.origin.copy(), patch=patch, uv0=p.uv0,
                                        R0=R0, normal=normal))
        st.added += 1

    def _delete(self, st: FrameStats) -> None:
        for k in range(len(self.features) - 1, -1, -1):
            f = self.features[k]
            if f.attempts >= self.s.delete_min_attempts and f.successes < self.s.delete_ratio * f.attempts:
                self.state.remove_feature(k)
                del self.features[k]
                st.deleted += 1

    def _start_rays(self, g: np.ndarray, st: FrameStats) -> None:
        occupied = [p.uv0 for _, p, _, _ in self.rays]
        if self.state.n_features:
            uv, _, _, valid = h_and_jacobians_many(self.state.x_v, self.state.features, self.cam)
            occupied += list(uv[valid])
        n = self.s.max_initialising - len(self.rays)
        candidates = new_features(g, np.array(occupied).reshape(-1, 2), 4 * n if self.s.lookahead_s else n)
        if self.s.lookahead_s and candidates:
            # MonoSLAM places new features where the camera's motion will keep them in view
            # longest: keep the corners still in the image after lookahead_s of constant
            # velocity (seen at lookahead_depth_m), strongest first.
            stay = self._stay_in_view(np.array([uv for uv, _ in candidates]))
            candidates = [c for c, ok in zip(candidates, stay) if ok] or candidates
        for uv, tpl in candidates[:n]:
            origin, d = ray_from_pixel(self.state.x_v, uv, self.cam)[:2]
            p = depth_init.DepthParticles.create(origin, d, tpl, uv, self.s.particles, self.s.depth_near_m,
                                                 self.s.depth_far_m)
            self.rays.append((self.next_id, p, quat_to_rotation(self.state.q), _patch(g, uv)))
            self.next_id += 1

    def _stay_in_view(self, uv: np.ndarray) -> np.ndarray:
        """(k,) bool: whether each pixel's point (at ``lookahead_depth_m``) is still inside the
        image, ``margin_px`` in, after ``lookahead_s`` of the motion model's constant velocity."""
        x_v = self.state.x_v
        rays = unproject(self.cam, uv)                                     # (k, 3), z = 1
        X = x_v[:3] + (self.s.lookahead_depth_m * rays / np.linalg.norm(rays, axis=1, keepdims=True)) \
            @ quat_to_rotation(x_v[3:7]).T
        x_next, _ = f_and_dfdx(x_v, self.s.lookahead_s)                   # the camera then
        uv_next = project_points(self.cam, (X - x_next[:3]) @ quat_to_rotation(x_next[3:7]))
        return in_image(self.cam, np.nan_to_num(uv_next, nan=-1e9), margin=self.s.margin_px)

    # -------------------------------------------------------------- outputs
    def T_world_cam(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = quat_to_rotation(self.state.q)
        T[:3, 3] = self.state.r
        return T
