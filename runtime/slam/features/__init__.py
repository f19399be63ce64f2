"""Feature models of the map, in the manner of SceneLib's feature models: each kind states its
size in the state vector, its measurement function with its Jacobians, how it is made from an
image point and how it converts to another kind.

- :mod:`.point`: a 3D point in the world frame (3 numbers).
- :mod:`.inverse_depth`: Civera, Davison and Montiel's inverse-depth ray (6 numbers: the
  camera centre of the first view, azimuth, elevation and inverse depth), in the state from its
  first frame.
- :mod:`.particles`: the paper's factored-sampling ray (a depth pdf of particles, outside the
  state until it becomes a point).

The kinds are numbered so compiled code can switch on them (:data:`FEATURE_DIMS` is indexed by
kind).
"""

import numpy as np

POINT = 0
INVERSE_DEPTH = 1

FEATURE_DIMS = np.array([3, 6], dtype=np.intp)   #: numbers in the state, by kind
FEATURE_NAMES = ("point", "inverse-depth")
MAX_FEATURE_DIM = int(FEATURE_DIMS.max())
