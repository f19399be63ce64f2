"""Feature models of the map, in the manner of SceneLib's feature models: each kind states its
size in the state vector, its measurement function with its Jacobians, how it is made from an
image point and how it converts to another kind.

- :mod:`.point`: a 3D point in the world frame (3 numbers).
- :mod:`.inverse_depth`: Civera, Davison and Montiel's inverse-depth ray (6 numbers: the
  camera centre of the first view, azimuth, elevation and inverse depth), in the state from its
  first frame.
- :mod:`.particles`: the paper's factored-sampling ray (a depth pdf of particles, outside the
  state until it becomes a point).

The kinds and their sizes are the state's layout (layout.py), read here by the models.
"""

from ..layout import FEATURE_DIMS, FEATURE_NAMES, INVERSE_DEPTH, MAX_FEATURE_DIM, POINT

__all__ = ["FEATURE_DIMS", "FEATURE_NAMES", "INVERSE_DEPTH", "MAX_FEATURE_DIM", "POINT"]
