"""What the SLAM reports: its tracking status, each frame's statistics, the last active search
and a snapshot of the map for displays."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class TrackingStatus(enum.Enum):
    """Where the track stands after its last frame (ORB-SLAM's states, with MonoSLAM's lost rule).

    INITIALISING: not localised yet (before ``start``, or a saved map's session until it is
    first re-localised). TRACKING: the last frame matched at least 3 features. RECENTLY_LOST:
    fewer for some frames, fewer than ``MapSettings.relocalisation.lost_after``. LOST: for that
    many: the map is frozen and the pose sought again. RELOCALISED: a lost track's pose found again this frame
    and confirmed by the active search."""

    INITIALISING = "initialising"
    TRACKING = "tracking"
    RECENTLY_LOST = "recently lost"
    LOST = "lost"
    RELOCALISED = "relocalised"


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
    seconds: float = 0.0          # wall-clock time of the frame's processing (decoding excluded)
    cpu_seconds: float = 0.0      # the tracking thread's CPU time for it (what a loaded machine does not inflate)
    imu: bool = False             # predicted through the IMU
    lost: bool = False
    relocalised: bool = False
    guided: int = 0               # features searched in regions narrowed by the first ones (guided.py)
    over_cap: int = 0             # guides searched over the search cap (measure.Measurement._rescue_guides)
    outgrown: int = 0             # chosen, not searched: the ellipse's box over the search cap (a failed search)
    retried: bool = False         # searched again with a larger motion impulse (measure.Measurement.measure)
    onset: bool = False           # measured again with a turn's impulses (track.Track.step)
    sigma_a: float = 0.0          # the linear impulse the prediction took, m/s^2 (SlamConfig.impulses.adapt_sigma_a)
    sigma_alpha: float = 0.0      # the angular impulse, rad/s^2 (SlamConfig.impulses.adapt_sigma_alpha)
    reacquired: bool = False      # the camera put back at the target's pose (reacquire.TargetWatch)
    skipped: str = ""
    map_units_per_m: float | None = None   # the scale state k once the IMU holds a natural start's map
