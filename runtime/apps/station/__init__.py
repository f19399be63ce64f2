"""The remote operator's web station (paper section 5, Fig. 1b): a stable 3D view of SLAM's map
and camera and the live augmented camera view in a browser, clicks to saccade to and fixate
features, labels and virtual objects, mode changes and a latched emergency stop, and a JSON API
with the same actions. See :mod:`.station` for how the parts fit."""

from .actions import ActionResult, AddLabel, AddObject, BadAction, Fixate, Reset, SetMode, Stop, from_json
from .geometry import Label, VirtualObject, feature_at_pixel, feature_near_ray, world_to_pixels
from .live import LiveStation, Snapshot
from .slam_view import MapView, map_view
from .station import Station

__all__ = ["ActionResult", "AddLabel", "AddObject", "BadAction", "Fixate", "Label", "LiveStation", "MapView", "Reset",
           "SetMode", "Snapshot", "Station", "Stop", "VirtualObject", "feature_at_pixel", "feature_near_ray",
           "from_json", "map_view", "world_to_pixels"]
