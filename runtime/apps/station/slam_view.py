"""What the station shows of the SLAM: one snapshot type, :class:`MapView`, and :func:`map_view`.

The new SLAM gives ``slam.map_view()`` itself; until it lands on main this module builds the same
fields from today's MonoSLAM (its state vector, covariance, features and particle rays). The
fallback lives only in :func:`_from_state`: delete it (and the dataclasses, importing the SLAM's
own) once every SLAM has ``map_view``.

Everything here is world frame, SI: points m, covariances m^2, pixels for the search.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SearchView:
    """The last frame's active search. ids : (m,) feature ids. uv : (m, 2) predicted pixels.
    S : (m, 2, 2) innovation covariances, px^2. z : (m, 2) matches (NaN: not found, or not
    recorded). used : (m,) inliers."""

    ids: np.ndarray
    uv: np.ndarray
    S: np.ndarray
    z: np.ndarray
    used: np.ndarray


@dataclass(frozen=True)
class MapView:
    """A snapshot of the map for displays. t : s. T_world_cam : (4, 4) (NaN before localised or
    while lost). ids : (N,). xyz : (N, 3) world points, m. cov : (N, 3, 3) m^2. kinds : (N,)
    "point" or "inverse-depth". known : (N,) target points. ray_ids : (K,), ray_origin (K, 3),
    ray_direction (K, 3) unit, ray_depth (K, 2) near and far, m: features being initialised.
    search : the last frame's :class:`SearchView`, or None."""

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


def empty_view(t: float = 0.0) -> MapView:
    """The view before SLAM has started (or without SLAM)."""
    z3 = np.zeros((0, 3))
    return MapView(t, np.full((4, 4), np.nan), np.zeros(0, int), z3, np.zeros((0, 3, 3)), (), np.zeros(0, bool),
                   np.zeros(0, int), z3, z3, np.zeros((0, 2)), None)


def map_view(slam) -> MapView:
    """The SLAM's :class:`MapView` (its own ``map_view()`` where it has one); an empty view for
    None or a SLAM not yet started."""
    if slam is None:
        return empty_view()
    if hasattr(slam, "map_view"):
        return slam.map_view()
    if getattr(slam, "state", None) is None:
        return empty_view()
    return _from_state(slam)


def _from_state(slam) -> MapView:
    """Today's MonoSLAM: points and their covariance blocks straight from x and P, particle rays
    as their depth span, and the search as the features predicted visible now (their pixels and
    innovation covariances at the current estimate; this SLAM keeps no record of its matches,
    so ``z`` is NaN and ``used`` False). To be deleted with the fallback."""
    from runtime.slam.state import feature_slice

    st = slam.state
    n = st.n_features
    cov = np.array([st.P[feature_slice(k), feature_slice(k)] for k in range(n)]).reshape(n, 3, 3)
    lost = bool(slam.stats and slam.stats[-1].lost)
    T = slam.T_world_cam() if not lost else np.full((4, 4), np.nan)
    rays = list(slam.rays)
    search = None
    try:
        ks, uv, S = slam._visible()
        ids = np.array([slam.features[k].id for k in ks], int)
        search = SearchView(ids, np.asarray(uv, float).reshape(-1, 2), np.asarray(S, float).reshape(-1, 2, 2),
                            np.full((len(ks), 2), np.nan), np.zeros(len(ks), bool))
    except AttributeError:
        pass
    return MapView(
        t=float(slam.t_prev) if slam.t_prev is not None else 0.0, T_world_cam=T,
        ids=np.array([f.id for f in slam.features], int), xyz=st.features.copy().reshape(-1, 3), cov=cov,
        kinds=("point",) * n, known=np.array([f.known for f in slam.features], bool),
        ray_ids=np.array([r[0] for r in rays], int),
        ray_origin=np.array([r[1].origin for r in rays], float).reshape(-1, 3),
        ray_direction=np.array([r[1].direction for r in rays], float).reshape(-1, 3),
        ray_depth=np.array([(r[1].depths.min(), r[1].depths.max()) for r in rays], float).reshape(-1, 2),
        search=search)
