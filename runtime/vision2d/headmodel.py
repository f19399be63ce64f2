"""The tracked head: a polyhedral model with texture coordinates and landmarks, and the pose
conventions the head tracker (:mod:`.headtrack`), its test scenes (:mod:`.headscene`) and the
slaving of the wearable's head (:mod:`runtime.gaze.slaving`) share.

Conventions
-----------
head frame
    origin at the head's centre; x forward (out of the face, through the nose), y to the head's
    own left, z up (the same axes as the wearable's mount frame).
camera (optical) frame
    x right, y down, z forward (kinematics.camera).
neutral pose
    the head facing the camera: head x = -z_cam, head y = +x_cam, head z = -y_cam
    (:data:`R_CAM_REF`).
yaw, pitch, roll (radians)
    ``R_cam_head = R_CAM_REF @ Rz(yaw) @ Ry(-pitch) @ Rx(roll)`` (intrinsic z-y'-x''): yaw about
    the head's vertical axis, positive turning to the person's own left; pitch about its
    left-right axis, positive raising the chin (looking up); roll about its front-back axis,
    positive lowering the right ear. Yaw 0 = facing the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

#: Columns: the neutral head's x (forward), y (left), z (up) axes in the optical frame.
R_CAM_REF = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])

#: (depth x, width y, height z) of the default head, metres.
DEFAULT_HEAD_SIZE_M = (0.20, 0.16, 0.24)


# ---------------------------------------------------------------------------------------------
# Pose conventions
# ---------------------------------------------------------------------------------------------

def _ypr_array(ypr, name: str = "ypr") -> np.ndarray:
    a = np.asarray(ypr, dtype=float)
    if a.shape[-1:] != (3,) or a.ndim > 2:
        raise ValueError(f"{name} must be (3,) or (N, 3) yaw, pitch, roll in radians, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has NaN or infinite angles; give finite radians")
    return a


def rotation_from_ypr(ypr) -> np.ndarray:
    """``R_cam_head`` (3, 3) or (N, 3, 3) of yaw, pitch, roll (3,) or (N, 3), radians
    (module docstring for the convention)."""
    a = _ypr_array(ypr)
    flat = a.reshape(-1, 3)
    R_ref_head = Rotation.from_euler("ZYX", np.column_stack([flat[:, 0], -flat[:, 1], flat[:, 2]])).as_matrix()
    R = R_CAM_REF @ R_ref_head
    return R[0] if a.ndim == 1 else R


def ypr_from_rotation(R_cam_head) -> np.ndarray:
    """(yaw, pitch, roll) (3,) or (N, 3), radians, of ``R_cam_head`` (3, 3) or (N, 3, 3)."""
    R = np.asarray(R_cam_head, dtype=float)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R_cam_head must be (3, 3) or (N, 3, 3), got shape {R.shape}")
    flat = R.reshape(-1, 3, 3)
    e = Rotation.from_matrix(R_CAM_REF.T @ flat).as_euler("ZYX")
    out = np.column_stack([e[:, 0], -e[:, 1], e[:, 2]])
    return out[0] if R.ndim == 2 else out


def head_pose(ypr=(0.0, 0.0, 0.0), distance_m: float = 1.0, offset_m=(0.0, 0.0)) -> np.ndarray:
    """``T_cam_head`` (4, 4) or (N, 4, 4): the head at yaw, pitch, roll ``ypr`` (radians), its centre
    ``distance_m`` in front of the camera, shifted by ``offset_m`` = (x right, y down) metres."""
    if not (np.isfinite(distance_m) and distance_m > 0):
        raise ValueError(f"distance_m must be a positive number of metres, got {distance_m}")
    R = rotation_from_ypr(ypr)
    off = np.asarray(offset_m, float)
    if off.shape != (2,):
        raise ValueError(f"offset_m must be (x, y) metres in the image plane, got shape {off.shape}")
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = [off[0], off[1], distance_m]
    T[..., 3, 3] = 1.0
    return T


# ---------------------------------------------------------------------------------------------
# The polyhedral head model
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class HeadModel:
    """A polyhedral head in the head frame (module docstring).

    vertices : (V, 3) float, metres. faces : (F, 3) int, counter-clockwise seen from outside
    (outward normals). uv : (V, 2) float texture coordinates in [0, 1] (u around the head from
    the back through the face, v from chin to crown), or None. landmarks : name -> (3,) points
    on the surface, metres (``nose_tip``, ``left_eye``, ``right_eye``, ``mouth`` for the default head).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    landmarks: dict = field(default_factory=dict)

    def __post_init__(self):
        V = np.asarray(self.vertices, float)
        F = np.asarray(self.faces)
        if V.ndim != 2 or V.shape[1] != 3 or len(V) < 4 or not np.all(np.isfinite(V)):
            raise ValueError(f"HeadModel.vertices must be (V >= 4, 3) finite metres, got shape {V.shape}")
        if F.ndim != 2 or F.shape[1] != 3 or len(F) < 4 or not np.issubdtype(F.dtype, np.integer):
            raise ValueError(f"HeadModel.faces must be (F >= 4, 3) integer vertex indices, got shape {F.shape}")
        if F.min() < 0 or F.max() >= len(V):
            raise ValueError(f"HeadModel.faces index vertices 0..{len(V) - 1}, found {F.min()}..{F.max()}")
        object.__setattr__(self, "vertices", V)
        object.__setattr__(self, "faces", F.astype(np.int64))
        if self.uv is not None:
            uv = np.asarray(self.uv, float)
            if uv.shape != (len(V), 2):
                raise ValueError(f"HeadModel.uv must be (V, 2) = ({len(V)}, 2), got {uv.shape}")
            object.__setattr__(self, "uv", uv)
        tri = V[F]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(n, axis=1)
        # Degenerate faces (zero area) get a zero normal and are never hit by a ray.
        object.__setattr__(self, "face_normals", np.divide(n, area2[:, None], out=np.zeros_like(n),
                                                           where=area2[:, None] > 0))
        object.__setattr__(self, "face_centres", tri.mean(axis=1))

    @property
    def extent_m(self) -> np.ndarray:
        """(3,) size along the head's x, y, z, metres."""
        return self.vertices.max(axis=0) - self.vertices.min(axis=0)


def polyhedral_head(size_m=DEFAULT_HEAD_SIZE_M, n_lon: int = 16, n_lat: int = 9,
                    nose_m: float = 0.025) -> HeadModel:
    """An ellipsoid-like convex polyhedron (a latitude-longitude grid, ``2 n_lon (n_lat - 1)``
    faces; 256 by default) of size ``size_m`` = (depth, width, height) metres with a pyramidal
    nose pushed ``nose_m`` out of the face just below the centre, so that no pose is symmetric.

    The grid's seam (where u wraps) is at the back of the head and the poles are split per
    column, so each vertex has one texture coordinate: u = (longitude + pi) / 2 pi (0.5 = the
    face), v = (latitude + pi/2) / pi.
    """
    size = np.asarray(size_m, float)
    if size.shape != (3,) or not np.all(size > 0):
        raise ValueError(f"size_m must be (depth, width, height) > 0 metres, got {size_m}")
    if n_lon < 8 or n_lon % 2 or n_lat < 4:
        raise ValueError(f"n_lon must be even and >= 8 and n_lat >= 4 (got {n_lon}, {n_lat})")
    a, b, c = size / 2.0
    lon = -math.pi + 2.0 * math.pi * np.arange(n_lon + 1) / n_lon
    lat = -math.pi / 2 + math.pi * np.arange(n_lat + 1) / n_lat
    LAT, LON = np.meshgrid(lat, lon, indexing="ij")  # (n_lat+1, n_lon+1)
    V = np.stack([a * np.cos(LAT) * np.cos(LON), b * np.cos(LAT) * np.sin(LON), c * np.sin(LAT)], -1)
    uv = np.stack([(LON + math.pi) / (2 * math.pi), (LAT + math.pi / 2) / math.pi], -1)
    idx = np.arange((n_lat + 1) * (n_lon + 1)).reshape(n_lat + 1, n_lon + 1)
    # The nose: the front column's vertex nearest 10 degrees below the centre, pushed forward;
    # the one above (the bridge) a little.
    front = n_lon // 2
    j_tip = int(np.argmin(np.abs(lat - math.radians(-10.0))))
    V[j_tip, front, 0] += nose_m
    if j_tip + 1 < n_lat:
        V[j_tip + 1, front, 0] += 0.3 * nose_m
    faces = []
    for j in range(n_lat):
        for i in range(n_lon):
            p, q, r, s = idx[j, i], idx[j, i + 1], idx[j + 1, i + 1], idx[j + 1, i]
            if j > 0:  # the bottom band's p, q are both the south pole
                faces.append((p, q, r))
            if j < n_lat - 1:  # the top band's r, s are both the north pole
                faces.append((p, r, s))
    V = V.reshape(-1, 3)
    landmarks = {"nose_tip": V[idx[j_tip, front]].copy()}
    model = HeadModel(V, np.array(faces, np.int64), uv.reshape(-1, 2), landmarks)
    # Eyes and mouth: the surface points carrying the texture coordinates where the test texture
    # (headscene) draws them.
    for name, (lo, la) in FACE_FEATURES_DEG.items():
        u = (math.radians(lo) + math.pi) / (2 * math.pi)
        v = (math.radians(la) + math.pi / 2) / math.pi
        model.landmarks[name] = surface_point_at_uv(model, (u, v))
    return model


def surface_point_at_uv(model: HeadModel, uv) -> np.ndarray:
    """(3,) the point of ``model``'s surface (head frame, metres) whose interpolated texture
    coordinate is ``uv`` = (u, v); raises if no face's texture triangle contains it."""
    if model.uv is None:
        raise ValueError("this HeadModel has no texture coordinates (uv)")
    p = np.asarray(uv, float)
    T = model.uv[model.faces]                                  # (F, 3, 2)
    e1, e2, d = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0], p - T[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
        b2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
    inside = (np.abs(det) > 1e-15) & (b1 >= -1e-9) & (b2 >= -1e-9) & (b1 + b2 <= 1 + 1e-9)
    if not inside.any():
        raise ValueError(f"no face of the model has texture coordinate {tuple(p)}")
    f = int(np.flatnonzero(inside)[0])
    X = model.vertices[model.faces[f]]
    return X[0] + b1[f] * (X[1] - X[0]) + b2[f] * (X[2] - X[0])


#: (longitude, latitude) degrees of the face features the test texture draws (headscene), as seen
#: from the head's centre; eyes at +-30 deg longitude (left eye on the head's left, +y).
FACE_FEATURES_DEG = {"left_eye": (30.0, 5.0), "right_eye": (-30.0, 5.0), "mouth": (0.0, -32.0)}
