"""One filter and its map through a frame (MonoSLAM's loop): predict, select and measure, update,
delete, add; with the lost track's relocalisation, the target's re-acquisition and the impulses'
adaptation around it. The parts are in their own modules; this one only orders them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from kinematics.camera import CameraIntrinsics

from .config import MapSettings, SlamConfig
from .covariance_watch import CovarianceWatch
from .filter import FrameUpdate
from .impulses import ImpulseAdapter
from .inertial import predict_imu
from .layout import W_SLICE
from .mapping import FeatureIds, ImageNoise, MapManager
from .measure import Measurement
from .motion import predict as predict_cv
from .prior import restart_at
from .reacquire import TargetWatch
from .records import FrameStats, SearchView, TrackingStatus
from .relocalisation import Relocaliser
from .startup import PoseHypothesis, RefinedTarget
from .state import SlamNumericalError, State
from .map_feature import MapFeature
from .views import SlamMap


class Track:
    """One filter and its map (:class:`SlamMap`) with its parts: measurement, map management,
    target watching, relocalisation and impulse adaptation; ``score`` : the evidence for its
    start-up hypothesis (a log-likelihood); ``low_matches`` : frames in a row with fewer than 3
    inliers; ``status`` : :class:`TrackingStatus` after the last frame."""

    def __init__(self, map_: SlamMap, cam: CameraIntrinsics, cfg: SlamConfig, settings: MapSettings, *, seed: int,
                 template_px: int, linearity_threshold: float, nis_limit: float, ids: FeatureIds, noise: ImageNoise,
                 target: RefinedTarget | None, target_contrast: float, localised: bool = True):
        self.map = map_
        self.cfg, self.settings = cfg, settings
        self.measurement = Measurement(cam, settings, cfg.sigma_pixel, seed, target)
        self.mapping = MapManager(cam, settings, cfg.sigma_pixel, template_px, linearity_threshold, nis_limit, ids,
                                  noise)
        self.watch = TargetWatch(cam, settings, target, target_contrast, cfg.sigma_pixel)
        self.relocaliser = Relocaliser(cam, settings, cfg.sigma_pixel)
        self.impulses = ImpulseAdapter(cfg)
        self.low_matches = 0 if localised else settings.relocalisation.lost_after
        self.status = TrackingStatus.TRACKING if localised else TrackingStatus.INITIALISING
        self.score = 0.0
        self.covariance = CovarianceWatch()     # the full PSD check, beside the tracker

    # -- the map's pieces, as the facade and its callers name them --
    @property
    def state(self) -> State:
        return self.map.state

    @property
    def features(self) -> list[MapFeature]:
        return self.map.features

    @property
    def rays(self) -> list:
        return self.map.rays

    @property
    def last(self) -> SearchView | None:
        return self.map.last

    @property
    def lost(self) -> bool:
        return self.low_matches >= self.settings.relocalisation.lost_after

    @property
    def localised(self) -> bool:
        """Whether the camera has been localised in the map (a saved map's session: not until its
        first re-localisation)."""
        return self.status is not TrackingStatus.INITIALISING

    def world_points(self) -> np.ndarray:
        return self.map.world_points()

    def span(self, t_prev: float, t: float) -> tuple[float, float]:
        """The prediction's interval on the IMU's clock for the frame at camera time ``t``: from
        where the camera block stands to ``t`` plus the clock offset's estimate."""
        if not self.state.has_time_offset:
            return t_prev, t
        t0 = t_prev + self.state.t_ref
        return t0, max(t + self.state.t_d, t0)

    # ------------------------------------------------------------------ one frame
    def propagate(self, t_prev: float, t: float, imu_rows, noise_gain: float, covered_until: float = np.inf) -> bool:
        """The camera block to the frame at camera time ``t``, through the IMU rows when they
        cover it (True; ``covered_until`` : the time up to which they describe the motion),
        else by the constant-velocity model."""
        t0, t1 = self.span(t_prev, t)
        self.state.t_ref = t1 - t
        if imu_rows is not None:
            try:
                predict_imu(self.state, imu_rows, t0, t1, self.cfg, noise_gain=noise_gain, covered_until=covered_until)
                return True
            except (SlamNumericalError, ValueError):
                pass
        predict_cv(self.state, t1 - t0, self.impulses.motion_cfg, noise_gain=noise_gain)
        return False

    def step(self, g: np.ndarray, t_prev: float, t: float, imu_rows, st: FrameStats, frame: int,
             covered_until: float = np.inf) -> None:
        """One frame ``g`` at camera time ``t`` (the last at ``t_prev``), counted in ``st``."""
        s = self.settings
        lost = self.lost
        onset = self._predict(t_prev, t, imu_rows, st, lost, covered_until)
        if lost:
            # Lost: the map is frozen; the pose is sought again by whole-image matches and by
            # the active search in the grown ellipses; either must be confirmed by the active
            # search's inliers, else the frame leaves no trace.
            records = [(f.attempts, f.successes, f.drift) for f in self.features]
            saved = self.state.snapshot()
            st.relocalised = self._relocalise(g)
        if s.warp != "known" and frame % s.normals.normals_every == 0:
            self.mapping.normals_from_map(self.map)     # neighbours' planes change slowly: every few frames
        closed = not lost and self._close_loop(g, st, frame)
        if not closed:
            self._measure_with_onset(g, t_prev, t, st, frame, lost, onset)
        if lost:
            if not self._confirmed(st):
                self._roll_back(saved, records, st)
                return
        elif s.reacquire.reacquire_after > 0 and not closed:
            self._watch_target(g, st, frame)
        if s.normals.normals_per_frame > 0 and s.warp != "known" and not lost and not closed:
            self.mapping.normals_from_views(g, self.map)     # the matches measured in this frame
        self._delete(g, st, frame)
        # MonoSLAM adds features when too few are actually observed (matched), not predicted.
        if st.matched < s.measure.visible_min:
            self.mapping.add(g, self.map, st, frame, st.matched)
        if not lost:
            self.impulses.adapt(t, self.state)
        if frame % self.cfg.guard.psd_check_every == 0:
            self.covariance.submit(self.state, f"frame {frame}", self.cfg.guard.psd_rel_tol)
        self.covariance.raise_if_failed()
        self.low_matches = self.low_matches + 1 if st.matched < 3 else 0
        self.status = (TrackingStatus.RELOCALISED if lost else TrackingStatus.LOST if self.lost
                       else TrackingStatus.RECENTLY_LOST if self.low_matches else TrackingStatus.TRACKING)

    # ------------------------------------------------------------------ the loop's steps
    def _predict(self, t_prev: float, t: float, imu_rows, st: FrameStats, lost: bool, covered_until: float):
        """The prediction, and before it the camera's mean and rows of P (all a prediction
        changes) while a turn may begin in this frame (SlamConfig.impulses.adapt_onset)."""
        cfg, imp = self.cfg, self.impulses
        if lost:
            imp.reset()              # lost, the prior: nothing says how the camera moves now
        st.sigma_a, st.sigma_alpha = imp.motion_cfg.motion.sigma_a, imp.motion_cfg.motion.sigma_alpha
        before = (self.state.snapshot(camera_only=True)
                  if cfg.impulses.adapt_onset and not lost and imp.adapting(t_prev) and imp.at_priors else None)
        gain = self.settings.relocalisation.lost_noise_gain if lost else 1.0
        st.imu = self.propagate(t_prev, t, imu_rows, gain, covered_until)
        return before

    def _measure(self, g: np.ndarray, st: FrameStats, frame: int, retry_dt: float | None = None,
                 accept: Callable[[FrameUpdate], bool] | None = None) -> bool:
        """Search, RANSAC and update (measure.Measurement.measure); False when ``accept`` refused
        the updates."""
        ok, evidence = self.measurement.measure(g, self.map, st, frame, self.impulses.motion_cfg, retry_dt, accept)
        self.score += evidence
        return ok

    def _measure_with_onset(self, g, t_prev: float, t: float, st: FrameStats, frame: int, lost: bool, before) -> None:
        """The frame measured; if its update starts a turn (``before``: the state before the
        prediction, kept for this), predicted and measured again with the turn's impulses."""
        turn: list = []
        check = before is not None and not st.imu
        accept = (lambda fu: not self.impulses.turn_began(t, fu, turn)) if check else None
        if not self._measure(g, st, frame, retry_dt=None if lost or st.imu else t - t_prev, accept=accept):
            # The prior impulses took the turn's unforeseen start partly as translation.
            self.state.restore(before)
            self.impulses.set(*turn)
            st.onset, st.retried = True, False
            turned = self.impulses.motion_cfg.motion
            st.sigma_a, st.sigma_alpha = turned.sigma_a, turned.sigma_alpha
            self.propagate(t_prev, t, None, 1.0)
            self._measure(g, st, frame, retry_dt=t - t_prev)

    def _relocalise(self, g: np.ndarray) -> bool:
        """Every ``reloc_every`` lost frames (every frame before the first localisation): the
        camera restarted at a pose found against the map (relocalisation.Relocaliser)."""
        s = self.settings
        every = 1 if not self.localised else s.relocalisation.reloc_every
        if (self.low_matches - s.relocalisation.lost_after) % every != 0:
            return False
        hyp = self.relocaliser.relocalise(g, self.map)
        if hyp is None:
            return False
        restart_at(self.state, hyp, s.startup.init_sigma_v, s.startup.init_sigma_w)
        return True

    def _confirmed(self, st: FrameStats) -> bool:
        """Whether a lost frame's pose is confirmed by the active search's inliers."""
        rl = self.settings.relocalisation
        return not st.matched < max(rl.reloc_min_confirmed, rl.reloc_confirm_fraction * st.searched)

    def _roll_back(self, saved, records: list, st: FrameStats) -> None:
        """A lost frame not confirmed: the state and the features' records as before it."""
        self.state.restore(saved)
        for f, (a, b, d) in zip(self.features, records):
            f.attempts, f.successes, f.drift = a, b, d
        st.relocalised = False
        st.matched = st.rescued = 0
        self.low_matches += 1

    def _delete(self, g: np.ndarray, st: FrameStats, frame: int) -> None:
        """Particle rays refined and promoted, or inverse-depth features converted; then the
        deletion rules and the size cap (mapping.MapManager)."""
        if self.settings.features == "particles":
            self.mapping.refine_rays(g, self.map, st, frame)
            self.mapping.delete(self.map, st, frame)
        else:
            self.mapping.delete(self.map, st, frame, self.mapping.conversions(self.map, st))

    def _close_loop(self, g: np.ndarray, st: FrameStats, frame: int) -> bool:
        """The target unmatched for ``loop_after`` frames: sought over the whole image every
        ``loop_every`` frames (reacquire.TargetWatch.close_loop); found and confirmed, the camera
        is restarted there and the frame measured. Returns whether it was."""
        s = self.settings
        away = frame - self.watch.target_seen
        if not (s.reacquire.reacquire_after > 0 and s.reacquire.loop_after > 0 and away >= s.reacquire.loop_after
                and (away - s.reacquire.loop_after) % s.reacquire.loop_every == 0):
            return False
        hyp = self.watch.close_loop(g, self.map)
        if hyp is None:
            return False
        self._restart_at_target(hyp, st, frame)
        self._measure(g, st, frame)
        return True

    def _watch_target(self, g: np.ndarray, st: FrameStats, frame: int) -> None:
        """The target's corners predicted in view and missed: sought near their prediction
        (reacquire.TargetWatch.watch) and the camera put back there."""
        hyp = self.watch.watch(g, self.map, frame)
        if hyp is not None:
            self._restart_at_target(hyp, st, frame)

    def _restart_at_target(self, hyp: PoseHypothesis, st: FrameStats, frame: int) -> None:
        """The camera put back at the target's pose ``hyp`` (of a planar pair, the one the
        caller chose), and the features first seen since the target was last matched, placed
        from the drifting poses, removed. A turn goes on (the templates often miss in one): the
        filter's angular velocity, which the drift leaves nearly right, is a better guess than
        rest; its linear velocity is the drift's own and is reset with the pose."""
        s = self.settings
        restart_at(self.state, hyp, s.startup.init_sigma_v, s.startup.init_sigma_w, w=self.state.x[W_SLICE].copy())
        drifted = self.watch.drifted(self.map)
        if drifted:
            self.map.remove(drifted, st)
        st.reacquired = True
        self.watch.restarted(frame)
