"""What the station shows of the SLAM: its :class:`~runtime.slam.system.MapView` snapshot (the
map's points and covariances, rays being initialised, the camera, the last active search), or an
empty one before SLAM has started. World frame, SI: points m, covariances m^2, search in px."""

from __future__ import annotations

from runtime.slam.system import MapView, SearchView

__all__ = ["MapView", "SearchView", "empty_view", "map_view"]


def empty_view(t: float = 0.0) -> MapView:
    """The view before SLAM has started (or without SLAM)."""
    return MapView.empty(t)


def map_view(slam) -> MapView:
    """The SLAM's :class:`MapView`; an empty view for None or a SLAM not yet started."""
    if slam is None or not slam.started:
        return empty_view()
    return slam.map_view()
