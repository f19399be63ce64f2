"""Target watching and re-acquisition: a drifted pose put back at the known target, near its
prediction when its corners are predicted in view and missed, and over the whole image when it
has not been matched for a while, a pose found there being confirmed by the map made before it
was lost."""

from __future__ import annotations

import numpy as np

from kinematics.camera import CameraIntrinsics, in_image
from kinematics.camera import project as project_points
from kinematics.transforms import rotation_angle

from .config import MapSettings
from .filter import innovation_covariances, innovation_nis
from .appearance import match_features
from .measurement import predict
from .quaternion import quat_from_rotation, quat_to_rotation
from .startup import (PoseHypothesis, RefinedTarget, SlamStartError, find_quadrilateral, locate_target,
                      pose_hypotheses, print_contrast, refine_by_edges)
from .layout import Q_SLICE
from .views import SlamMap, warped


class TargetWatch:
    """Watches one track's view of the known target (``target``: its four corners, world, m;
    None: no target to watch) and finds the pose to put a drifted camera back at.
    ``target_contrast`` : the target's print contrast in the first image (startup.print_contrast).
    ``target_seen`` : the last frame the target's corners were matched; ``target_missed`` : frames
    since, with all four predicted in view."""

    def __init__(self, cam: CameraIntrinsics, settings: MapSettings, target: RefinedTarget | None,
                 target_contrast: float, sigma_pixel: float):
        self.cam, self.settings, self.target = cam, settings, target
        self.target_contrast, self.sigma_pixel = float(target_contrast), float(sigma_pixel)
        self.target_seen = 0
        self.target_missed = 0

    def restarted(self, frame: int) -> None:
        """The camera was put back at the target in ``frame``."""
        self.target_seen, self.target_missed = frame, 0

    def drifted(self, m: SlamMap) -> list[int]:
        """The natural features first seen since the target was last matched (map indices),
        placed from the drifting poses."""
        return [k for k, f in enumerate(m.features) if not f.known and f.first_frame > self.target_seen]

    def watch(self, g: np.ndarray, m: SlamMap, frame: int) -> PoseHypothesis | None:
        """The target's four corners predicted in view and not matched for ``reacquire_after``
        frames: the pose has drifted beyond their search ellipses (a long look away, a fast turn
        the motion model missed), and the natural map, made from the drifting pose, agrees with
        it. The printed quadrilateral is sought near its prediction; found, fitting one pose as
        at the start, and with the natural features mapped while the target was matched found
        where that pose projects them (:meth:`old_map_agrees`, as the whole-image search asks),
        that pose is returned, for the camera to be put back there (a re-localisation against the
        target) and the features first seen since the target was last matched, placed from the
        drifted poses, removed (:meth:`drifted`); else None."""
        s, target = self.settings, self.target
        if target is None or len(target.xyz) != 4 or m.last is None:
            return None
        rows = [j for j, k in enumerate(m.last.ks) if m.features[k].known]
        if len(rows) == 4 and m.last.used[rows].sum() >= 3:
            self.target_seen, self.target_missed = frame, 0
            return None
        if len(rows) < 4 or m.last.used[rows].sum() > 1:
            self.target_missed = 0          # not all in view, or partly matched: no evidence of drift
            return None
        self.target_missed += 1
        if self.target_missed < s.reacquire.reacquire_after:
            return None
        self.target_missed = 0              # found or not, look again only after as many frames
        rows.sort(key=lambda j: m.last.ids[j])
        uv_pred = m.last.uv[rows]
        diag = max(np.linalg.norm(uv_pred[2] - uv_pred[0]), np.linalg.norm(uv_pred[3] - uv_pred[1]))
        quad = find_quadrilateral(g, uv_pred, s.reacquire.reacquire_search * diag)
        if quad is None:
            return None
        edged = refine_by_edges(self.cam, g, quad)
        quad = quad if edged is None else edged
        # Found where the filter's own uncertainty allows (the templates missed for blur or
        # shading, not for drift): nothing to correct.
        nu = quad - uv_pred
        d2 = float(innovation_nis(nu, m.last.S[rows]).sum())
        if d2 < s.reacquire.reacquire_chi2:
            return None
        try:
            hyps = pose_hypotheses(self.cam, target.xyz, quad, s.startup.start_pixel_sigma, s.startup.ambiguity_ratio)
        except SlamStartError:
            return None
        hyps = [h for h in hyps if h.rms_px <= s.startup.start_max_rms_px]
        if not hyps:
            return None
        R_now = quat_to_rotation(m.state.x[Q_SLICE])
        hyp = min(hyps, key=lambda h: np.linalg.norm(h.R_world_cam - R_now))
        # A drift turns the camera by little; a pose half a turn away is another quadrilateral
        # (or this one's corners in another order), as in the whole-image search.
        if rotation_angle(R_now, hyp.R_world_cam) > s.reacquire.loop_max_turn_rad:
            return None
        # A drifted pose has left the map the target anchored: the natural features mapped
        # while the target was matched must match at the target's pose. A quadrilateral that is
        # not the target (the target hidden, a shadow's edge) gives a pose they refute.
        old = self.mapped_before_loss(m)
        if old is not None and not self.old_map_agrees(g, m, hyp.R_world_cam, hyp.r, old):
            return None
        return hyp

    def close_loop(self, g: np.ndarray, m: SlamMap) -> PoseHypothesis | None:
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
        target was in the first image. Returns the confirmed pose, for the camera to be restarted
        there, the features first seen since the target was lost (placed from the drifting
        poses) removed and the frame measured; else None."""
        s, target, cam = self.settings, self.target, self.cam
        if target is None or len(target.xyz) != 4:
            return None
        known = m.known_in_id_order()
        if len(known) != 4:
            return None
        found = locate_target(g, cam, target.xyz, quat_to_rotation(m.state.x[Q_SLICE]), s.reacquire.loop_max_turn_rad,
                              s.startup.start_max_rms_px, s.reacquire.loop_min_area_px)
        if not found:
            return None
        pred = predict(m.state, known, cam)
        S = innovation_covariances(m.state, pred, self.sigma_pixel**2, np.ones(4)) if pred.valid.all() else None
        # Lost before any natural feature was mapped (a drift from the first frames), the map
        # holds only what the drift placed and there is nothing to ask: the most print-like
        # quadrilateral is taken, as the start-up takes it. A map that had such features asks
        # them even when the cap has since removed them (a lone dark quadrilateral is no proof).
        old = self.mapped_before_loss(m)
        ask_map = old is not None
        if not ask_map:
            # and only if it looks as printed as the target did at the start (not a picture frame)
            found = [f for f in found[:1] if print_contrast(g, f.uv) >= 0.5 * self.target_contrast]
        for seen in found[:s.reacquire.loop_trials]:
            if S is not None:
                nu = seen.uv - pred.uv
                if float(innovation_nis(nu, S).sum()) < s.reacquire.reacquire_chi2:
                    return None    # where the filter expects it: the active search will take it
            if not ask_map or self.old_map_agrees(g, m, seen.R_world_cam, seen.r, old):
                break
        else:
            return None
        try:
            hyps = pose_hypotheses(cam, target.xyz, seen.uv, s.startup.start_pixel_sigma, s.startup.ambiguity_ratio)
        except SlamStartError:
            return None
        return min(hyps, key=lambda h: np.linalg.norm(h.R_world_cam - seen.R_world_cam))

    def mapped_before_loss(self, m: SlamMap) -> np.ndarray | None:
        """The natural features mapped while the target was last matched (map indices), which a
        pose put back at the target must match; None when no natural feature had been mapped by
        then (a drift from the first frames: no map to ask). Empty when the cap has since removed
        them all: a lone quadrilateral is then no proof."""
        if m.first_mapped is None or m.first_mapped > self.target_seen:
            return None
        return np.array([k for k, f in enumerate(m.features) if not f.known and f.first_frame <= self.target_seen],
                        int)

    def old_map_agrees(self, g: np.ndarray, m: SlamMap, R_world_cam: np.ndarray, r: np.ndarray, ks: np.ndarray) -> bool:
        """Whether features ``ks`` match in ``g`` where the pose (R_world_cam, r) projects them: at least
        ``loop_min_old`` of them, and half of those it puts in the image, each found within
        ``loop_window_px`` of its projection, and by the median within a third of that. A right
        pose puts its matches within a pixel or two; at a wrong one, a bare counter's grain
        still gives best scores, spread over the windows and most on their rims (twin
        kitchen-walk at 320x240: 9 of 15 found, 6-7 px off, the pose 37 cm away)."""
        s, cam = self.settings, self.cam
        if len(ks) < s.reacquire.loop_min_old:
            return False
        Y = m.world_points()[ks]
        uv = project_points(cam, (Y - r) @ R_world_cam)
        inside = np.isfinite(uv).all(axis=1) & in_image(cam, np.nan_to_num(uv, nan=-1e9), margin=s.views.margin_px)
        if inside.sum() < s.reacquire.loop_min_old:
            return False
        ks, Y, uv = ks[inside], Y[inside], uv[inside]
        feats = [m.features[k] for k in ks]
        x_v = np.r_[r, quat_from_rotation(R_world_cam)]
        S = np.broadcast_to(np.eye(2) * (s.reacquire.loop_window_px / 3.0) ** 2, (len(ks), 2, 2)).copy()
        z, _, found = match_features(g, feats, np.array([warped(s.warp, f) for f in feats], bool), Y, x_v, cam, uv, S,
                                     s.views.match_score, s.views.max_search_area_px)
        if int(found.sum()) < max(s.reacquire.loop_min_old, 0.5 * len(ks)):
            return False
        return float(np.median(np.linalg.norm(z[found] - uv[found], axis=1))) <= s.reacquire.loop_window_px / 3.0
