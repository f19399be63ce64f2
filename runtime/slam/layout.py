"""The state vector's layout, written once: the camera block's sizes and slices, the feature
kinds and their sizes, and the offset table. The bottom of the package: it imports nothing of
it, so the state (state.py) and the feature models (features/) both read it.

Camera block ``x_v`` (13 numbers, 19 with IMU bias states, 20 with the IMU's clock offset, 24
with the map's scale and gravity as the IMU sees them): ``r`` (0:3, m, world), ``q`` (3:7, w x y
z, camera -> world), ``v`` (7:10, m/s, world), ``w`` (10:13, rad/s, camera), ``b_g`` (13:16,
rad/s), ``b_a`` (16:19, m/s^2), ``t_d`` (19, s), ``k`` (20, map units per metre: a map started
from natural features has no metric unit, so its lengths (r, v, the features) are in its own
unit), ``g`` (21:24, m/s^2: gravity in that map's frame, the first camera's).
Features follow, each of the size its kind gives (:data:`FEATURE_DIMS`, indexed by kind).
"""

from __future__ import annotations

import numpy as np

CAMERA_DIM = 13          #: the MonoSLAM camera block
CAMERA_DIM_BIASED = 19   #: with gyro and accelerometer bias states
CAMERA_DIM_TIMED = 20    #: and the IMU's clock offset t_d (s)
CAMERA_DIM_SCALED = 24   #: and the map's scale k (map units per metre) and gravity g in its frame
POSE_DIM = 7             #: r and q: the part of the camera block a measurement sees
NOISE_DIM = 6            #: the constant-velocity impulse n = (V, Omega) = dt (a, alpha)

R_SLICE = slice(0, 3)
Q_SLICE = slice(3, 7)
V_SLICE = slice(7, 10)
W_SLICE = slice(10, 13)
BG_SLICE = slice(13, 16)
BA_SLICE = slice(16, 19)
TD_INDEX = 19            #: t_d: an IMU sample stamped t was taken at camera time t - t_d
SCALE_INDEX = 20         #: k: a metre is k of the map's units
G_SLICE = slice(21, 24)  #: g: gravity in the map's frame, m/s^2 (metric, like the IMU's forces)

CAMERA_NAMES = (("r", R_SLICE), ("q", Q_SLICE), ("v", V_SLICE), ("w", W_SLICE), ("b_g", BG_SLICE),
                ("b_a", BA_SLICE), ("t_d", slice(TD_INDEX, TD_INDEX + 1)), ("k", slice(SCALE_INDEX, SCALE_INDEX + 1)), ("g", G_SLICE))

# Feature kinds, numbered so compiled code can switch on them.
POINT = 0
INVERSE_DEPTH = 1

FEATURE_DIMS = np.array([3, 6], dtype=np.intp)   #: numbers in the state, by kind
FEATURE_NAMES = ("point", "inverse-depth")
MAX_FEATURE_DIM = int(FEATURE_DIMS.max())


def check_camera_dim(cam_dim: int) -> int:
    """``cam_dim`` as an int, or a ValueError naming the three sizes the camera block may have."""
    if cam_dim not in (CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_TIMED, CAMERA_DIM_SCALED):
        raise ValueError(f"the camera block has {CAMERA_DIM} numbers, {CAMERA_DIM_BIASED} with IMU biases, "
                         f"{CAMERA_DIM_TIMED} with the IMU's clock offset as well or {CAMERA_DIM_SCALED} with the "
                         f"map's scale and gravity; got {cam_dim}")
    return int(cam_dim)


def feature_starts(cam_dim: int, kinds: np.ndarray) -> np.ndarray:
    """(N,) int: where each feature begins in the state vector."""
    dims = FEATURE_DIMS[np.asarray(kinds, np.intp)]
    return (cam_dim + np.concatenate([[0], np.cumsum(dims)[:-1]])).astype(np.intp) if len(dims) else \
        np.zeros(0, np.intp)


def state_size(cam_dim: int, kinds) -> int:
    """The state vector's length for a camera block of ``cam_dim`` and features of ``kinds``."""
    return int(cam_dim + FEATURE_DIMS[np.asarray(kinds, np.intp)].sum())
