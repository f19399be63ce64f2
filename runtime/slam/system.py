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
map's own frame; a saved map (map_io.py) starts a session lost, re-localising. A track that
drifted without being lost is put back at the target.

:class:`MonoSLAM` is the facade; behind it, one :class:`track.Track` per start-up hypothesis
orders the parts, each taking what it needs explicitly:

- views.py: the map and its queries (SlamMap: state, features, rays, last search; views, first
  views, world points, covariances);
- measure.py: measurement and update (select, active search, target corners by their sides,
  1-point RANSAC and the EKF update);
- mapping.py: map management (delete, convert, add, plane normals, particle rays);
- reacquire.py: target watching and re-acquisition (near its prediction, over the whole image);
- relocalisation.py: a lost camera found again in its map;
- impulses.py: impulse adaptation (the constant-velocity model's impulses through a turn);
- inertial.py, motion.py: the IMU and constant-velocity predictions;
- state.py over layout.py: the state, written through one door; prior.py: the camera's prior;
- records.py: the tracking status, per-frame statistics, the map's snapshot for displays.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import replace

import numpy as np

from kinematics.camera import CameraIntrinsics

from ..sequence import Target
from .config import DEFAULT_CONFIG, MapSettings, SlamConfig
from .corners import grey
from .features import FEATURE_NAMES, INVERSE_DEPTH, POINT, inverse_depth
from .imu_handover import ImuHandover
from .inertial import ImuStream, StillBiases, predict_imu, still_biases
from .mapping import FeatureIds, ImageNoise, cap_victims, stay_in_view
from .prior import camera_prior, pose_covariance, restart_at
from .quaternion import quat_from_rotation, quat_to_rotation
from .records import FrameStats, MapView, SearchView, TrackingStatus
from .appearance import extract_template
from .startup import PoseHypothesis, RefinedTarget, SlamStartError, print_contrast, start_hypotheses
from .filter import FeatureNotMeasurable
from .state import (CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_SCALED, CAMERA_DIM_TIMED, TD_INDEX, SlamNumericalError,
                    State)
from .appearance import first_view_patch, patch_half
from .map_feature import MapFeature
from .track import Track
from .views import SlamMap, warped

__all__ = ["MonoSLAM", "FrameStats", "MapSettings", "MapView", "SearchView", "SlamStartError", "MapFeature",
           "TrackingStatus", "Track", "cap_victims", "NARROW_WIDTH_PX"]

#: Images narrower than this convert inverse-depth features at ``linearity_threshold_narrow``:
#: keeping them in inverse depth longer halves the walks' drift from 480 px wide, but at 320 it
#: gains nothing measurable and its larger state costs 13% of the frame rate (benchmarks/NOTES.md).
NARROW_WIDTH_PX = 480


class MonoSLAM:
    """Single-camera EKF SLAM over a sequence of images (see the module docstring).

    camera : the intrinsics and lens model. cfg, settings : the filter's and the map's
    parameters. imu : whether an IMU will drive the prediction (then, with
    ``settings.imu.imu_biases``, the camera block carries bias states). seed : the RANSAC's random
    order (per frame), so a run is repeatable.
    """

    def __init__(self, camera: CameraIntrinsics, cfg: SlamConfig = DEFAULT_CONFIG, settings: MapSettings = MapSettings(),
                 imu: bool = False, seed: int = 0):
        self.cam = camera
        self.cfg = cfg
        self.settings = settings
        self.seed = seed
        self.use_imu = bool(imu) and settings.imu.use_imu
        self.cam_dim = CAMERA_DIM
        if self.use_imu and settings.imu.imu_biases:
            self.cam_dim = CAMERA_DIM_TIMED if settings.imu.imu_time_offset else CAMERA_DIM_BIASED
        # Templates and distances scale with the image (15 px at 640 px wide).
        t = int(round(settings.measure.template_px * camera.width / 640.0))
        self.template_px = max(t + (1 - t % 2), 7)
        self._tracks: list[Track] = []
        self.ids = FeatureIds()
        self.frame = -1
        self.t_prev: float | None = None
        self.stats: list[FrameStats] = []
        self.imu = ImuStream(settings)
        self.messages: list[str] = []      # what the console should say (IMU problems, ...)
        d = settings.deletion
        # Imported here: scipy.stats takes ~0.7 s to import, and every `wvr` command imports this module.
        from scipy.stats import chi2
        self.nis_limit = float(chi2.ppf(d.consistency_confidence, 2 * d.consistency_window))
        self.linearity_threshold = (settings.inverse_depth.linearity_threshold if camera.width >= NARROW_WIDTH_PX
                                    else settings.inverse_depth.linearity_threshold_narrow)
        self.refined_target: RefinedTarget | None = None
        self.target_contrast = 0.0              # the target's print contrast in the first image
        self.still: StillBiases | None = None    # the biases a still stretch before the start gave
        self.noise = ImageNoise(settings.measure.noise_every, settings.views.match_score)
        self.scale_source = "target"            # what fixed the map's unit: target, map, depth, imu or arbitrary
        self.handover: ImuHandover | None = None   # a natural start's map waiting for the IMU (imu_handover.py)

    # -------------------------------------------------------------- views
    @property
    def track(self) -> Track:
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

    @property
    def status(self) -> TrackingStatus:
        """The tracking status after the last frame (INITIALISING before the start)."""
        return self.track.status if self._tracks else TrackingStatus.INITIALISING

    def new_id(self) -> int:
        return self.ids.new()

    def warped(self, f: MapFeature) -> bool:
        """Whether the feature's template is predicted through its plane (MapSettings.warp)."""
        return warped(self.settings.warp, f)

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
        tr = self.track
        state = tr.state
        Y = tr.world_points()
        n = state.n_features
        cov = tr.map.point_covariances(np.arange(n))
        r_ids, r_o, r_d, r_depth = [], [], [], []
        for k in range(n):
            sl = state.feature_slice(k)
            P = state.P[sl, sl]
            if state.kinds[k] == INVERSE_DEPTH:
                y = state.feature(k).copy()
                y[5] = max(y[5], 0.05)
                m = state.anchors[k] @ inverse_depth.direction_kernel(float(y[3]), float(y[4]))[0]
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
            kinds=tuple(FEATURE_NAMES[k] for k in state.kinds), known=np.array([f.known for f in tr.features], bool),
            ray_ids=np.array(r_ids, int), ray_origin=np.array(r_o).reshape(-1, 3),
            ray_direction=np.array(r_d).reshape(-1, 3), ray_depth=np.array(r_depth, float).reshape(-1, 2),
            search=tr.last)

    # -------------------------------------------------------------- start-up
    def _camera_state(self, hyp: PoseHypothesis, t: float, gyro_bias=None, gyro_bias_sigma: float = 0.0,
                      upright: bool = True) -> State:
        """A state of the camera alone at the start-up pose ``hyp``; with bias states, the biases
        a still stretch before the first frame gave (kept in ``still``; only in an ``upright``
        world, whose gravity is known), the gyro's replaced by ``gyro_bias`` (3,) rad/s with
        standard deviation ``gyro_bias_sigma`` where a start gives it."""
        q = quat_from_rotation(hyp.R_world_cam)
        still = None
        if self.cam_dim >= CAMERA_DIM_BIASED and upright:
            still = still_biases(self.imu.rows, t, q, self.settings, self.cfg)
            if still is not None:
                self.still = still
        x_v, P = camera_prior(self.cam_dim, hyp.r, q, pose_covariance(q, hyp.cov), self.settings.startup.init_sigma_v,
                              self.settings.startup.init_sigma_w, self.cfg, still, gyro_bias, gyro_bias_sigma)
        return State.from_camera(x_v, P)

    def restart_camera(self, state: State, hyp: PoseHypothesis, w: np.ndarray | None = None) -> None:
        """Put the camera at a pose found against the map (re-localisation), at rest (or turning
        at ``w`` (3,), rad/s), with no correlation to the map; bias estimates are kept."""
        restart_at(state, hyp, self.settings.startup.init_sigma_v, self.settings.startup.init_sigma_w, w)

    def _new_track(self, state: State, features: list[MapFeature], localised: bool = True) -> Track:
        return Track(SlamMap(state, features), self.cam, self.cfg, self.settings, seed=self.seed,
                     template_px=self.template_px, linearity_threshold=self.linearity_threshold,
                     nis_limit=self.nis_limit, ids=self.ids, noise=self.noise, target=self.refined_target,
                     target_contrast=self.target_contrast, localised=localised)

    def start(self, image: np.ndarray, t: float, target: Target) -> RefinedTarget:
        """Fix the world frame from the known target in the first image: its clicked pixels are
        refined on the image, its pose (and the planar ambiguity's second pose when it explains
        the corners nearly as well) found with its covariance, and its points inserted as
        features. Returns the refined target. Raises :class:`SlamStartError`."""
        g = grey(image)
        s = self.settings.startup
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
            self._tracks.append(self._new_track(state, feats))
        if self.still is not None:
            self.messages.append(f"slam: IMU biases from the {self.still.seconds:.1f} s still before the first frame "
                                 f"(gyro {np.round(1e3 * self.still.b_g, 2).tolist()} mrad/s)")
        self.ids.next_id = len(ref.xyz)
        self.frame = 0
        self.t_prev = t
        self.stats.append(FrameStats(0, t, matched=len(ref.xyz), map_size=len(ref.xyz), hypotheses=len(self._tracks)))
        self._warm_up(g, t)
        return ref

    def start_natural(self, image: np.ndarray, t: float, ns) -> None:
        """Start from natural features (natural_start.NaturalStart of this frame): the camera at
        the start's pose (by default the world's origin: the first camera's frame is the world's),
        fixed (the gauge), the start's
        points mapped as point features with their covariances, its velocity the two views'. No
        target: nothing is watched for or sought again but the map."""
        g = grey(image)
        T = np.eye(4) if ns.T_world_cam is None else np.asarray(ns.T_world_cam, float)
        R_wc, r = T[:3, :3].copy(), T[:3, 3].copy()
        hyp = PoseHypothesis(R_wc, r, np.zeros((6, 6)), 0.0, 0.0)
        self.handover = None
        if ns.scale == "arbitrary" and self.use_imu and self.settings.imu.imu_handover:
            # The map's unit and its frame's gravity are the IMU's to find: camera only until then.
            self.cam_dim = CAMERA_DIM_SCALED
            self.handover = ImuHandover(self.settings)
        # A map waiting for the IMU's hand-over is in the first camera's frame, whose gravity a
        # still stretch cannot be read against (the head-motion start's frame is upright).
        state = self._camera_state(hyp, t, ns.gyro_bias, ns.gyro_bias_sigma, upright=self.handover is None)
        if state.has_time_offset and not self.settings.imu.imu_time_offset:
            state.P[TD_INDEX, TD_INDEX] = 0.0
        state.x[7:10] = ns.v_world
        ph = patch_half(self.template_px)
        feats = []
        for X, C, uv in zip(ns.xyz, ns.xyz_cov, ns.uv):
            tpl = extract_template(g, uv, self.template_px)
            if tpl is None or float(np.std(tpl)) <= 2.0:
                continue
            state.add_feature(POINT, X, C, np.zeros((3, state.n)))
            feats.append(MapFeature(len(feats), tpl, 0, r.copy(), patch=first_view_patch(g, uv, ph),
                                    uv0=np.asarray(uv, float), R0=R_wc.copy(), normal=(r - X) / np.linalg.norm(r - X),
                                    last_seen=0))
        if len(feats) < 3:
            raise SlamStartError("the natural start's points have no usable appearance (a blank view)")
        self.refined_target = None
        if ns.scale == "arbitrary":
            # Two views' points hold the map's scale loosely, and a new feature's prior narrower
            # than the depths it may have (far nearer than any it matches) drags that scale.
            idp = self.settings.inverse_depth
            self.settings = replace(self.settings, inverse_depth=replace(
                idp, scene_relative_width=idp.two_view_relative_width))
        self._tracks = [self._new_track(state, feats)]
        self.scale_source = ns.scale
        self.ids.next_id = len(feats)
        self.frame = 0
        self.t_prev = t
        self.stats.append(FrameStats(0, t, matched=len(feats), map_size=len(feats), hypotheses=1))
        self._warm_up(g, t)

    def start_from_map(self, saved, t: float) -> None:
        """Start from a saved map (map_io.SavedMap) with the camera unknown: the track begins
        lost and re-localises against the map at every frame until it is found, then continues
        in the map's world frame."""
        state = saved.state_with_camera(self.cam_dim, self.cfg)
        # Made before this session's frame 0: the target's re-acquisition keeps them as the map
        # from before a loss, and the cap's order sees them as seen longest ago.
        feats = [replace(f, attempts=0, successes=0, rays0=None, first_frame=0, last_seen=0) for f in saved.features]
        # The map's known points are the target it was started from: placed by the print's sides,
        # watched for and sought again as after a start from the target (no pixels: no clicks).
        known = SlamMap(state, feats).known_in_id_order()
        self.refined_target = None
        if len(known) == 4:
            xyz = np.array([state.feature(k)[:3] for k in known])
            self.refined_target = RefinedTarget(xyz, np.full((4, 2), np.nan), np.zeros(4))
        self._tracks = [self._new_track(state, feats, localised=False)]
        self.ids.next_id = max((f.id for f in feats), default=-1) + 1
        self.frame = 0
        self.t_prev = t
        # A map made with no metre (a natural start with nothing to scale it) stays without one.
        self.scale_source = "arbitrary" if saved.scale == "arbitrary" else "map"
        self.stats.append(FrameStats(0, t, map_size=len(feats), lost=True))

    # -------------------------------------------------------------- per frame
    def add_imu(self, rows) -> None:
        """Queue IMU rows (k, 7) ``[t, wx, wy, wz, ax, ay, az]`` (camera frame, imu.txt) in time
        order; bad samples are dropped, counted and said (``messages``)."""
        if not self.settings.imu.use_imu:
            return
        for msg in self.imu.add(rows):
            self.messages.append(msg)

    def process(self, image: np.ndarray, t: float, imu=None) -> FrameStats:
        """One frame at time t (s); ``imu`` : optional IMU rows since the last frame."""
        t0, c0 = time.perf_counter(), time.thread_time()
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
            tr.step(g, t_prev, t, rows, st, self.frame, self.imu.covered_until)
            st.lost = tr.lost
            st.map_size = tr.state.n_features
            stats.append(st)
        self._drop_imu(t)
        self._decide()
        st = stats[0] if len(self._tracks) == len(stats) else stats[self._winner]
        st.hypotheses = len(self._tracks)
        if self.handover is not None:
            self._hand_over(t)
            st.map_units_per_m = self.state.k if self.handover.done is not None else None
        st.seconds = time.perf_counter() - t0
        st.cpu_seconds = time.thread_time() - c0
        self.stats.append(st)
        return st

    def _warm_up(self, g: np.ndarray, t: float) -> None:
        """One frame tracked on a copy of the first track, the start's own image again, then
        thrown away: the compiled kernels a frame uses are loaded (from numba's cache) here, at the
        start, instead of stalling the first tracked frame (200-300 ms on EuRoC). Nothing of the
        copy is kept; a failure on it is left for the real frames to meet."""
        if not self._tracks:
            return
        trial = copy.deepcopy(self._tracks[0])
        try:
            trial.step(g, t, t + 1e-3, None, FrameStats(1, t + 1e-3), 1, self.imu.covered_until)
            if self.awaiting_imu:
                # And the inertial prediction's, which the hand-over would otherwise load mid-run.
                predict_imu(trial.state, np.array([[t, 0.0, 0.0, 0.0, 0.0, 0.0, 9.81]]), t, t + 1e-3, self.cfg)
        except (SlamNumericalError, FeatureNotMeasurable, ValueError, np.linalg.LinAlgError):
            pass

    def finish(self) -> None:
        """Wait for the checks running beside the tracker (track.Track.covariance), raising a
        failure they found."""
        for tr in self._tracks:
            tr.covariance.wait()

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
        su = self.settings.startup
        if gap > 2 * math.log(su.ambiguity_ratio) or self.frame >= su.ambiguity_frames:
            self._winner = best
            self._tracks = [self._tracks[best]]
            self.messages.append(f"slam: planar target ambiguity resolved at frame {self.frame} "
                                 f"(log-likelihood ratio {gap:.1f}, pose {best})")

    @property
    def awaiting_imu(self) -> bool:
        """Whether a natural start's map waits to be handed to the IMU (imu_handover.py)."""
        return self.handover is not None and self.handover.done is None

    def _hand_over(self, t: float) -> None:
        """Give a natural start's map to the IMU once its scale is observed (imu_handover.py)."""
        if not self.awaiting_imu or self.lost or not self.localised:
            return
        st = self.state
        e = self.handover.add(t, st.r, quat_to_rotation(st.q), self.imu.rows)
        if e is None:
            return
        h = self.handover.hand_over(st, e)
        self.scale_source = "imu"
        self.messages.append(f"slam: the IMU takes the map at frame {self.frame}, {h.seconds:.1f} s after the start: "
                             f"{e.scale:.4g} m per map unit (+- {100 * e.sigma_rel:.1f}%, the camera's acceleration "
                             f"{e.excitation:.2f} m/s^2 RMS); the filter refines it from here")

    def _imu_rows(self, t_prev: float, t: float):
        """The IMU rows covering every track's prediction to the frame at ``t`` (None: not
        covered, no IMU, or a natural start's map not yet handed to it)."""
        if not (self.settings.imu.use_imu and len(self.imu.rows)):
            return None
        if self.awaiting_imu:
            return None
        spans = [tr.span(t_prev, t) for tr in self._tracks] or [(t_prev, t)]
        return self.imu.covering(min(a for a, _ in spans), max(b for _, b in spans))

    def _drop_imu(self, t: float) -> None:
        if self.awaiting_imu:
            return                              # the hand-over's estimate needs every sample since the start
        self.imu.drop_before(t + min([0.0] + [tr.state.t_ref for tr in self._tracks]))

    def skip(self, t: float, why: str) -> FrameStats:
        """A frame that could not be read: predict through it, count it."""
        self.frame += 1
        rows = self._imu_rows(self.t_prev, t)
        for tr in self._tracks:
            gain = self.settings.relocalisation.lost_noise_gain if tr.lost else 1.0
            tr.propagate(self.t_prev, t, rows, gain, self.imu.covered_until)
        self.t_prev = t
        st = FrameStats(self.frame, t, skipped=why, lost=self.lost, map_size=self.state.n_features)
        self.stats.append(st)
        return st

    def contrast_floor(self, g: np.ndarray) -> float:
        """The contrast a new feature's template needs to be matched through this camera's noise
        (mapping.ImageNoise)."""
        return self.noise.contrast_floor(g, self.frame)

    def stay_in_view(self, x_v: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(k,) bool: whether each pixel's point (at 1 m) is still inside the image, ``margin_px``
        in, after 0.6 s of the motion model's constant velocity (mapping.stay_in_view)."""
        return stay_in_view(self.cam, self.settings.views.margin_px, x_v, uv)
