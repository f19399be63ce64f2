"""Measurement and update: the features to measure this frame (predicted visible, spread over
the image), their active search, the target's corners placed by its sides, and the 1-point
RANSAC's EKF update with its record in each feature."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from kinematics.camera import CameraIntrinsics

from .config import MapSettings, SlamConfig
from .filter import FrameUpdate, innovation_covariances, innovation_nis
from .guided import guided_regions
from .appearance import match_features
from .measurement import Prediction, predict, predict_uv
from .motion import f_and_dfdx_dfdn, noise_covariance
from .ransac import one_point_ransac
from .records import FrameStats, SearchView
from .startup import RefinedTarget, corners_by_edges
from .state import State
from .map_feature import MapFeature
from .views import SlamMap, warped

#: Grid over the image for spreading the measured features (columns, rows).
_GRID = (4, 3)


def start_evidence(d2: np.ndarray, used: np.ndarray, known: np.ndarray, gate: float) -> float:
    """A frame's log-likelihood for a track's start-up hypothesis (system.MonoSLAM._decide): over
    the target's known points only, ``-0.5 sum min(d2, gate)``, a point searched but not used (a
    miss or an outlier) costing the gate. d2, used, known : (n,) each searched feature's prior
    innovation NIS, whether its match updated the filter, whether it is the target's.

    The known points are the data both hypotheses measure alike. Each track's own natural
    features were placed from its own pose, so they fit it either way, and their misses (each
    track's own) differ by chance: counted, one miss more (half the gate, 4.6) outweighed the
    decisive gap (log 16, 2.8) while nothing yet told the poses apart (a still head)."""
    d = np.where(np.asarray(used, bool), np.minimum(np.asarray(d2, float), gate), gate)
    return -0.5 * float(d[np.asarray(known, bool)].sum())


class Measurement:
    """One track's measurement. cam, settings : the camera and the map's settings; sigma_pixel :
    a match's standard deviation, px; seed : the RANSAC's random order (per frame); target : the
    known target (its corners are placed by its sides, ``known_edges``) or None."""

    def __init__(self, cam: CameraIntrinsics, settings: MapSettings, sigma_pixel: float, seed: int,
                 target: RefinedTarget | None):
        self.cam, self.settings, self.sigma_pixel = cam, settings, float(sigma_pixel)
        self.seed, self.target = seed, target
        self.guided = 0             # features the last search guided (search)
        # The search cap grows with the image above 640 px width (an ellipse's area goes as the
        # focal length squared); smaller images keep it.
        self.search_cap_px = settings.views.max_search_area_px * max(1.0, (cam.width / 640.0) ** 2)
        # The rescue's guides may be larger (_rescue_guides).
        self.rescue_cap_px = max(self.search_cap_px, settings.measure.rescue_area_px * (cam.width / 640.0) ** 2)
        self.over_cap = 0           # guides the last search took over the search cap (select)
        self.outgrown = 0           # features the last search chose and did not search (_match)
        self._rescue: np.ndarray | None = None   # those guides' indices into select's features

    def select(self, m: SlamMap) -> tuple[Prediction, np.ndarray, np.ndarray, int, np.ndarray]:
        """The features to measure this frame, their innovation covariances and noise (multiples
        of the pixel noise: (m,), or (m, 2, 2) shaped by each template's gradients with
        ``aperture_noise``), how many are predicted visible, and their points (m, 3).

        A feature is searchable while its 3-sigma ellipse's area is within the search cap; the
        search itself takes an ellipse while the box around it is (``_match``). One between the
        two is chosen, not searched, and its search counts as failed (``outgrown``)."""
        s, cam = self.settings, self.cam
        state = m.state
        ks = np.arange(state.n_features)
        if not len(ks):
            empty = predict(state, ks, cam)
            return empty, np.zeros((0, 2, 2)), np.zeros(0), 0, np.zeros((0, 3))
        pred = predict(state, ks, cam)
        Y = m.world_points()
        ok, r_scale = m.views(pred, Y, cam, s, self.sigma_pixel)
        sel = np.flatnonzero(ok)
        r_scale = r_scale[sel]
        if s.drift.drift_gain > 0:
            sig2 = self.sigma_pixel ** 2
            r_scale = r_scale * np.array([m.features[k].drift_variance_scale(s.drift.drift_gain, sig2) for k in sel])
        if s.drift.aperture_noise:
            r_scale = r_scale[:, None, None] * m.noise_shapes(sel)
        pred = pred.take(sel)
        m.in_view_ids = {m.features[k].id for k in pred.ks}
        S = innovation_covariances(state, pred, self.sigma_pixel**2, r_scale)
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        area = 9 * math.pi * np.sqrt(np.maximum(det, 0))   # the 3-sigma ellipse, px^2
        searchable = np.isfinite(area) & (area <= self.search_cap_px)
        visible = int(len(sel))
        idx = np.flatnonzero(searchable)
        rescue = self._rescue_guides(area, searchable)
        if rescue is not None:
            # Every ellipse goes on: the guides' matches narrow the rest's (search).
            idx = np.union1d(idx, np.flatnonzero(np.isfinite(area)))
        if len(idx) > s.measure.measure_max:
            # The most reliable first (MapFeature.reliability), the most uncertain among equals,
            # spread over the image.
            feats = [m.features[k] for k in pred.ks[idx]]
            reliability = np.array([f.reliability for f in feats])
            priority = reliability + 1e-6 * np.log(np.maximum(det[idx], 1e-12))
            known = np.array([f.known for f in feats], bool)
            if rescue is not None:
                known |= np.isin(idx, rescue)           # the guides are kept, as the target's points are
            idx = self._spread(pred.uv[idx], priority, known, s.measure.measure_max, idx)
        self._rescue = None if rescue is None else np.flatnonzero(np.isin(idx, rescue))
        self.over_cap = 0 if rescue is None else int(np.count_nonzero(~searchable[idx[self._rescue]]))
        pred = pred.take(idx)
        return pred, S[idx], r_scale[idx], visible, Y[pred.ks]

    def _rescue_guides(self, area: np.ndarray, searchable: np.ndarray) -> np.ndarray | None:
        """When most of the predicted features' 3-sigma ellipses (``area``, px^2) and all but
        fewer than ``guide_first`` are over the search cap (the camera's own motion uncertain: a
        start's or re-localisation's unknown velocity at a low frame rate, a long focal length;
        not a few young features' depths), the guides: those under it and the smallest others up
        to ``rescue_area_px`` (at 640 px width), ``guide_first`` in all; None otherwise. Without
        them no feature would be searched and the track would be lost for want of looking."""
        g = self.settings.measure
        n_ok = int(np.count_nonzero(searchable))
        if g.guide_first <= 0 or n_ok >= g.guide_first or 2 * n_ok >= np.count_nonzero(np.isfinite(area)):
            return None
        over = np.flatnonzero(np.isfinite(area) & ~searchable & (area <= self.rescue_cap_px))
        if not len(over):
            return None
        take = over[np.argsort(area[over], kind="stable")][:g.guide_first - n_ok]
        return np.union1d(np.flatnonzero(searchable), take)

    def _spread(self, uv: np.ndarray, priority: np.ndarray, known, n: int, idx: np.ndarray) -> np.ndarray:
        """``n`` of the candidates ``idx``: the target's points first, then round-robin over a
        grid of image cells, the highest ``priority`` first."""
        cam = self.cam
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

    def search(self, g: np.ndarray, m: SlamMap) -> tuple[Prediction, np.ndarray, np.ndarray, int, list, np.ndarray]:
        """The features chosen this frame (:meth:`select`: prediction, innovation covariances, noise
        scales, how many predicted visible) and their matches in ``g``: z (m, 2) NaN where not
        found."""
        s = self.settings
        pred, S, r_scale, visible, Y = self.select(m)
        self.outgrown = 0
        feats = [m.features[k] for k in pred.ks]
        warp = np.array([warped(s.warp, f) for f in feats], bool)
        rescue = self._rescue
        first = rescue if rescue is not None else self._guides(m, pred, S, feats)
        self.guided = 0
        if first is None:
            z, found = self._match(g, m, feats, warp, Y, pred.uv, S)
            return pred, S, r_scale, visible, feats, z
        # Guided: the first features' matches narrow the rest's regions (guided.py); the update
        # is still made from every match against the prior.
        z = np.full((len(feats), 2), np.nan)
        z[first], _ = self._match(g, m, [feats[i] for i in first], warp[first], Y[first], pred.uv[first], S[first],
                                  self.search_cap_px if rescue is None else self.rescue_cap_px)
        rest = np.setdiff1d(np.arange(len(feats)), first)
        guide = guided_regions(m.state, pred, S, first, z[first], s.ransac, s.measure.guide_floor_px)
        uv_r, S_r = (guide.uv, guide.S) if guide is not None else (pred.uv[rest], S[rest])
        self.guided = len(rest) if guide is not None else 0
        z[rest], _ = self._match(g, m, [feats[i] for i in rest], warp[rest], Y[rest], uv_r, S_r)
        return pred, S, r_scale, visible, feats, z

    def _match(self, g, m: SlamMap, feats: list, warp: np.ndarray, Y: np.ndarray, uv: np.ndarray,
               S: np.ndarray, max_area: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``feats``' matches in ``g`` searched in the ellipses (uv, S) (none larger than
        ``max_area``, px^2; default the search cap): z (m, 2) NaN where not found, and found (m,).
        An ellipse whose box is over ``max_area`` is not searched (its score is inf), counted in
        ``outgrown``."""
        s = self.settings
        z, score, found = match_features(g, feats, warp, Y, m.state.x_v, self.cam, uv, S, s.views.match_score,
                                         self.search_cap_px if max_area is None else max_area)
        self.outgrown += int(np.count_nonzero(np.isinf(score)))
        z[~found] = np.nan
        return z, found

    def _guides(self, m: SlamMap, pred: Prediction, S: np.ndarray, feats: list) -> np.ndarray | None:
        """The features (indices into ``pred``) to search first when the chosen features' search
        ellipses are large on average (MeasureSettings.guide_*): the most reliable, spread over the image;
        None to search all at once."""
        g = self.settings.measure
        n = len(pred.ks)
        if g.guide_first <= 0 or n < g.guide_first + 3:
            return None
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        area = 9 * math.pi * np.sqrt(np.maximum(det, 0))
        # Guiding costs about a millisecond: worth it only where the ellipses are large.
        if not area.mean() > g.guide_area_px * (self.cam.width / 640.0) ** 2:
            return None
        priority = np.array([f.reliability for f in feats]) + 1e-6 * np.log(np.maximum(det, 1e-12))
        return self._spread(pred.uv, priority, [f.known for f in feats], g.guide_first, np.arange(n))

    def measure(self, g: np.ndarray, m: SlamMap, st: FrameStats, frame: int, motion_cfg: SlamConfig,
                retry_dt: float | None = None,
                accept: Callable[[FrameUpdate], bool] | None = None) -> tuple[bool, float]:
        """Search, RANSAC and update for this frame; ``retry_dt`` : the constant-velocity
        prediction's interval, s, when a frame most searches miss may be searched again;
        ``accept`` : shown the updates before they are written (one_point_ransac). False when it
        refused them: the state and the features' records are as they were. Returns whether the
        updates were written and the change of the track's start-up evidence (a log-likelihood)."""
        s, cam = self.settings, self.cam
        pred, S, r_scale, visible, feats, z = self.search(g, m)
        n = len(pred.ks)
        n_found = int(np.isfinite(z).all(axis=1).sum())
        rl = s.relocalisation
        if (retry_dt and rl.retry_noise_gain > 1 and n >= rl.retry_min_searched
                and n_found < rl.retry_found_fraction * n):
            # Most features missed their ellipses: a jerk the constant-velocity model did not
            # allow for (a fast turn's start or stop). The prediction's impulse is taken
            # retry_noise_gain times larger and the frame searched again in the grown ellipses,
            # kept if it finds more (after a long gap the grown ellipses can pass searching).
            first, before = (pred, S, r_scale, visible, feats, z, self.outgrown), m.state.snapshot(camera_only=True)
            self._grow_impulse(m.state, motion_cfg, retry_dt, s.relocalisation.retry_noise_gain)
            pred, S, r_scale, visible, feats, z = self.search(g, m)
            if np.isfinite(z).all(axis=1).sum() > n_found:
                st.retried = True
            else:
                pred, S, r_scale, visible, feats, z, self.outgrown = first
                m.state.restore(before)
            n = len(pred.ks)
        st.predicted = visible
        st.guided = self.guided
        st.over_cap = self.over_cap
        st.outgrown = self.outgrown
        edged = self.known_by_edges(g, feats, z, pred.uv) if s.startup.known_edges else np.zeros(n, bool)
        for f in feats:
            f.attempts += 1
        st.searched = n
        found = np.isfinite(z).all(axis=1)
        st.found = int(found.sum())
        m.last = SearchView(np.array([m.features[k].id for k in pred.ks], int), pred.uv.copy(), S.copy(), z,
                            np.zeros(n, bool), pred.ks.copy())
        known = np.array([m.features[k].known for k in pred.ks.tolist()], bool)
        if not found.any():
            return True, start_evidence(np.zeros(n), np.zeros(n, bool), known, s.startup.ambiguity_gate_chi2)
        fi = np.flatnonzero(found)
        sub = pred.take(fi)
        rng = np.random.default_rng((self.seed, frame))
        res = one_point_ransac(m.state, sub.ks, z[fi], cam, self.sigma_pixel**2, sub, S[fi], s.ransac, rng,
                               r_scale[fi], votes=self.votes(m.features, sub.ks, edged[fi]), accept=accept)
        if res.refused:
            for f in feats:             # the search counted as not made (the votes read it first)
                f.attempts -= 1
            return False, 0.0
        used = res.used.tolist()
        ks_found = sub.ks.tolist()
        for k, u in zip(ks_found, used):
            if u:
                m.features[k].successes += 1
                m.features[k].last_seen = frame
        m.last.used[fi] = res.used
        if s.drift.drift_gain > 0 and res.used.any():
            ku = sub.ks[res.used]
            residual = z[fi][res.used] - predict_uv(m.state, ku, cam)
            for k, r, finite in zip(ku.tolist(), residual, np.isfinite(residual).all(axis=1).tolist()):
                if finite and not m.features[k].known:
                    m.features[k].note_residual(r, s.drift.drift_memory)
        st.matched = res.n_inliers
        st.rescued = int(res.rescued.sum())
        st.outliers = res.n_outliers
        nu = z[fi] - sub.uv
        d2 = innovation_nis(nu, S[fi])
        for k, u, d in zip(ks_found, used, d2.tolist()):
            if u:
                h = m.features[k].nis
                h.append(d)
                if len(h) > s.deletion.consistency_window:
                    del h[0]
        d2_all, used_all = np.zeros(n), np.zeros(n, bool)
        d2_all[fi], used_all[fi] = d2, res.used
        return True, start_evidence(d2_all, used_all, known, s.startup.ambiguity_gate_chi2)

    @staticmethod
    def _grow_impulse(state: State, motion_cfg: SlamConfig, dt: float, gain: float) -> None:
        """The camera block's covariance as if the constant-velocity prediction over ``dt`` (with
        ``motion_cfg``'s impulses) had taken impulses ``gain`` times larger: ``G P_n G^T`` added
        ``gain^2 - 1`` times more."""
        cd = state.cam_dim
        _, _, G = f_and_dfdx_dfdn(state.x[:cd], dt)
        state.add_camera_noise(G @ noise_covariance(dt, motion_cfg, math.sqrt(gain * gain - 1.0)) @ G.T)

    def votes(self, features: list[MapFeature], ks: np.ndarray, edged: np.ndarray | None = None) -> np.ndarray:
        """Each match's vote for a 1-point hypothesis: its feature's reliability (MapFeature, at
        most 1); a target corner placed by the target's fitted sides in this frame (``edged``
        (m,)) votes ``known_vote``: it is within a few tenths of a pixel, and a map that drifted
        with the camera agrees with itself and would outvote a small far target's corners."""
        votes = np.array([features[k].reliability for k in ks], float)
        if edged is not None:
            votes[np.asarray(edged, bool)] = self.settings.ransac.known_vote
        return votes

    def known_by_edges(self, g: np.ndarray, feats: list, z: np.ndarray, uv_pred: np.ndarray) -> np.ndarray:
        """A printed quadrilateral target whose corners' templates found at least three of them
        is located by its fitted sides (as at the start), not by the templates: a template, cut
        once at the start and warped by the estimated pose, carries that pose's error into every
        match, and one cut from a small far view matches a near one a few pixels off or not at
        all. A corner not found starts from its prediction ``uv_pred`` (m, 2); the sides may then
        move the corners as far as at the start (startup.corners_by_edges), or they are
        left to the templates. Returns which of ``feats`` (m,) it placed."""
        placed = np.zeros(len(feats), bool)
        rows = [j for j, f in enumerate(feats) if f.known]
        target = self.target
        if len(rows) != 4 or target is None or len(target.xyz) != 4:
            return placed
        rows.sort(key=lambda j: feats[j].id)
        quad = z[rows]
        found = np.isfinite(quad).all(axis=1)
        if found.sum() < 3:
            return placed
        quad = np.where(found[:, None], quad, uv_pred[rows])
        edged = corners_by_edges(self.cam, g, quad, self.settings.startup.click_search_px)
        if edged is not None:
            z[rows] = edged
            placed[rows] = True
        return placed
