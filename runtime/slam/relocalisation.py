"""Relocalisation of a lost track against its own map: whole-image matches of the target and the
most reliable features, a pose by PnP-RANSAC (relocalise.py), for the active search to confirm."""

from __future__ import annotations

import numpy as np

from kinematics.camera import CameraIntrinsics

from .config import MapSettings
from .features import POINT
from .relocalise import relocalise
from .startup import PoseHypothesis
from .views import SlamMap

#: A feature whose match variance along its weakest direction is more than this many times that
#: across it (a standard deviation ratio above 3) is a relocalisation candidate after the rest.
MAX_RELOC_ELONGATION = 10.0


class Relocaliser:
    """Finds a lost camera again in its map. cam, settings : the camera and the map's settings;
    sigma_pixel : a match's standard deviation, px."""

    def __init__(self, cam: CameraIntrinsics, settings: MapSettings, sigma_pixel: float):
        self.cam, self.settings, self.sigma_pixel = cam, settings, float(sigma_pixel)

    @staticmethod
    def elongated(m: SlamMap, k: int) -> bool:
        """Whether feature ``k``'s matches are uncertain along one direction beyond
        ``MAX_RELOC_ELONGATION`` times its variance across it (an edge)."""
        w = np.linalg.eigvalsh(m.features[k].noise_shape)
        return bool(w[1] > MAX_RELOC_ELONGATION * w[0])

    def relocalise(self, g: np.ndarray, m: SlamMap) -> PoseHypothesis | None:
        """Re-acquire the camera pose from whole-image matches of the target and the most
        reliable point features (relocalise.py): the pose found, for the camera block to be
        restarted there in the map's own frame, or None."""
        s = self.settings
        # Points first; inverse-depth features too (a rotating head converts few), at their
        # current depth: PnP-RANSAC and the active search decide whether those are good enough.
        candidates = list(range(m.state.n_features))
        if len(candidates) < s.relocalisation.reloc_min_inliers:
            return None
        # An edge's template matches anywhere along the edge in a whole-image search: features
        # whose matches are elongated (templates.match_noise_shape) come after the rest.
        rank = sorted(candidates, key=lambda k: (not m.features[k].known, self.elongated(m, k),
                                                 m.state.kinds[k] != POINT, -m.features[k].successes))
        rl = s.relocalisation
        ks = np.array(rank[:rl.reloc_candidates])
        found = relocalise(g, [m.features[k].template for k in ks], m.world_points()[ks], self.cam,
                           s.views.match_score, min_inliers=rl.reloc_min_inliers, Y_cov=m.point_covariances(ks),
                           sigma_px=self.sigma_pixel)
        if found is None:
            return None
        return PoseHypothesis(found.R_world_cam, found.r,
                              np.diag(np.r_[np.full(3, rl.reloc_sigma_rad**2), np.full(3, rl.reloc_sigma_m**2)]), 0.0, 0.0)
