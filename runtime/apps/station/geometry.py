"""The station's geometry: projecting world points through SLAM's pose and the lens model, the
operator's annotations (labels, virtual objects) as world-frame data, and picking the map feature
under a click (a pixel of the camera view, or a ray of the 3D view).

Frames: world (SLAM's), optical (x right, y down, z forward). Points m, angles rad, pixels.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from kinematics.camera import CameraIntrinsics, project, unproject

from .slam_view import MapView

#: A pixel click picks the map feature projecting nearest to it, if within this many pixels.
PICK_PX = 8.0
#: A 3D-view click picks the feature nearest its ray, if within this angle (about 8 px at a
#: typical browser's 50 deg field of view over 1000 px).
PICK_RAD = math.radians(0.5)

OBJECT_KINDS = ("box", "arrow")


@dataclass(frozen=True)
class Label:
    """An operator's label at a world point. id : its number. xyz : (3,) m. text."""

    id: int
    xyz: np.ndarray
    text: str


@dataclass(frozen=True)
class VirtualObject:
    """A virtual object in the world. kind : "box" (centred on ``xyz``, edge lengths ``size``
    (3,) m, world-aligned) or "arrow" (from ``xyz`` along ``size`` (3,), m: its vector)."""

    id: int
    kind: str
    xyz: np.ndarray
    size: np.ndarray = field(default_factory=lambda: np.full(3, 0.05))

    def edges(self) -> np.ndarray:
        """(E, 2, 3) its outline as world segments, m."""
        c, s = np.asarray(self.xyz, float), np.asarray(self.size, float)
        if self.kind == "arrow":
            tip = c + s
            n = np.linalg.norm(s)
            d = s / n
            side = np.cross(d, [0.0, 0.0, 1.0])
            side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0.0, 0.0])
            back = tip - 0.25 * n * d
            return np.array([[c, tip], [tip, back + 0.12 * n * side], [tip, back - 0.12 * n * side]])
        corners = c + 0.5 * s * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        pairs = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
        return np.array([[corners[i], corners[j]] for i, j in pairs])


#: What explore maximises over its candidate views (runtime.apps.explore), as the station states it.
EXPLORE_OBJECTIVE = "score = pose information + novelty (nats)"


@dataclass(frozen=True)
class ExploreView:
    """Explore's last choice as the station shows it: its candidates (the reachable views it
    scored, finite scores only). points_world (n, 3) m, each candidate's fixation point;
    score (n,) nats; pose_info (n,) nats, the expected pose information; novelty (n,) nats, the
    score's empty-cells term; visible (n,) mapped features predicted in that view; chosen : the
    index (into these) of the fixation the loop saccaded to, -1 if none yet."""

    points_world: np.ndarray
    score: np.ndarray
    pose_info: np.ndarray
    novelty: np.ndarray
    visible: np.ndarray
    chosen: int = -1

    @classmethod
    def of(cls, choice, target_world) -> "ExploreView":
        """From an :class:`~runtime.apps.explore.ExploreChoice` (None: nothing chosen yet) and the
        loop's fixation target (3,) m: the chosen one is the candidate at that target (the loop
        takes the best the controller accepts, not always the top score)."""
        if choice is None:
            return cls(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, int))
        k = np.flatnonzero(np.isfinite(choice.score))
        pts = np.asarray(choice.points_world, float)[k]
        tgt = np.asarray(target_world, float).reshape(-1)
        hit = np.flatnonzero(np.all(np.abs(pts - tgt) <= 1e-9, axis=1)) if tgt.shape == (3,) else []
        return cls(pts, choice.score[k].astype(float), choice.pose_info[k].astype(float),
                   (choice.score[k] - choice.pose_info[k]).astype(float), choice.n_visible[k].astype(int),
                   int(hit[0]) if len(hit) else -1)

    def normalised(self) -> np.ndarray:
        """(n,) the scores mapped to [0, 1] over the candidates (all 1 when they are equal)."""
        s = np.asarray(self.score, float)
        if len(s) == 0:
            return s
        span = s.max() - s.min()
        return (s - s.min()) / span if span > 0 else np.ones_like(s)


def world_to_pixels(camera: CameraIntrinsics, T_world_cam: np.ndarray, X) -> np.ndarray:
    """(N, 2) pixels of world points X (N, 3) m seen from ``T_world_cam`` (4, 4), through the
    camera's lens model; NaN for points behind the camera or with no pose."""
    X = np.asarray(X, float).reshape(-1, 3)
    T = np.asarray(T_world_cam, float)
    if not np.isfinite(T).all() or len(X) == 0:
        return np.full((len(X), 2), np.nan)
    P_cam = (X - T[:3, 3]) @ T[:3, :3]
    return project(camera, P_cam)


def pixel_ray(camera: CameraIntrinsics, T_world_cam: np.ndarray, uv) -> tuple[np.ndarray, np.ndarray]:
    """The world ray (origin (3,), unit direction (3,)) through pixel ``uv`` (2,)."""
    d = unproject(camera, np.asarray(uv, float).reshape(1, 2))[0]
    T = np.asarray(T_world_cam, float)
    d = T[:3, :3] @ (d / np.linalg.norm(d))
    return T[:3, 3].copy(), d


def feature_at_pixel(view: MapView, camera: CameraIntrinsics, uv, max_px: float = PICK_PX) -> int | None:
    """The id of the map feature projecting nearest to pixel ``uv`` (2,) in the current view,
    if within ``max_px``; None otherwise (or before SLAM is localised)."""
    uv = np.asarray(uv, float).reshape(2)
    if not view.localised or len(view.ids) == 0 or not np.isfinite(uv).all():
        return None
    p = world_to_pixels(camera, view.T_world_cam, view.xyz)
    d = np.linalg.norm(p - uv, axis=1)
    d[~np.isfinite(d)] = np.inf
    k = int(np.argmin(d))
    return int(view.ids[k]) if d[k] <= max_px else None


def feature_near_ray(view: MapView, origin, direction, max_rad: float = PICK_RAD) -> int | None:
    """The id of the map feature at the smallest angle from the ray (origin (3,), direction
    (3,)), in front of it and within ``max_rad``; None otherwise."""
    o, d = np.asarray(origin, float).reshape(3), np.asarray(direction, float).reshape(3)
    if len(view.ids) == 0 or not (np.isfinite(o).all() and np.isfinite(d).all()) or np.linalg.norm(d) == 0:
        return None
    d = d / np.linalg.norm(d)
    v = view.xyz - o
    dist = np.linalg.norm(v, axis=1)
    ang = np.arccos(np.clip((v @ d) / np.maximum(dist, 1e-12), -1.0, 1.0))
    k = int(np.argmin(ang))
    return int(view.ids[k]) if ang[k] <= max_rad else None


def ellipse_axes(S: np.ndarray, n_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes (2,) px and the angle of the first, rad, of the ``n_sigma`` ellipse of a 2x2
    covariance S (px^2)."""
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    w = np.sqrt(np.maximum(w, 0.0)) * n_sigma
    return w, math.atan2(V[1, 0], V[0, 0])


@functools.lru_cache(maxsize=4)
def _unit_sphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(s.vertices), np.asarray(s.faces)


def ellipsoid_mesh(centres: np.ndarray, covs: np.ndarray, n_sigma: float = 3.0, subdivisions: int = 1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """One triangle mesh of the ``n_sigma`` ellipsoids of covariances covs (N, 3, 3) m^2 about
    centres (N, 3): vertices (N V, 3), faces (N F, 3)."""
    v0, f0 = _unit_sphere(subdivisions)
    verts, faces = [], []
    for i, (c, C) in enumerate(zip(np.asarray(centres, float).reshape(-1, 3), np.asarray(covs, float).reshape(-1, 3, 3))):
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        A = V * (n_sigma * np.sqrt(np.maximum(w, 0.0)))        # columns: the principal semi-axes
        verts.append(c + v0 @ A.T)
        faces.append(f0 + i * len(v0))
    if not verts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    return np.vstack(verts).astype(np.float32), np.vstack(faces).astype(np.uint32)
