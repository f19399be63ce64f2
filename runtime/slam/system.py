"""MonoSLAM for the wearable (paper, section 4), as its successors run it: the per-frame loop.

Each frame:

1. **predict** the camera: through the IMU samples when there are any fit to use (inertial.py,
   with bias states), else with the constant-velocity model (motion.py);
2. **select** the map features predicted visible (well inside the image, viewed close enough
   to their first view for the template to hold), at most ``measure_max`` of them, spread over
   the image;
3. **search** each inside the 3-sigma ellipse of its innovation covariance (search.py), with
   its template warped by its plane where one is known (templates.py); a printed quadrilateral
   target found whole is then placed by its fitted sides, as at the start (``known_edges``);
4. **1-point RANSAC** (ransac.py; each match votes for a hypothesis with its feature's record of
   inlier matches): the low-innovation inliers update the filter, then the high-innovation ones
   are rescued by a chi-square test and update it again;
5. **map management**: inverse-depth features whose depth has become linear turn into points;
   features whose ratio of inlier matches to searches falls below 1:2 are deleted; when fewer
   than ``visible_min`` features are predicted visible, new ones start on Shi-Tomasi corners in
   empty parts of the image, where the motion will keep them in view, as inverse-depth features
   (in the state from their first frame) or, with ``features = "particles"``, as the paper's
   factored-sampling rays.

Start-up: the known target's clicks are refined on the first image, its pose (or both planar
poses) found with an honest covariance (startup.py); a second pose hypothesis is tracked beside
the first until the map separates them. A lost track is re-localised against the map in the
map's own frame (relocalise.py); a saved map (map_io.py) starts a session lost, re-localising.
A track that drifted without being lost is put back at the target: near its prediction when its
corners are predicted in view and missed, and, when it has not been matched for a while, over
the whole image, a pose found there being confirmed by the map made before it was lost.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2

from kinematics.camera import CameraIntrinsics, in_image, lens_kernel_args, unproject, unproject_jacobian
from kinematics.camera import project as project_points
from kinematics.transforms import rotation_angle

from ..sequence import Target
from .config import DEFAULT_CONFIG, MapSettings, SlamConfig
from .corners import grey, min_template_std, new_features, noise_sigma
from .features import INVERSE_DEPTH, POINT, inverse_depth
from .features import particles as depth_init
from .filter import (FeatureNotMeasurable, FrameUpdate, add_inverse_depth_features, add_point_feature, point_conversions,
                     innovation_covariances, innovation_nis)
from .inertial import ImuStream, StillBiases, predict_imu, still_biases
from .kernels import compiled_kernel
from .measurement import Prediction, predict, predict_points, predict_uv, ray_from_pixel
from .motion import (adapted_sigma_a, adapted_sigma_alpha, f_and_dfdx, f_and_dfdx_dfdn, noise_covariance,
                     predict as predict_cv, turning)
from .quaternion import quat_from_rotation, quat_to_rotation
from .ransac import one_point_ransac
from .relocalise import relocalise
from .matching import fit_normal_kernel, match_features
from .search import extract_template, search
from .startup import (PoseHypothesis, RefinedTarget, SlamStartError, corners_by_edges, find_quadrilateral,
                      locate_target, pose_hypotheses, print_contrast, refine_by_edges, start_hypotheses)
from .state import (BA_SLICE, BG_SLICE, CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_TIMED, POSE_DIM, Q_SLICE,
                    TD_INDEX, V_SLICE, W_SLICE, SlamNumericalError, State, check_covariance)
from .templates import MapFeature, first_view_patch, local_plane_normal, patch_half

__all__ = ["MonoSLAM", "FrameStats", "MapSettings", "MapView", "SearchView", "SlamStartError", "MapFeature"]

#: A feature whose match variance along its weakest direction is more than this many times that
#: across it (a standard deviation ratio above 3) is a relocalisation candidate after the rest.
MAX_RELOC_ELONGATION = 10.0

#: Grid over the image for spreading the measured features (columns, rows).
_GRID = (4, 3)

#: Images narrower than this convert inverse-depth features at ``linearity_threshold_narrow``:
#: keeping them in inverse depth longer halves the walks' drift from 480 px wide, but at 320 it
#: gains nothing measurable and its larger state costs 13% of the frame rate (benchmarks/NOTES.md).
NARROW_WIDTH_PX = 480


def cap_victims(excess: int, last_seen: np.ndarray, in_view: np.ndarray, is_point: np.ndarray) -> np.ndarray:
    """The ``excess`` candidates (indices into the (m,) arrays) that leave a map over its size
    cap: those predicted in view this frame last (the frame's tracking rests on them); of the
    rest, inverse-depth features before points, and within each the one seen longest ago (frame
    index ``last_seen``) first. A point out of view is the map's memory of a place, which
    re-observed pulls a drifted pose back; an inverse-depth feature out of view has an
    unsettled depth, and seen again it constrains the pose little."""
    order = np.lexsort((np.asarray(last_seen), np.asarray(is_point, bool), np.asarray(in_view, bool)))
    return order[:max(int(excess), 0)]


@dataclass
class SearchView:
    """The last frame's active search, for displays and diagnostics: the features searched, by
    ``ids`` (m,) (stable across deletions; ``ks`` (m,) their map indices at the search), their
    predicted pixels ``uv`` (m, 2) and innovation covariances ``S`` (m, 2, 2) at the prior, the
    matches ``z`` (m, 2) (NaN: not found) and which were used (inliers)."""

    ids: np.ndarray
    uv: np.ndarray
    S: np.ndarray
    z: np.ndarray
    used: np.ndarray
    ks: np.ndarray | None = None


@dataclass(frozen=True)
class MapView:
    """A snapshot of the SLAM for displays (the operator station) and scripts.

    t : s. T_world_cam : (4, 4) (NaN before the camera is localised). ids : (N,) feature ids.
    xyz : (N, 3) their points, world, m (an inverse-depth feature's at its current depth).
    cov : (N, 3, 3) the points' covariances, m^2. kinds : (N,) "point" or "inverse-depth".
    known : (N,) target points. ``ray_origin`` (K, 3), ``ray_direction`` (K, 3) unit, ``ray_depth`` (K, 2) near and far, m: features still being initialised, as
    their rays (inverse-depth features' 95% depth interval, or particle rays), with ``ray_ids``
    (K,). search : the last frame's active search (:class:`SearchView`) or None.
    """

    t: float
    T_world_cam: np.ndarray
    ids: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray
    kinds: tuple
    known: np.ndarray
    ray_ids: np.ndarray
    ray_origin: np.ndarray
    ray_direction: np.ndarray
    ray_depth: np.ndarray
    search: SearchView | None

    @property
    def localised(self) -> bool:
        return bool(np.isfinite(self.T_world_cam).all())

    def point_of(self, feature_id: int) -> np.ndarray | None:
        """(3,) the world point of feature ``feature_id``, or None if the map has no such id."""
        k = np.flatnonzero(self.ids == int(feature_id))
        return self.xyz[k[0]].copy() if len(k) else None

    @classmethod
    def empty(cls, t: float = 0.0) -> "MapView":
        """The view before SLAM has started (or without SLAM)."""
        z3 = np.zeros((0, 3))
        return cls(t, np.full((4, 4), np.nan), np.zeros(0, int), z3, np.zeros((0, 3, 3)), (), np.zeros(0, bool),
                   np.zeros(0, int), z3, z3, np.zeros((0, 2)), None)


@dataclass
class FrameStats:
    frame: int
    t: float
    predicted: int = 0            # features predicted visible
    searched: int = 0
    found: int = 0                # matches the search found
    matched: int = 0              # inliers used to update (low-innovation and rescued)
    rescued: int = 0
    outliers: int = 0             # found but rejected by RANSAC
    added: int = 0
    deleted: int = 0
    converted: int = 0
    initialising: int = 0         # inverse-depth features, or particle rays in flight
    map_size: int = 0
    hypotheses: int = 1
    seconds: float = 0.0
    imu: bool = False             # predicted through the IMU
    lost: bool = False
    relocalised: bool = False
    retried: bool = False         # searched again with a larger motion impulse (_Track._measure)
    onset: bool = False           # measured again with a turn's impulses (_Track.step)
    sigma_a: float = 0.0          # the linear impulse the prediction took, m/s^2 (SlamConfig.adapt_sigma_a)
    sigma_alpha: float = 0.0      # the angular impulse, rad/s^2 (SlamConfig.adapt_sigma_alpha)
    reacquired: bool = False      # the camera put back at the target's pose (_Track._watch_target, _close_loop)
    skipped: str = ""


@compiled_kernel()
def _first_view_kernel(Y, r, r0, k):
    """How far point ``Y[k]`` is seen from its first view, the camera now at r (3,) and then at
    ``r0[k]``: the cosine of the angle between the two viewing rays and the ratio of the ranges,
    now over then."""
    a0, a1, a2 = Y[k, 0] - r[0], Y[k, 1] - r[1], Y[k, 2] - r[2]
    b0, b1, b2 = Y[k, 0] - r0[k, 0], Y[k, 1] - r0[k, 1], Y[k, 2] - r0[k, 2]
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    nb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    cos = min(max((a0 * b0 + a1 * b1 + a2 * b2) / max(na * nb, 1e-12), -1.0), 1.0)
    return cos, na / max(nb, 1e-9)


@compiled_kernel(_first_view_kernel)
def _from_first_view(Y, r, r0):
    """:func:`_first_view_kernel` for every point Y (N, 3), first seen from r0 (N, 3): cosines
    (N,) and range ratios (N,)."""
    N = Y.shape[0]
    cos, ratio = np.empty(N), np.empty(N)
    for k in range(N):
        cos[k], ratio[k] = _first_view_kernel(Y, r, r0, k)
    return cos, ratio


@compiled_kernel(_first_view_kernel)
def _views_kernel(uv, valid, Y, r, r0s, known, width, height, margin, cos_lim, cos_lim_known, rmax, rmax_known,
                  angle_unit_deg, log_scale_unit, known_scale):
    """:meth:`_Track._views` for the features predicted at ``uv`` (N, 2) (``valid``) inside the
    image (``margin`` px from its edge, as kinematics.camera.in_image): whether each is both in
    the image and seen close enough to its first view (N,), and its noise scale (N,)."""
    N = uv.shape[0]
    ok = np.zeros(N, dtype=np.bool_)
    scale = np.ones(N)
    lo = -0.5 + margin
    for k in range(N):
        u, v = uv[k, 0], uv[k, 1]
        if not (valid[k] and u >= lo and u <= width - 0.5 - margin and v >= lo and v <= height - 0.5 - margin):
            continue
        cos, ratio = _first_view_kernel(Y, r, r0s, k)
        cl, rm = (cos_lim_known, rmax_known) if known[k] else (cos_lim, rmax)
        ok[k] = cos >= cl and ratio >= 1.0 / rm and ratio <= rm
        if known[k]:
            scale[k] = known_scale
        else:
            scale[k] = (1.0 + (math.degrees(math.acos(cos)) / angle_unit_deg) ** 2
                        + (math.log(max(ratio, 1e-9)) / log_scale_unit) ** 2)
    return ok, scale


@compiled_kernel()
def _rolled_shapes(R_world_cam, A, R0, ks):
    """(m, 2, 2) the shapes ``A[ks]`` (first-view image axes) turned by each first view's roll
    about the optic axis to this view: the angle of ``R_world_cam^T R0``'s upper 2 x 2 block."""
    m = ks.shape[0]
    out = np.empty((m, 2, 2))
    for i in range(m):
        k = ks[i]
        # The upper 2 x 2 block of R_world_cam^T R0[k]: (r00 + r11, r10 - r01) is the roll's angle.
        cos_sum, sin_sum = 0.0, 0.0
        for j in range(3):
            cos_sum += R_world_cam[j, 0] * R0[k, j, 0] + R_world_cam[j, 1] * R0[k, j, 1]
            sin_sum += R_world_cam[j, 1] * R0[k, j, 0] - R_world_cam[j, 0] * R0[k, j, 1]
        ang = np.arctan2(sin_sum, cos_sum)
        c, s = np.cos(ang), np.sin(ang)
        a00, a01, a11 = A[k, 0, 0], A[k, 0, 1], A[k, 1, 1]
        # rot A rot^T, rot = [[c, -s], [s, c]]
        out[i, 0, 0] = c * c * a00 - 2.0 * c * s * a01 + s * s * a11
        out[i, 1, 1] = s * s * a00 + 2.0 * c * s * a01 + c * c * a11
        out[i, 0, 1] = c * s * (a00 - a11) + (c * c - s * s) * a01
        out[i, 1, 0] = out[i, 0, 1]
    return out


class _Track:
    """One filter and its map: the state, the features' appearance and bookkeeping, rays being
    initialised (particles), and the evidence for its start-up hypothesis."""

    def __init__(self, slam: "MonoSLAM", state: State, features: list[MapFeature], localised: bool = True):
        self.slam = slam
        self.state = state
        self.features = features
        self.rays: list = []
        self.low_matches = 0 if localised else slam.settings.lost_after
        self.localised = localised
        self.score = 0.0
        self.last: SearchView | None = None
        self.in_view_ids: set[int] = set()       # features predicted in view at this frame's search
        self._first_views_key: list | None = None
        self._first_views_cache = (np.zeros((0, 3)), np.zeros(0, bool), np.zeros((0, 2, 2)), np.zeros((0, 3, 3)))
        self.target_seen = 0                     # the last frame the target's corners were matched
        self.target_missed = 0                   # frames since, with all four predicted in view
        # The first frame any natural feature was mapped in (None: none yet; 0: a map given), so
        # the whole-image search knows whether a map from before the target's loss ever existed.
        self.first_mapped = 0 if any(not f.known for f in features) else None
        # The impulses this track predicts with (SlamConfig.adapt_sigma_a, adapt_sigma_alpha)
        # and the history they are estimated from: (t, v (3,), trace of v's covariance, w (3,),
        # trace of w's covariance).
        self.motion_cfg = slam.cfg
        self.v_hist: list[tuple[float, np.ndarray, float, np.ndarray, float]] = []
        self.t_start: float | None = None

    def _impulses(self, t: float, x: np.ndarray, var_v: float, var_w: float) -> tuple[list, float, float]:
        """The velocity and rate history with the estimates ``x`` now (the traces of their
        covariances ``var_v``, ``var_w``), and the impulses a prediction takes from it: the
        linear one while the camera turns faster than ``adapt_turn_rate``
        (motion.adapted_sigma_a), the angular one through a manoeuvre
        (motion.adapted_sigma_alpha)."""
        cfg = self.slam.cfg
        span = cfg.adapt_window + cfg.adapt_lag
        t_keep = t - max(span, 1.05 * cfg.adapt_alpha_lag)
        hist = [h for h in self.v_hist if h[0] >= t_keep]
        hist.append((t, x[V_SLICE].copy(), var_v, x[W_SLICE].copy(), var_w))
        rate = float(np.linalg.norm(x[W_SLICE]))
        if not turning(cfg, rate):                  # both rules keep the priors: not built
            return hist, cfg.sigma_a, cfg.sigma_alpha
        th, v, tr_v, w, tr_w = (np.array([h[k] for h in hist]) for k in range(5))
        i = int(np.searchsorted(th, t - span))       # the linear rule's own span of the history
        sigma_a = adapted_sigma_a(cfg, th[i:], v[i:], tr_v[i:], rate)
        return hist, sigma_a, adapted_sigma_alpha(cfg, th, w, tr_w)

    def _adapting(self, t: float) -> bool:
        cfg = self.slam.cfg
        if not (cfg.adapt_sigma_a or cfg.adapt_sigma_alpha):
            return False
        if self.t_start is None:
            self.t_start = t
        return t - self.t_start >= cfg.adapt_after

    def _adapt_impulse(self, t: float) -> None:
        """Keep the estimates after this frame and set the impulses the next prediction takes."""
        if self._adapting(t):
            x, P = self.state.x, self.state.P
            self.v_hist, sigma_a, sigma_alpha = self._impulses(t, x, float(np.trace(P[V_SLICE, V_SLICE])),
                                                                float(np.trace(P[W_SLICE, W_SLICE])))
            self._set_impulses(sigma_a, sigma_alpha)

    def _set_impulses(self, sigma_a: float, sigma_alpha: float) -> None:
        if (sigma_a, sigma_alpha) != (self.motion_cfg.sigma_a, self.motion_cfg.sigma_alpha):
            self.motion_cfg = replace(self.slam.cfg, sigma_a=sigma_a, sigma_alpha=sigma_alpha)

    def _turn_began(self, t: float, fu: FrameUpdate, turn: list) -> bool:
        """Whether a frame's updates ``fu``, not yet written, start a turn: the impulses after
        them differ from the priors the frame was predicted with; if so they go in ``turn``."""
        cfg = self.slam.cfg
        impulses = self._impulses(t, fu.x, float(fu.variances(V_SLICE).sum()),
                                  float(fu.variances(W_SLICE).sum()))[1:]
        if impulses == (cfg.sigma_a, cfg.sigma_alpha):
            return False
        turn.extend(impulses)
        return True

    @property
    def lost(self) -> bool:
        return self.low_matches >= self.slam.settings.lost_after

    def copy_for(self, state: State, features: list[MapFeature]) -> "_Track":
        return _Track(self.slam, state, features)

    def span(self, t_prev: float, t: float) -> tuple[float, float]:
        """The prediction's interval on the IMU's clock for the frame at camera time ``t``: from
        where the camera block stands to ``t`` plus the clock offset's estimate."""
        if not self.state.has_time_offset:
            return t_prev, t
        t0 = t_prev + self.state.t_ref
        return t0, max(t + self.state.t_d, t0)

    # ------------------------------------------------------------------ one frame
    def propagate(self, t_prev: float, t: float, imu_rows, noise_gain: float) -> bool:
        """The camera block to the frame at camera time ``t``, through the IMU rows when they
        cover it (True), else by the constant-velocity model."""
        cfg = self.slam.cfg
        t0, t1 = self.span(t_prev, t)
        self.state.t_ref = t1 - t
        if imu_rows is not None:
            try:
                predict_imu(self.state, imu_rows, t0, t1, cfg, noise_gain=noise_gain,
                            covered_until=self.slam.imu.covered_until)
                return True
            except (SlamNumericalError, ValueError):
                pass
        predict_cv(self.state, t1 - t0, self.motion_cfg, noise_gain=noise_gain)
        return False

    def step(self, g: np.ndarray, t_prev: float, t: float, imu_rows, st: FrameStats, frame: int) -> None:
        s, cfg = self.slam.settings, self.slam.cfg
        lost = self.lost
        if lost:
            self.motion_cfg = cfg        # lost, the prior: nothing says how the camera moves now
        st.sigma_a, st.sigma_alpha = self.motion_cfg.sigma_a, self.motion_cfg.sigma_alpha
        # Before the prediction, the camera's mean and rows of P (all a prediction changes), kept
        # while a turn may begin in this frame (SlamConfig.adapt_onset).
        cd = self.state.cam_dim
        before = ((self.state.x.copy(), self.state.P[:cd].copy())
                  if cfg.adapt_onset and not lost and self._adapting(t_prev)
                  and (self.motion_cfg.sigma_a, self.motion_cfg.sigma_alpha) == (cfg.sigma_a, cfg.sigma_alpha)
                  else None)
        st.imu = self.propagate(t_prev, t, imu_rows, s.lost_noise_gain if lost else 1.0)
        counts = saved = None
        if lost:
            # Lost: the map is frozen; the pose is sought again by whole-image matches
            # (relocalise.py) and by the active search in the grown ellipses; either must be
            # confirmed by the active search's inliers, else the frame leaves no trace.
            counts = [(f.attempts, f.successes, f.drift) for f in self.features]
            saved = (self.state.x.copy(), self.state.P.copy())
            every = 1 if not self.localised else s.reloc_every
            if (self.low_matches - s.lost_after) % every == 0:
                st.relocalised = self._relocalise(g)
        if s.warp != "known" and frame % s.normals_every == 0:
            self._normals_from_map()        # neighbours' planes change slowly: every few frames
        away = frame - self.target_seen
        closed = (not lost and s.reacquire_after > 0 and s.loop_after > 0 and away >= s.loop_after
                  and (away - s.loop_after) % s.loop_every == 0 and self._close_loop(g, st, frame))
        if not closed:
            turn: list = []
            check = before is not None and not st.imu
            if not self._measure(g, st, frame, retry_dt=None if lost or st.imu else t - t_prev,
                                 accept=(lambda fu: not self._turn_began(t, fu, turn)) if check else None):
                # A turn began in this frame, and the prior impulses took its unforeseen start
                # partly as translation: predicted and measured again with the turn's impulses.
                x, rows = before
                self.state.x = x
                self.state.P[:cd] = rows
                self.state.P[:, :cd] = rows.T
                self._set_impulses(*turn)
                st.onset, st.retried = True, False
                st.sigma_a, st.sigma_alpha = self.motion_cfg.sigma_a, self.motion_cfg.sigma_alpha
                self.propagate(t_prev, t, None, 1.0)
                self._measure(g, st, frame, retry_dt=t - t_prev)
        if lost:
            if st.matched < max(s.reloc_min_confirmed, s.reloc_confirm_fraction * st.searched):
                self.state.x, self.state.P = saved
                for f, (a, b, d) in zip(self.features, counts):
                    f.attempts, f.successes, f.drift = a, b, d
                st.relocalised = False
                st.matched = st.rescued = 0
                self.low_matches += 1
                return
            self.localised = True
        elif s.reacquire_after > 0 and not closed:
            self._watch_target(g, st, frame)
        if s.normals_per_frame > 0 and s.warp != "known" and not lost and not closed:
            self._normals_from_views(g)         # the matches _measure made in this frame
        if s.features == "particles":
            self._refine_rays(g, st, frame)
            self._delete(st, frame)
        else:
            self._delete(st, frame, self._conversions(st))
        # MonoSLAM adds features when too few are actually observed (matched), not predicted.
        if st.matched < s.visible_min:
            self._add(g, st, frame, st.matched)
        if not lost:
            self._adapt_impulse(t)
        if frame % cfg.psd_check_every == 0:
            self.state.P = check_covariance(self.state.P, f"frame {frame}", cfg.psd_rel_tol, True, self.state.describe)
        self.low_matches = self.low_matches + 1 if st.matched < 3 else 0

    # ------------------------------------------------------------------ measurement
    def _views(self, pred: Prediction, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each feature predicted by ``pred`` (every feature of the map, in order; its point in
        ``Y`` (N, 3)): whether it is in the image and seen close enough to its first view for its
        template to hold (viewing angle and range against the first view's centre), and its
        measurement noise as a multiple of the pixel noise: the template's prediction degrades as
        the view moves from the first (a wrong plane guess warps it wrongly), ``1 + (angle /
        view_noise_angle)^2 + (log range ratio / log view_noise_scale)^2``; the target's points,
        printed corners whose plane is known, are located more closely (``known_sigma_px``)."""
        s, cam = self.slam.settings, self.slam.cam
        r0s, known = self._first_views()[:2]
        return _views_kernel(pred.uv, pred.valid, Y, self.state.r, r0s, known, float(cam.width),
                             float(cam.height), float(s.margin_px), math.cos(math.radians(s.max_view_angle_deg)),
                             math.cos(math.radians(s.max_view_angle_known_deg)), float(s.max_range_ratio),
                             float(s.max_range_ratio_known), float(s.view_noise_angle_deg),
                             math.log(s.view_noise_scale), (s.known_sigma_px / self.slam.cfg.sigma_pixel) ** 2)

    def _first_views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every feature's first-view centre (N, 3), whether it is a target point (N,), its match
        noise shape (N, 2, 2) and its first view's rotation (N, 3, 3) (the identity for the
        target's points), kept while the map holds the same features (none changes during a
        feature's life)."""
        key = [f.id for f in self.features]
        if self._first_views_key != key:
            # The features kept since the last call keep their rows (by id); only new ones are read.
            was = {fid: i for i, fid in enumerate(self._first_views_key or [])}
            rows = np.array([was.get(fid, -1) for fid in key], np.intp)
            kept = np.flatnonzero(rows >= 0)
            n = len(self.features)
            r0s, known = np.empty((n, 3)), np.empty(n, bool)
            shapes, R0s = np.empty((n, 2, 2)), np.empty((n, 3, 3))
            if len(kept):
                for new, old in zip((r0s, known, shapes, R0s), self._first_views_cache):
                    new[kept] = old[rows[kept]]
            for i in np.flatnonzero(rows < 0).tolist():
                f = self.features[i]
                r0s[i], known[i], shapes[i] = f.r0, f.known, f.noise_shape
                R0s[i] = f.R0 if f.R0 is not None and not f.known else np.eye(3)
            self._first_views_cache = (r0s, known, shapes, R0s)
            self._first_views_key = key
        return self._first_views_cache

    def world_points(self) -> np.ndarray:
        """(N, 3) every feature's point (an inverse-depth feature's at its current depth, at
        most 20 m)."""
        return self._points_and_linearity()[0]

    def point_covariances(self, ks: np.ndarray) -> np.ndarray:
        """(len(ks), 3, 3) features' point covariances, world, m^2 (an inverse-depth feature's
        through its conversion, at an inverse depth of at least 0.05 /m, as world_points)."""
        st = self.state
        cov = np.empty((len(ks), 3, 3))
        for i, k in enumerate(ks):
            sl = st.feature_slice(k)
            P = st.P[sl, sl]
            if st.kinds[k] == INVERSE_DEPTH:
                y = st.feature(k).copy()
                y[5] = max(y[5], 0.05)
                _, J = inverse_depth.to_point(y, st.anchors[k])
                cov[i] = J @ P @ J.T
            else:
                cov[i] = P
        return cov

    def known_in_id_order(self) -> np.ndarray:
        """The target's points' map indices, in the order of their ids (the target's corners')."""
        return np.array(sorted((k for k, f in enumerate(self.features) if f.known), key=lambda k: self.features[k].id),
                        np.intp)

    def _points_and_linearity(self) -> tuple[np.ndarray, np.ndarray]:
        st = self.state
        return inverse_depth.points_and_linearity_kernel(st.x, st.P, st.kinds, st.starts, st.anchors, st.r, 0.05)

    def _select(self) -> tuple[Prediction, np.ndarray, np.ndarray, int, np.ndarray]:
        """The features to measure this frame, their innovation covariances and noise (multiples
        of the pixel noise: (m,), or (m, 2, 2) shaped by each template's gradients with
        ``aperture_noise``), how many are predicted visible, and their points (m, 3)."""
        s, cam = self.slam.settings, self.slam.cam
        st = self.state
        ks = np.arange(st.n_features)
        if not len(ks):
            empty = predict(st, ks, cam)
            return empty, np.zeros((0, 2, 2)), np.zeros(0), 0, np.zeros((0, 3))
        pred = predict(st, ks, cam)
        Y = self.world_points()
        ok, r_scale = self._views(pred, Y)
        sel = np.flatnonzero(ok)
        r_scale = r_scale[sel]
        if s.drift_gain > 0:
            sig2 = self.slam.cfg.sigma_pixel ** 2
            r_scale = r_scale * np.array([self.features[k].drift_variance_scale(s.drift_gain, sig2) for k in sel])
        if s.aperture_noise:
            r_scale = r_scale[:, None, None] * self._noise_shapes(sel)
        pred = pred.take(sel)
        self.in_view_ids = {self.features[k].id for k in pred.ks}
        S = innovation_covariances(st, pred, self.slam.cfg.sigma_pixel**2, r_scale)
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        area = 9 * math.pi * np.sqrt(np.maximum(det, 0))   # the 3-sigma ellipse, px^2
        searchable = np.isfinite(area) & (area <= s.max_search_area_px)
        visible = int(len(sel))
        idx = np.flatnonzero(searchable)
        if len(idx) > s.measure_max:
            # The most reliable first (MapFeature.reliability), the most uncertain among equals,
            # spread over the image.
            feats = [self.features[k] for k in pred.ks[idx]]
            reliability = np.array([f.reliability for f in feats])
            priority = reliability + 1e-6 * np.log(np.maximum(det[idx], 1e-12))
            idx = self._spread(pred.uv[idx], priority, [f.known for f in feats], s.measure_max, idx)
        pred = pred.take(idx)
        return pred, S[idx], r_scale[idx], visible, Y[pred.ks]

    def _noise_shapes(self, ks: np.ndarray) -> np.ndarray:
        """(m, 2, 2) features ``ks``' match noise shapes (MapFeature.noise_shape) turned from their
        first view's image axes into this view's by the camera's roll about its optic axis since."""
        _, _, A, R0 = self._first_views()
        return _rolled_shapes(quat_to_rotation(self.state.q), A, R0, np.asarray(ks, np.intp))

    def _spread(self, uv: np.ndarray, priority: np.ndarray, known, n: int, idx: np.ndarray) -> np.ndarray:
        """``n`` of the candidates ``idx``: the target's points first, then round-robin over a
        grid of image cells, the highest ``priority`` first."""
        cam = self.slam.cam
        cell = (np.clip((uv[:, 0] / cam.width * _GRID[0]).astype(int), 0, _GRID[0] - 1) * _GRID[1]
                + np.clip((uv[:, 1] / cam.height * _GRID[1]).astype(int), 0, _GRID[1] - 1))
        order = np.lexsort((-priority, cell))
        rank = np.empty(len(order), int)
        for c in np.unique(cell):
            members = order[cell[order] == c]
            rank[members] = np.arange(len(members))
        key = np.where(np.asarray(known, bool), -1, rank)
        pick = np.lexsort((-priority, key))[:n]
        return idx[np.sort(pick)]

    def _search(self, g: np.ndarray) -> tuple[Prediction, np.ndarray, np.ndarray, int, list, np.ndarray]:
        """The features chosen this frame (_select: prediction, innovation covariances, noise
        scales, how many predicted visible) and their matches in ``g``: z (m, 2) NaN where not
        found."""
        slam = self.slam
        s = slam.settings
        pred, S, r_scale, visible, Y = self._select()
        feats = [self.features[k] for k in pred.ks]
        warp = np.array([slam.warped(f) for f in feats], bool)
        z, _, found = match_features(g, feats, warp, Y, self.state.x_v, slam.cam, pred.uv, S,
                                     s.match_score, s.max_search_area_px)
        z[~found] = np.nan
        return pred, S, r_scale, visible, feats, z

    def _measure(self, g: np.ndarray, st: FrameStats, frame: int, retry_dt: float | None = None,
                 accept: Callable[[FrameUpdate], bool] | None = None) -> bool:
        """Search, RANSAC and update for this frame; ``retry_dt`` : the constant-velocity
        prediction's interval, s, when a frame most searches miss may be searched again;
        ``accept`` : shown the updates before they are written (one_point_ransac). False when it
        refused them: the state and the features' records are as they were."""
        slam = self.slam
        s, cam = slam.settings, slam.cam
        pred, S, r_scale, visible, feats, z = self._search(g)
        m = len(pred.ks)
        n_found = int(np.isfinite(z).all(axis=1).sum())
        if retry_dt and s.retry_noise_gain > 1 and m >= s.retry_min_searched and n_found < s.retry_found_fraction * m:
            # Most features missed their ellipses: a jerk the constant-velocity model did not
            # allow for (a fast turn's start or stop). The prediction's impulse is taken
            # retry_noise_gain times larger and the frame searched again in the grown ellipses,
            # kept if it finds more (after a long gap the grown ellipses can pass searching).
            cd = self.state.cam_dim
            first, P_cam = (pred, S, r_scale, visible, feats, z), self.state.P[:cd, :cd].copy()
            self._grow_impulse(retry_dt, s.retry_noise_gain)
            pred, S, r_scale, visible, feats, z = self._search(g)
            if np.isfinite(z).all(axis=1).sum() > n_found:
                st.retried = True
            else:
                pred, S, r_scale, visible, feats, z = first
                self.state.P[:cd, :cd] = P_cam
            m = len(pred.ks)
        st.predicted = visible
        edged = self._known_by_edges(g, feats, z, pred.uv) if s.known_edges else np.zeros(m, bool)
        for f in feats:
            f.attempts += 1
        st.searched = m
        found = np.isfinite(z).all(axis=1)
        st.found = int(found.sum())
        self.last = SearchView(np.array([self.features[k].id for k in pred.ks], int), pred.uv.copy(), S.copy(), z,
                               np.zeros(m, bool), pred.ks.copy())
        if not found.any():
            self.score -= 0.5 * s.ambiguity_gate_chi2 * m
            return True
        fi = np.flatnonzero(found)
        sub = pred.take(fi)
        rng = np.random.default_rng((slam.seed, frame))
        res = one_point_ransac(self.state, sub.ks, z[fi], cam, slam.cfg.sigma_pixel**2, sub, S[fi],
                               s.ransac_threshold_px, s.ransac_max_hypotheses, s.ransac_confidence, s.rescue_chi2, rng,
                               r_scale[fi], votes=self._votes(sub.ks, edged[fi]), accept=accept)
        if res.refused:
            for f in feats:             # the search counted as not made (the votes read it first)
                f.attempts -= 1
            return False
        used = res.used.tolist()
        ks_found = sub.ks.tolist()
        for k, u in zip(ks_found, used):
            if u:
                self.features[k].successes += 1
                self.features[k].last_seen = frame
        self.last.used[fi] = res.used
        if s.drift_gain > 0 and res.used.any():
            ku = sub.ks[res.used]
            residual = z[fi][res.used] - predict_uv(self.state, ku, cam)
            for k, r, finite in zip(ku.tolist(), residual, np.isfinite(residual).all(axis=1).tolist()):
                if finite and not self.features[k].known:
                    self.features[k].note_residual(r, s.drift_memory)
        st.matched = res.n_inliers
        st.rescued = int(res.rescued.sum())
        st.outliers = res.n_outliers
        # Evidence for this track's start-up hypothesis: the prior innovations' Mahalanobis
        # distances, capped at a gate (a miss or an outlier costs the gate).
        nu = z[fi] - sub.uv
        d2 = innovation_nis(nu, S[fi])
        for k, u, d in zip(ks_found, used, d2.tolist()):
            if u:
                h = self.features[k].nis
                h.append(d)
                if len(h) > s.consistency_window:
                    del h[0]
        gate = s.ambiguity_gate_chi2
        d2 = np.where(res.used, np.minimum(d2, gate), gate)
        self.score -= 0.5 * (d2.sum() + gate * (m - len(fi)))
        return True

    def _grow_impulse(self, dt: float, gain: float) -> None:
        """The camera block's covariance as if the constant-velocity prediction over ``dt`` had
        taken impulses ``gain`` times larger: ``G P_n G^T`` added ``gain^2 - 1`` times more."""
        cd = self.state.cam_dim
        _, _, G = f_and_dfdx_dfdn(self.state.x[:cd], dt)
        extra = G @ noise_covariance(dt, self.motion_cfg, math.sqrt(gain * gain - 1.0)) @ G.T
        self.state.P[:cd, :cd] += 0.5 * (extra + extra.T)

    def _votes(self, ks: np.ndarray, edged: np.ndarray | None = None) -> np.ndarray:
        """Each match's vote for a 1-point hypothesis: its feature's reliability (MapFeature, at
        most 1); a target corner placed by the target's fitted sides in this frame (``edged``
        (m,)) votes ``known_vote``: it is within a few tenths of a pixel, and a map that drifted
        with the camera agrees with itself and would outvote a small far target's corners."""
        votes = np.array([self.features[k].reliability for k in ks], float)
        if edged is not None:
            votes[np.asarray(edged, bool)] = self.slam.settings.known_vote
        return votes

    def _known_by_edges(self, g: np.ndarray, feats: list, z: np.ndarray, uv_pred: np.ndarray) -> np.ndarray:
        """A printed quadrilateral target whose corners' templates found at least three of them
        is located by its fitted sides (as at the start), not by the templates: a template, cut
        once at the start and warped by the estimated pose, carries that pose's error into every
        match, and one cut from a small far view matches a near one a few pixels off or not at
        all. A corner not found starts from its prediction ``uv_pred`` (m, 2); the sides may then
        move the corners as far as at the start (startup.corners_by_edges), or they are
        left to the templates. Returns which of ``feats`` (m,) it placed."""
        placed = np.zeros(len(feats), bool)
        rows = [j for j, f in enumerate(feats) if f.known]
        slam = self.slam
        target = slam.refined_target
        if len(rows) != 4 or target is None or len(target.xyz) != 4:
            return placed
        rows.sort(key=lambda j: feats[j].id)
        quad = z[rows]
        found = np.isfinite(quad).all(axis=1)
        if found.sum() < 3:
            return placed
        quad = np.where(found[:, None], quad, uv_pred[rows])
        edged = corners_by_edges(slam.cam, g, quad, slam.settings.click_search_px)
        if edged is not None:
            z[rows] = edged
            placed[rows] = True
        return placed

    def _watch_target(self, g: np.ndarray, st: FrameStats, frame: int) -> None:
        """The target's four corners predicted in view and not matched for ``reacquire_after``
        frames: the pose has drifted beyond their search ellipses (a long look away, a fast turn
        the motion model missed), and the natural map, made from the drifting pose, agrees with
        it. The printed quadrilateral is sought near its prediction; found, fitting one pose as
        at the start, and with the natural features mapped while the target was matched found
        where that pose projects them (:meth:`_old_map_agrees`, as the whole-image search asks),
        the camera is put back at that pose (a re-localisation against the target) and the
        features first seen since the target was last matched, placed from the drifted poses,
        are removed."""
        slam = self.slam
        s, target = slam.settings, slam.refined_target
        if target is None or len(target.xyz) != 4 or self.last is None:
            return
        rows = [j for j, k in enumerate(self.last.ks) if self.features[k].known]
        if len(rows) == 4 and self.last.used[rows].sum() >= 3:
            self.target_seen, self.target_missed = frame, 0
            return
        if len(rows) < 4 or self.last.used[rows].sum() > 1:
            self.target_missed = 0          # not all in view, or partly matched: no evidence of drift
            return
        self.target_missed += 1
        if self.target_missed < s.reacquire_after:
            return
        self.target_missed = 0              # found or not, look again only after as many frames
        rows.sort(key=lambda j: self.last.ids[j])
        uv_pred = self.last.uv[rows]
        diag = max(np.linalg.norm(uv_pred[2] - uv_pred[0]), np.linalg.norm(uv_pred[3] - uv_pred[1]))
        quad = find_quadrilateral(g, uv_pred, s.reacquire_search * diag)
        if quad is None:
            return
        edged = refine_by_edges(slam.cam, g, quad)
        quad = quad if edged is None else edged
        # Found where the filter's own uncertainty allows (the templates missed for blur or
        # shading, not for drift): nothing to correct.
        nu = quad - uv_pred
        d2 = float(innovation_nis(nu, self.last.S[rows]).sum())
        if d2 < s.reacquire_chi2:
            return
        try:
            hyps = pose_hypotheses(slam.cam, target.xyz, quad, s.start_pixel_sigma, s.ambiguity_ratio)
        except SlamStartError:
            return
        hyps = [h for h in hyps if h.rms_px <= s.start_max_rms_px]
        if not hyps:
            return
        R_now = quat_to_rotation(self.state.x[Q_SLICE])
        hyp = min(hyps, key=lambda h: np.linalg.norm(h.R_world_cam - R_now))
        # A drift turns the camera by little; a pose half a turn away is another quadrilateral
        # (or this one's corners in another order), as in the whole-image search.
        if rotation_angle(R_now, hyp.R_world_cam) > s.loop_max_turn_rad:
            return
        # A drifted pose has left the map the target anchored: the natural features mapped
        # while the target was matched must match at the target's pose. A quadrilateral that is
        # not the target (the target hidden, a shadow's edge) gives a pose they refute.
        old = self._mapped_before_loss()
        if old is not None and not self._old_map_agrees(g, hyp.R_world_cam, hyp.r, old):
            return
        self._restart_at_target(hyp, st, frame)

    def _close_loop(self, g: np.ndarray, st: FrameStats, frame: int) -> bool:
        """The target unmatched for a while: sought anywhere in the image (startup.locate_target),
        since a pose drifted far (a fast turn absorbed as a wrong velocity while only new
        features were in view) can predict it off the image when it is back. A pose found there
        that the filter's corner predictions do not allow is checked against the natural
        features mapped before the target was lost: projected from that pose, at least
        ``loop_min_old`` of them, and half of those in view, must match within
        ``loop_window_px`` of where it puts them, which a dark rectangle elsewhere does not give
        (features printed with the target, on its card, move with any copy of it; the rest of
        the scene does not). Lost before any natural feature was mapped, there is no such map:
        the most print-like candidate is taken if it is at least half as print-like as the
        target was in the first image. Confirmed, the camera is restarted there, the features
        first seen since the target was lost (placed from the drifting poses) removed, and the
        frame measured. Returns whether it was."""
        slam = self.slam
        s, target, cam = slam.settings, slam.refined_target, slam.cam
        if target is None or len(target.xyz) != 4:
            return False
        known = self.known_in_id_order()
        if len(known) != 4:
            return False
        found = locate_target(g, cam, target.xyz, quat_to_rotation(self.state.x[Q_SLICE]), s.loop_max_turn_rad,
                              s.start_max_rms_px, s.loop_min_area_px)
        if not found:
            return False
        pred = predict(self.state, known, cam)
        S = innovation_covariances(self.state, pred, slam.cfg.sigma_pixel**2, np.ones(4)) if pred.valid.all() else None
        # Lost before any natural feature was mapped (a drift from the first frames), the map
        # holds only what the drift placed and there is nothing to ask: the most print-like
        # quadrilateral is taken, as the start-up takes it. A map that had such features asks
        # them even when the cap has since removed them (a lone dark quadrilateral is no proof).
        old = self._mapped_before_loss()
        ask_map = old is not None
        if not ask_map:
            # and only if it looks as printed as the target did at the start (not a picture frame)
            found = [f for f in found[:1] if print_contrast(g, f.uv) >= 0.5 * slam.target_contrast]
        for seen in found[:s.loop_trials]:
            if S is not None:
                nu = seen.uv - pred.uv
                if float(innovation_nis(nu, S).sum()) < s.reacquire_chi2:
                    return False    # where the filter expects it: the active search will take it
            if not ask_map or self._old_map_agrees(g, seen.R_world_cam, seen.r, old):
                break
        else:
            return False
        try:
            hyps = pose_hypotheses(cam, target.xyz, seen.uv, s.start_pixel_sigma, s.ambiguity_ratio)
        except SlamStartError:
            return False
        self._restart_at_target(min(hyps, key=lambda h: np.linalg.norm(h.R_world_cam - seen.R_world_cam)), st, frame)
        self._measure(g, st, frame)
        return True

    def _restart_at_target(self, hyp: PoseHypothesis, st: FrameStats, frame: int) -> None:
        """The camera put back at the target's pose ``hyp`` (of a planar pair, the one the
        caller chose), and the features first seen since the target was last matched, placed
        from the drifting poses, removed. A turn goes on (the templates often miss in one): the
        filter's angular velocity, which the drift leaves nearly right, is a better guess than
        rest; its linear velocity is the drift's own and is reset with the pose."""
        turning = self.state.x[W_SLICE].copy()
        self.slam.restart_camera(self.state, hyp)
        self.state.x[W_SLICE] = turning
        drifted = [k for k, f in enumerate(self.features) if not f.known and f.first_frame > self.target_seen]
        if drifted:
            self._remove(drifted, st)
        st.reacquired = True
        self.target_seen, self.target_missed = frame, 0

    def _mapped_before_loss(self) -> np.ndarray | None:
        """The natural features mapped while the target was last matched (map indices), which a
        pose put back at the target must match; None when no natural feature had been mapped by
        then (a drift from the first frames: no map to ask). Empty when the cap has since removed
        them all: a lone quadrilateral is then no proof."""
        if self.first_mapped is None or self.first_mapped > self.target_seen:
            return None
        return np.array([k for k, f in enumerate(self.features) if not f.known and f.first_frame <= self.target_seen],
                        int)

    def _old_map_agrees(self, g: np.ndarray, R_world_cam: np.ndarray, r: np.ndarray, ks: np.ndarray) -> bool:
        """Whether features ``ks`` match in ``g`` where the pose (R_world_cam, r) projects them: at least
        ``loop_min_old`` of them, and half of those it puts in the image, each found within
        ``loop_window_px`` of its projection, and by the median within a third of that. A right
        pose puts its matches within a pixel or two; at a wrong one, a bare counter's grain
        still gives best scores, spread over the windows and most on their rims (twin
        kitchen-walk at 320x240: 9 of 15 found, 6-7 px off, the pose 37 cm away)."""
        slam = self.slam
        s, cam = slam.settings, slam.cam
        if len(ks) < s.loop_min_old:
            return False
        Y = self.world_points()[ks]
        uv = project_points(cam, (Y - r) @ R_world_cam)
        inside = np.isfinite(uv).all(axis=1) & in_image(cam, np.nan_to_num(uv, nan=-1e9), margin=s.margin_px)
        if inside.sum() < s.loop_min_old:
            return False
        ks, Y, uv = ks[inside], Y[inside], uv[inside]
        feats = [self.features[k] for k in ks]
        x_v = np.r_[r, quat_from_rotation(R_world_cam)]
        S = np.broadcast_to(np.eye(2) * (s.loop_window_px / 3.0) ** 2, (len(ks), 2, 2)).copy()
        z, _, found = match_features(g, feats, np.array([slam.warped(f) for f in feats], bool), Y, x_v, cam, uv, S,
                                     s.match_score, s.max_search_area_px)
        if int(found.sum()) < max(s.loop_min_old, 0.5 * len(ks)):
            return False
        return float(np.median(np.linalg.norm(z[found] - uv[found], axis=1))) <= s.loop_window_px / 3.0

    # ------------------------------------------------------------------ map management
    def _conversions(self, st: FrameStats) -> tuple[list, list, list]:
        """The inverse-depth features whose depth is now well represented in Euclidean
        coordinates (Civera et al.'s linearity index) and their points and Jacobians, for
        :meth:`_delete` to apply: none if any conversion is not finite."""
        state = self.state
        _, L = self._points_and_linearity()
        ks = np.flatnonzero(L < self.slam.linearity_threshold).tolist()
        ys, Js = point_conversions(state, ks) if ks else ([], [])
        if not all(np.isfinite(y).all() and np.isfinite(J).all() for y, J in zip(ys, Js)):
            ks, ys, Js = [], [], []
        st.converted += len(ks)
        st.initialising = int((state.kinds == INVERSE_DEPTH).sum()) - len(ks)
        return ks, ys, Js

    def _delete(self, st: FrameStats, frame: int, conversions: tuple[list, list, list] = ([], [], [])) -> None:
        """MonoSLAM's rule (inlier matches below ``delete_ratio`` of searches after
        ``delete_min_attempts``), a quicker one for new features that fail from the start, and
        the map's size cap: beyond ``max_features`` natural features go in :func:`cap_victims`'
        order (out of view first, inverse-depth before points, seen longest ago first). The
        ``conversions`` (:meth:`_conversions`) are applied in the same rebuild of the state, and
        the rules see the converted features as points."""
        s = self.slam.settings
        state = self.state
        kinds = state.kinds.copy()
        kinds[conversions[0]] = POINT
        inv = np.flatnonzero(kinds == INVERSE_DEPTH)
        behind = set(inv[state.x[state.starts[inv] + 5] < 0].tolist())   # rho < 0
        bad = []
        min_attempts, ratio, young = s.delete_min_attempts, s.delete_ratio, s.delete_young_attempts
        window, nis_limit = s.consistency_window, self.slam.nis_limit
        for k, f in enumerate(self.features):
            if f.known:
                continue
            a, n = f.attempts, f.successes
            if a >= min_attempts and n < ratio * a:
                bad.append(k)
            elif a >= young and n <= a // 4:
                bad.append(k)
            elif len(f.nis) >= window and sum(f.nis) > nis_limit:
                # Its innovations over the window fail the chi-square test: not a fixed point
                # (a T-junction of a near edge and a far background, a reflection).
                bad.append(k)
            elif k in behind:
                bad.append(k)          # its depth went behind the first view: a mismatch's trace
        excess = len(self.features) - len(bad) - s.max_features
        if excess > 0:
            gone = set(bad)
            keep = np.array([k for k in range(len(self.features)) if k not in gone and not self.features[k].known],
                            np.intp)
            fs = [self.features[k] for k in keep]
            victims = cap_victims(excess, np.array([f.last_seen for f in fs]),
                                  np.array([f.id in self.in_view_ids for f in fs], bool), kinds[keep] == POINT)
            bad += keep[victims].tolist()
        bad = sorted(set(bad))
        ks, ys, Js = conversions
        gone = set(bad)
        keep_conv = [i for i, k in enumerate(ks) if k not in gone]   # a feature removed is not converted
        if keep_conv or bad:
            self._remove(bad, st, ([ks[i] for i in keep_conv], [ys[i] for i in keep_conv], [Js[i] for i in keep_conv]))

    def _remove(self, ks: list[int], st: FrameStats, conversions: tuple[list, list, list] = ([], [], [])) -> None:
        """Features ``ks`` (ascending) out of the state and the map, counted in ``st``, and the
        ``conversions`` to points applied in the same rebuild."""
        self.state.edit_features(remove=ks, convert=conversions[0], kind=POINT, ys_new=conversions[1],
                                 Js=conversions[2])
        for k in reversed(ks):
            del self.features[k]
        st.deleted += len(ks)

    def _occupied(self) -> np.ndarray:
        """Pixels new features keep away from: where every feature is predicted, except those
        searched for and not matched this frame (their place is free for new ones)."""
        uv = predict_uv(self.state, np.arange(self.state.n_features), self.slam.cam)
        failed = set(self.last.ids[~self.last.used].tolist()) if self.last is not None else set()
        free = np.array([f.id in failed for f in self.features], bool).reshape(-1)
        occupied = [uv[np.isfinite(uv).all(axis=1) & ~free]]
        occupied += [p.uv0[None] for _, p, _, _ in self.rays]
        return np.concatenate(occupied) if occupied else np.zeros((0, 2))

    def _add(self, g: np.ndarray, st: FrameStats, frame: int, visible: int) -> None:
        slam = self.slam
        s, cam = slam.settings, slam.cam
        if s.features == "particles":
            n = min(s.max_initialising - len(self.rays), s.new_per_frame)
        else:
            n = min(s.new_per_frame, s.visible_min - visible)
        if n <= 0:
            return
        scale = cam.width / 640.0
        # Where the motion keeps them in view first, else any (MonoSLAM's placement).
        chosen = new_features(g, self._occupied(), 4 * n, size=slam.template_px, min_std=slam.contrast_floor(g),
                              min_distance=s.min_distance_px * scale, border=max(int(20 * scale), slam.template_px),
                              prefer=lambda uv: slam.stay_in_view(self.state.x_v, uv), take=n)
        R0 = quat_to_rotation(self.state.q)
        ph = patch_half(slam.template_px)
        if s.features == "particles":
            for uv, tpl in chosen:
                origin, d = ray_from_pixel(self.state.x_v, uv, cam)[:2]
                p = depth_init.DepthParticles.create(origin, d, tpl, uv, s.particles, s.depth_near_m, s.depth_far_m)
                self.rays.append((slam.new_id(), p, R0.copy(), first_view_patch(g, uv, ph)))
        elif chosen:
            uvs = np.array([uv for uv, _ in chosen], float)
            rays_cam, J_rays = unproject_jacobian(cam, uvs)     # for the states and the normals
            rays = rays_cam @ R0.T
            ok = np.isfinite(rays).all(axis=1)
            chosen, uvs, rays = [c for c, o in zip(chosen, ok) if o], uvs[ok], rays[ok]
            try:
                added = add_inverse_depth_features(self.state, uvs, cam, *self._depth_prior(),
                                                   slam.cfg.sigma_pixel**2, rays=(rays_cam[ok], J_rays[ok]))
            except (FeatureNotMeasurable, SlamNumericalError):
                added = []
            if len(added) == len(chosen):
                for (uv, tpl), ray in zip(chosen, rays):
                    if self.first_mapped is None:
                        self.first_mapped = frame
                    self.features.append(MapFeature(slam.new_id(), tpl, frame, self.state.r.copy(),
                                                    patch=first_view_patch(g, uv, ph), uv0=np.asarray(uv, float),
                                                    R0=R0.copy(), normal=-ray / np.linalg.norm(ray), last_seen=frame))
                st.added += len(added)
            elif added:                                 # cannot happen: the rays were checked above
                self.state.remove_features(added)
        st.initialising = len(self.rays) if s.features == "particles" else int((self.state.kinds == INVERSE_DEPTH).sum())

    def _depth_prior(self) -> tuple[float, float]:
        """New inverse-depth features' prior (rho0, sigma_rho), 1/m: centred on the points this
        frame's measurement used (inverse_depth.scene_prior) unless the settings fix it."""
        s, sv = self.slam.settings, self.last
        if not s.scene_depth_prior or sv is None:
            return s.rho0, s.sigma_rho
        used = set(sv.ids[sv.used].tolist())         # by id: _delete may have renumbered the map
        ks = [k for k, f in enumerate(self.features) if f.id in used]
        return inverse_depth.scene_prior(self.world_points()[ks], self.state.r, s.rho0, s.sigma_rho)

    def _normals_from_views(self, g: np.ndarray) -> None:
        """The plane normals of features matched this frame whose view has turned far enough
        from their first, from their appearance (after Molton, Davison and Reid, "Locally planar
        patch features for real-time structure from motion", BMVC 2004): of candidate normals,
        the one whose warp of the first-view patch best matches the image at the match. A
        fronto-parallel guess warps a floor or wall seen obliquely wrongly, and its template
        stops matching a few tens of degrees on."""
        slam = self.slam
        s, cam = slam.settings, slam.cam
        sv = self.last
        if sv is None or not len(sv.ks):
            return
        feats = self.features
        cand = [(j, k) for j, k in zip(np.flatnonzero(sv.used).tolist(), sv.ks[sv.used].tolist())
                if k < len(feats) and feats[k].id == sv.ids[j] and not feats[k].known
                and feats[k].patch is not None and feats[k].normal is not None]
        if not cand:
            return
        js, ks = np.array(cand).T
        r = self.state.r
        Y = self.world_points()
        r0s = np.array([feats[k].r0 for k in ks], float).reshape(-1, 3)
        angle = np.degrees(np.arccos(_from_first_view(np.ascontiguousarray(Y[ks]), np.asarray(r, float), r0s)[0]))
        gain = angle - np.array([feats[k].normal_view_deg for k in ks])
        due = [i for i in np.argsort(-gain, kind="stable")[:s.normals_per_frame] if gain[i] >= s.normal_step_deg]
        if not due:
            return
        R = quat_to_rotation(self.state.x_v[3:7])
        model, lens = lens_kernel_args(cam)
        g32 = np.ascontiguousarray(g, np.float32)
        tilts = np.array([0.0, 20.0, 40.0, 60.0])
        for i in due:
            f = feats[ks[i]]
            n, score, current = fit_normal_kernel(
                g32, f.patch.astype(np.float32, copy=False), slam.template_px, f.first_view_rays(cam),
                np.asarray(f.r0, float), np.ascontiguousarray(Y[ks[i]], float), np.asarray(r, float), R, model, lens,
                np.asarray(sv.z[js[i]], float), np.asarray(f.normal, float), tilts, 8, 10.0)
            f.normal_view_deg = float(angle[i])
            if score < current - s.normal_margin:
                f.normal = n / np.linalg.norm(n)

    def _normals_from_map(self) -> None:
        """Give each natural point feature whose normal was not fitted to its looks
        (_normals_from_views) the normal of the plane through it and its map neighbours, facing
        its first view."""
        points = np.flatnonzero(self.state.kinds == POINT)
        if len(points) < 4:
            return
        Y = self.world_points()[points]
        neighbours = cKDTree(Y).query_ball_point(Y, self.slam.settings.plane_radius_m)
        for j, k in enumerate(points):
            f = self.features[k]
            if not f.known and len(neighbours[j]) >= 4 and f.normal_view_deg == 0:
                n = local_plane_normal(Y[neighbours[j]], neighbours[j].index(j), np.inf, self.slam.settings.plane_tol_m)
                if n is not None:
                    f.normal, f.normal_from_map = (n if n @ (f.r0 - Y[j]) > 0 else -n), True

    # ------------------------------------------------------------------ particles (the paper's)
    def _refine_rays(self, g: np.ndarray, st: FrameStats, frame: int) -> None:
        slam = self.slam
        s, cam = slam.settings, slam.cam
        x_v = self.state.x_v
        P_pose = self.state.P[:POSE_DIM, :POSE_DIM]
        R = slam.cfg.sigma_pixel**2 * np.eye(2)
        keep = []
        for fid, p, R0, patch in self.rays:
            def project(points):
                uv, H_c, valid = predict_points(x_v, points, cam)
                S = np.full((len(points), 2, 2), np.nan)
                S[valid] = H_c[valid] @ P_pose @ np.swapaxes(H_c[valid], 1, 2) + R
                return uv, S

            def match(uv, S):
                ok = np.isfinite(uv).all(axis=1) & np.isfinite(S).all(axis=(1, 2))
                if not ok.any():
                    return None
                lo = (uv[ok] - 3 * np.sqrt(S[ok][:, [0, 1], [0, 1]])).min(axis=0)
                hi = (uv[ok] + 3 * np.sqrt(S[ok][:, [0, 1], [0, 1]])).max(axis=0)
                c, half = (lo + hi) / 2, (hi - lo) / 2
                m = search(g, p.template, c, np.diag((half / 3) ** 2) + 1e-9, n_sigma=3.0,
                           max_score=s.match_score, max_area=120_000)
                return (m.uv, float(np.prod(2 * half + 1))) if m.found else None

            depth_init.step(p, project, match, s.prune, s.outlier)
            if p.is_gaussian(s.gauss_ratio) and p.frames >= s.min_init_frames:
                self._promote(fid, p, R0, patch, st, frame)
            elif p.frames < s.max_init_frames and p.failures < 10 and len(p.depths) > 0:
                keep.append((fid, p, R0, patch))
        self.rays = keep
        st.initialising = len(self.rays)

    def _promote(self, fid, p, R0, patch, st: FrameStats, frame: int) -> None:
        slam = self.slam
        y = p.origin + p.mean * p.direction
        uv = project_points(slam.cam, ((y - self.state.r) @ quat_to_rotation(self.state.q))[None])[0]
        if not np.isfinite(uv).all():
            return
        depth = float(np.linalg.norm(y - self.state.r))
        try:
            add_point_feature(self.state, uv, depth, (slam.settings.promote_std_gain * p.std) ** 2, slam.cfg.sigma_pixel**2,
                              slam.cam)
        except (SlamNumericalError, FeatureNotMeasurable):
            return
        normal = (p.origin - y) / np.linalg.norm(p.origin - y)
        if self.first_mapped is None:
            self.first_mapped = frame
        self.features.append(MapFeature(fid, p.template, frame, p.origin.copy(), patch=patch, uv0=p.uv0, R0=R0,
                                        normal=normal, last_seen=frame))
        st.added += 1

    # ------------------------------------------------------------------ re-localisation
    def _elongated(self, k: int) -> bool:
        """Whether feature ``k``'s matches are uncertain along one direction beyond
        ``MAX_RELOC_ELONGATION`` times its variance across it (an edge)."""
        w = np.linalg.eigvalsh(self.features[k].noise_shape)
        return bool(w[1] > MAX_RELOC_ELONGATION * w[0])

    def _relocalise(self, g: np.ndarray) -> bool:
        """Re-acquire the camera pose from whole-image matches of the target and the most
        reliable point features (relocalise.py); on success restart the camera block there, in
        the map's own frame."""
        s = self.slam.settings
        # Points first; inverse-depth features too (a rotating head converts few), at their
        # current depth: PnP-RANSAC and the active search decide whether those are good enough.
        candidates = list(range(self.state.n_features))
        if len(candidates) < s.reloc_min_inliers:
            return False
        # An edge's template matches anywhere along the edge in a whole-image search: features
        # whose matches are elongated (templates.match_noise_shape) come after the rest.
        rank = sorted(candidates, key=lambda k: (not self.features[k].known, self._elongated(k),
                                                 self.state.kinds[k] != POINT, -self.features[k].successes))
        ks = np.array(rank[:s.reloc_candidates])
        found = relocalise(g, [self.features[k].template for k in ks], self.world_points()[ks], self.slam.cam,
                           s.match_score, min_inliers=s.reloc_min_inliers, Y_cov=self.point_covariances(ks),
                           sigma_px=self.slam.cfg.sigma_pixel)
        if found is None:
            return False
        hyp = PoseHypothesis(found.R_world_cam, found.r,
                             np.diag(np.r_[np.full(3, s.reloc_sigma_rad**2), np.full(3, s.reloc_sigma_m**2)]), 0.0, 0.0)
        self.slam.restart_camera(self.state, hyp)
        return True


class MonoSLAM:
    """Single-camera EKF SLAM over a sequence of images (see the module docstring).

    camera : the intrinsics and lens model. cfg, settings : the filter's and the map's
    parameters. imu : whether an IMU will drive the prediction (then, with
    ``settings.imu_biases``, the camera block carries bias states). seed : the RANSAC's random
    order (per frame), so a run is repeatable.
    """

    def __init__(self, camera: CameraIntrinsics, cfg: SlamConfig = DEFAULT_CONFIG, settings: MapSettings = MapSettings(),
                 imu: bool = False, seed: int = 0):
        self.cam = camera
        self.cfg = cfg
        self.settings = settings
        self.seed = seed
        self.use_imu = bool(imu) and settings.use_imu
        self.cam_dim = CAMERA_DIM
        if self.use_imu and settings.imu_biases:
            self.cam_dim = CAMERA_DIM_TIMED if settings.imu_time_offset else CAMERA_DIM_BIASED
        # Templates and distances scale with the image (15 px at 640 px wide).
        t = int(round(settings.template_px * camera.width / 640.0))
        self.template_px = max(t + (1 - t % 2), 7)
        self._tracks: list[_Track] = []
        self._next_id = 0
        self.frame = -1
        self.t_prev: float | None = None
        self.stats: list[FrameStats] = []
        self.imu = ImuStream(settings)
        self.messages: list[str] = []      # what the console should say (IMU problems, ...)
        self.nis_limit = float(chi2.ppf(settings.consistency_confidence, 2 * settings.consistency_window))
        self.linearity_threshold = (settings.linearity_threshold if camera.width >= NARROW_WIDTH_PX
                                    else settings.linearity_threshold_narrow)
        self.refined_target: RefinedTarget | None = None
        self.target_contrast = 0.0              # the target's print contrast in the first image
        self.still: StillBiases | None = None    # the biases a still stretch before the start gave
        self._noise: tuple[int, float] | None = None   # (frame, image noise sigma) last estimated
        self.scale_source = "target"            # what fixed the map's unit: target, map, depth or arbitrary

    # -------------------------------------------------------------- views
    @property
    def track(self) -> _Track:
        if not self._tracks:
            raise RuntimeError("SLAM has not started: call start() (or start_from_map()) first")
        return self._tracks[0]

    @property
    def started(self) -> bool:
        return bool(self._tracks)

    @property
    def state(self) -> State | None:
        return self._tracks[0].state if self._tracks else None

    @property
    def features(self) -> list[MapFeature]:
        return self.track.features

    @property
    def rays(self) -> list:
        return self.track.rays

    @property
    def lost(self) -> bool:
        return self.track.lost

    @property
    def localised(self) -> bool:
        return bool(self._tracks) and self.track.localised and not self.track.lost

    def new_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    def warped(self, f: MapFeature) -> bool:
        """Whether the feature's template is predicted through its plane (MapSettings.warp)."""
        w = self.settings.warp
        return w == "all" or (w == "known" and f.known) or (
            w == "neighbours" and (f.known or f.normal_from_map or f.normal_view_deg > 0))

    def T_world_cam(self) -> np.ndarray:
        """(4, 4) the current camera pose (NaN before the camera is localised in the map)."""
        T = np.eye(4)
        tr = self.track
        if not tr.localised:
            return np.full((4, 4), np.nan)
        T[:3, :3] = quat_to_rotation(tr.state.q)
        T[:3, 3] = tr.state.r
        return T

    def world_points(self) -> np.ndarray:
        """(N, 3) every map feature's current point, world, m."""
        return self.track.world_points()

    def map_view(self) -> MapView:
        """A snapshot of the map, the camera and the last search (see :class:`MapView`)."""
        from .features import FEATURE_NAMES

        tr = self.track
        st = tr.state
        Y = tr.world_points()
        n = st.n_features
        cov = tr.point_covariances(np.arange(n))
        r_ids, r_o, r_d, r_depth = [], [], [], []
        for k in range(n):
            sl = st.feature_slice(k)
            P = st.P[sl, sl]
            if st.kinds[k] == INVERSE_DEPTH:
                y = st.feature(k).copy()
                y[5] = max(y[5], 0.05)
                m = st.anchors[k] @ inverse_depth.direction_kernel(float(y[3]), float(y[4]))[0]
                s_rho = math.sqrt(max(P[5, 5], 0.0))
                rho_hi, rho_lo = y[5] + 2 * s_rho, y[5] - 2 * s_rho
                r_ids.append(tr.features[k].id)
                r_o.append(y[:3].copy())
                r_d.append(m / np.linalg.norm(m))
                r_depth.append((1.0 / rho_hi, 1.0 / rho_lo if rho_lo > 0 else np.inf))
        for fid, p, _, _ in tr.rays:
            r_ids.append(fid)
            r_o.append(p.origin.copy())
            r_d.append(p.direction.copy())
            r_depth.append((float(p.depths.min()), float(p.depths.max())))
        return MapView(
            t=float(self.t_prev) if self.t_prev is not None else 0.0, T_world_cam=self.T_world_cam(),
            ids=np.array([f.id for f in tr.features], int), xyz=Y, cov=cov,
            kinds=tuple(FEATURE_NAMES[k] for k in st.kinds), known=np.array([f.known for f in tr.features], bool),
            ray_ids=np.array(r_ids, int), ray_origin=np.array(r_o).reshape(-1, 3),
            ray_direction=np.array(r_d).reshape(-1, 3), ray_depth=np.array(r_depth, float).reshape(-1, 2),
            search=tr.last)

    # -------------------------------------------------------------- start-up
    def _camera_state(self, hyp: PoseHypothesis, t: float) -> State:
        x_v, P = hyp.camera_prior(self.settings.init_sigma_v, self.settings.init_sigma_w, self.cam_dim)
        if self.cam_dim >= CAMERA_DIM_BIASED:
            for sl, s0 in ((BG_SLICE, self.cfg.gyro_bias_sigma0), (BA_SLICE, self.cfg.accel_bias_sigma0)):
                P[sl, sl] = np.eye(3) * s0**2
            if self.cam_dim == CAMERA_DIM_TIMED:
                x_v[TD_INDEX], P[TD_INDEX, TD_INDEX] = self.cfg.time_offset0, self.cfg.time_offset_sigma0**2
            # A still stretch before the first frame gives the biases: the gyro's directly, the
            # accelerometer's through the start's attitude, correlated with it (as a new
            # feature is with the camera), so that refining the attitude refines it.
            still = still_biases(self.imu.rows, t, x_v[3:7], self.settings, self.cfg)
            if still is not None:
                x_v[BG_SLICE], P[BG_SLICE, BG_SLICE] = still.b_g, np.eye(3) * still.var_g
                J = np.zeros((3, self.cam_dim))
                J[:, 3:7] = still.J_q
                P[BA_SLICE, :] = 0.0
                P[:, BA_SLICE] = 0.0
                P_ax = J @ P
                x_v[BA_SLICE] = still.b_a
                P[BA_SLICE, :] = P_ax
                P[:, BA_SLICE] = P_ax.T
                P[BA_SLICE, BA_SLICE] = J @ P_ax.T + np.eye(3) * still.var_f
                self.still = still
        return State.from_camera(x_v, P)

    def restart_camera(self, state: State, hyp: PoseHypothesis) -> None:
        """Put the camera at a pose found against the map (re-localisation), at rest, with no
        correlation to the map; bias estimates are kept."""
        x_v, P_vv = hyp.camera_prior(self.settings.init_sigma_v, self.settings.init_sigma_w, state.cam_dim)
        cd = state.cam_dim
        x = state.x.copy()
        x[:13] = x_v[:13]
        P = state.P.copy()
        P[:13, :] = 0.0
        P[:, :13] = 0.0
        P[:13, :13] = P_vv[:13, :13]
        if cd > 13:
            P[13:cd, 13:cd] = state.P[13:cd, 13:cd]
        state.x, state.P = x, P

    def start(self, image: np.ndarray, t: float, target: Target) -> RefinedTarget:
        """Fix the world frame from the known target in the first image: its clicked pixels are
        refined on the image, its pose (and the planar ambiguity's second pose when it explains
        the corners nearly as well) found with its covariance, and its points inserted as
        features. Returns the refined target. Raises :class:`SlamStartError`."""
        g = grey(image)
        s = self.settings
        ref, hyps = start_hypotheses(self.cam, g, target, s.click_search_px, s.start_pixel_sigma, s.start_max_rms_px,
                                     s.ambiguity_ratio)
        self.refined_target = ref
        self.target_contrast = print_contrast(g, ref.uv) if len(ref.uv) == 4 else 0.0
        c = ref.xyz.mean(axis=0)
        _, _, Vt = np.linalg.svd(ref.xyz - c)
        self._tracks = []
        for hyp in hyps:
            state = self._camera_state(hyp, t)
            normal = Vt[2] if Vt[2] @ (hyp.r - c) > 0 else -Vt[2]
            feats = []
            for i, (X, p) in enumerate(zip(ref.xyz, ref.uv)):
                tpl = extract_template(g, p, self.template_px)
                if tpl is None:
                    raise SlamStartError(f"target point at pixel {np.round(p, 1).tolist()} is too close to the image "
                                         "border to take its template; the target must be in view at the start")
                state.add_feature(POINT, X, np.eye(3) * s.target_sigma_m**2, np.zeros((3, state.n)))
                feats.append(MapFeature(i, tpl, 0, hyp.r.copy(), known=True,
                                        patch=first_view_patch(g, p, patch_half(self.template_px)),
                                        uv0=np.asarray(p, float), R0=hyp.R_world_cam.copy(), normal=normal, last_seen=0))
            self._tracks.append(_Track(self, state, feats))
        if self.still is not None:
            self.messages.append(f"slam: IMU biases from the {self.still.seconds:.1f} s still before the first frame "
                                 f"(gyro {np.round(1e3 * self.still.b_g, 2).tolist()} mrad/s)")
        self._next_id = len(ref.xyz)
        self.frame = 0
        self.t_prev = t
        self.stats.append(FrameStats(0, t, matched=len(ref.xyz), map_size=len(ref.xyz), hypotheses=len(self._tracks)))
        return ref

    def start_natural(self, image: np.ndarray, t: float, ns) -> None:
        """Start from natural features (natural_start.NaturalStart of this frame): the camera at
        the world's origin, fixed (the first camera's frame is the world's, the gauge), the start's
        points mapped as point features with their covariances, its velocity the two views'. No
        target: nothing is watched for or sought again but the map."""
        g = grey(image)
        hyp = PoseHypothesis(np.eye(3), np.zeros(3), np.zeros((6, 6)), 0.0, 0.0)
        state = self._camera_state(hyp, t)
        state.x[7:10] = ns.v_world
        ph = patch_half(self.template_px)
        feats = []
        for X, C, uv in zip(ns.xyz, ns.xyz_cov, ns.uv):
            tpl = extract_template(g, uv, self.template_px)
            if tpl is None or float(np.std(tpl)) <= 2.0:
                continue
            state.add_feature(POINT, X, C, np.zeros((3, state.n)))
            feats.append(MapFeature(len(feats), tpl, 0, np.zeros(3), patch=first_view_patch(g, uv, ph),
                                    uv0=np.asarray(uv, float), R0=np.eye(3), normal=-X / np.linalg.norm(X),
                                    last_seen=0))
        if len(feats) < 3:
            raise SlamStartError("the natural start's points have no usable appearance (a blank view)")
        self._tracks = [_Track(self, state, feats)]
        self._tracks[0].first_mapped = 0
        self.refined_target = None
        self.scale_source = ns.scale
        self._next_id = len(feats)
        self.frame = 0
        self.t_prev = t
        self.stats.append(FrameStats(0, t, matched=len(feats), map_size=len(feats), hypotheses=1))

    def start_from_map(self, saved, t: float) -> None:
        """Start from a saved map (map_io.SavedMap) with the camera unknown: the track begins
        lost and re-localises against the map at every frame until it is found, then continues
        in the map's world frame."""
        state = saved.state_with_camera(self.cam_dim, self.cfg)
        # Made before this session's frame 0: the target's re-acquisition keeps them as the map
        # from before a loss, and the cap's order sees them as seen longest ago.
        feats = [replace(f, attempts=0, successes=0, rays0=None, first_frame=0, last_seen=0) for f in saved.features]
        self._tracks = [_Track(self, state, feats, localised=False)]
        # The map's known points are the target it was started from: placed by the print's sides,
        # watched for and sought again as after a start from the target (no pixels: no clicks).
        known = self._tracks[0].known_in_id_order()
        self.refined_target = None
        if len(known) == 4:
            xyz = np.array([state.feature(k)[:3] for k in known])
            self.refined_target = RefinedTarget(xyz, np.full((4, 2), np.nan), np.zeros(4))
        self._next_id = max((f.id for f in feats), default=-1) + 1
        self.frame = 0
        self.t_prev = t
        self.scale_source = "map"
        self.stats.append(FrameStats(0, t, map_size=len(feats), lost=True))

    # -------------------------------------------------------------- per frame
    def add_imu(self, rows) -> None:
        """Queue IMU rows (k, 7) ``[t, wx, wy, wz, ax, ay, az]`` (camera frame, imu.txt) in time
        order; bad samples are dropped, counted and said (``messages``)."""
        if not self.settings.use_imu:
            return
        for msg in self.imu.add(rows):
            self.messages.append(msg)

    def process(self, image: np.ndarray, t: float, imu=None) -> FrameStats:
        """One frame at time t (s); ``imu`` : optional IMU rows since the last frame."""
        t0 = time.perf_counter()
        if imu is not None:
            self.add_imu(imu)
        self.frame += 1
        t_prev = self.t_prev
        self.t_prev = t
        g = grey(image)
        rows = self._imu_rows(t_prev, t)
        stats = []
        for tr in self._tracks:
            st = FrameStats(self.frame, t)
            tr.step(g, t_prev, t, rows, st, self.frame)
            st.lost = tr.lost
            st.map_size = tr.state.n_features
            stats.append(st)
        self._drop_imu(t)
        self._decide()
        st = stats[0] if len(self._tracks) == len(stats) else stats[self._winner]
        st.hypotheses = len(self._tracks)
        st.seconds = time.perf_counter() - t0
        self.stats.append(st)
        return st

    def _decide(self) -> None:
        """With two start-up hypotheses, keep the one the map's measurements favour once the
        evidence is decisive (likelihood ratio ``ambiguity_ratio^2``) or after
        ``ambiguity_frames``."""
        self._winner = 0
        if len(self._tracks) < 2:
            return
        scores = np.array([tr.score for tr in self._tracks])
        best = int(np.argmax(scores))
        gap = scores[best] - np.delete(scores, best).max()
        if gap > 2 * math.log(self.settings.ambiguity_ratio) or self.frame >= self.settings.ambiguity_frames:
            self._winner = best
            self._tracks = [self._tracks[best]]
            self.messages.append(f"slam: planar target ambiguity resolved at frame {self.frame} "
                                 f"(log-likelihood ratio {gap:.1f}, pose {best})")

    def _imu_rows(self, t_prev: float, t: float):
        """The IMU rows covering every track's prediction to the frame at ``t`` (None: not
        covered, or no IMU)."""
        if not (self.settings.use_imu and len(self.imu.rows)):
            return None
        spans = [tr.span(t_prev, t) for tr in self._tracks] or [(t_prev, t)]
        return self.imu.covering(min(a for a, _ in spans), max(b for _, b in spans))

    def _drop_imu(self, t: float) -> None:
        self.imu.drop_before(t + min([0.0] + [tr.state.t_ref for tr in self._tracks]))

    def skip(self, t: float, why: str) -> FrameStats:
        """A frame that could not be read: predict through it, count it."""
        self.frame += 1
        rows = self._imu_rows(self.t_prev, t)
        for tr in self._tracks:
            tr.propagate(self.t_prev, t, rows, self.settings.lost_noise_gain if tr.lost else 1.0)
        self.t_prev = t
        st = FrameStats(self.frame, t, skipped=why, lost=self.lost, map_size=self.state.n_features)
        self.stats.append(st)
        return st

    def contrast_floor(self, g: np.ndarray) -> float:
        """The contrast a new feature's template needs to be matched through this camera's noise
        (corners.min_template_std); the noise is estimated from the image every
        ``noise_every`` frames, since the exposure's gain moves it slowly."""
        if self._noise is None or self.frame - self._noise[0] >= self.settings.noise_every:
            self._noise = (self.frame, noise_sigma(g))
        return min_template_std(self._noise[1], self.settings.match_score)

    def stay_in_view(self, x_v: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(k,) bool: whether each pixel's point (at 1 m) is still inside the image, ``margin_px``
        in, after 0.6 s of the motion model's constant velocity (MonoSLAM places new features
        where the motion will keep them in view)."""
        rays = unproject(self.cam, uv)
        X = x_v[:3] + (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ quat_to_rotation(x_v[3:7]).T
        x_next, _ = f_and_dfdx(x_v, 0.6)
        uv_next = project_points(self.cam, (X - x_next[:3]) @ quat_to_rotation(x_next[3:7]))
        return in_image(self.cam, uv_next, margin=self.settings.margin_px)      # NaN: outside
