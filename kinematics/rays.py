"""Ray casting against a triangle mesh with Intel Embree (the engine trimesh uses): the suite's
one ray caster, for placement's field of view and line of sight and the head tracker's model.

trimesh's ``RayMeshIntersector`` answers "does the ray hit anything" by finding the first hit;
Embree's occlusion query stops at any hit and takes a maximum distance, which is what field of
view (rays to infinity) and line of sight (rays to a point) need, and is faster. The first-hit
query gives the triangle and the distance, for back-projection onto a model. The scene is the
embreex scene trimesh builds. Embree works in single precision, so occlusion near a triangle
edge can go either way; first hits are solved again in double precision on the triangle
Embree found. Both sides of a triangle count.
It lives in ``kinematics`` because both ``placement`` and ``runtime`` use it (the import rule).
"""

from __future__ import annotations

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

__all__ = ["RayCaster"]


class RayCaster:
    """A static triangle mesh for ray queries.

    vertices : (V, 3) float, metres (any unit). faces : (F, 3) int.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.scene = rtcore_scene.EmbreeScene()
        # Embree works in single precision; keep the triangles alive with the scene.
        tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
        self._triangles = np.ascontiguousarray(tri, dtype=np.float32)
        TriangleMesh(self.scene, self._triangles)
        # For first hits in double precision: each triangle's plane (a point and the normal).
        self._v0 = tri[:, 0]
        self._normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])

    def blocked(self, origins: np.ndarray, directions: np.ndarray, max_dist: np.ndarray | float | None = None,
                chunk: int = 1 << 20) -> np.ndarray:
        """(n,) bool: whether each ray (origin (n, 3), unit direction (n, 3)) hits the mesh before
        ``max_dist`` (scalar or (n,), metres; default infinity)."""
        origins = np.asarray(origins, np.float32)
        directions = np.asarray(directions, np.float32)
        n = len(origins)
        out = np.empty(n, bool)
        dists = None if max_dist is None else np.broadcast_to(np.asarray(max_dist, np.float32), (n,))
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            kw = {} if dists is None else {"dists": np.array(dists[s:e], np.float32)}  # embree writes into it
            # OCCLUDED returns 0 for an occluded ray and -1 for a free one.
            r = self.scene.run(np.ascontiguousarray(origins[s:e]), np.ascontiguousarray(directions[s:e]),
                               query="OCCLUDED", **kw)
            out[s:e] = r != -1
        return out

    def first_hit(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """The nearest hit of each ray: ``t`` (n,) float, the ray parameter (in units of each
        direction's length: the point is origin + t direction; NaN for a miss) and ``face`` (n,)
        int, the triangle hit (-1 for a miss). origins, directions : (n, 3); directions need not
        be unit (zero-length ones miss)."""
        O = np.asarray(origins, float).reshape(-1, 3)
        D = np.asarray(directions, float).reshape(-1, 3)
        if len(O) != len(D):
            raise ValueError(f"origins ({len(O)}) and directions ({len(D)}) must have the same number of rays")
        if len(O) == 0:
            return np.zeros(0), np.zeros(0, np.int64)
        length = np.linalg.norm(D, axis=1)
        ok = length > 0
        unit = np.zeros_like(D)
        unit[ok] = D[ok] / length[ok, None]
        res = self.scene.run(np.ascontiguousarray(O, np.float32), np.ascontiguousarray(unit, np.float32),
                             query="INTERSECT", output=True)
        face = np.asarray(res["primID"], np.int64)
        hit = ok & (face >= 0) & np.isfinite(np.asarray(res["tfar"], float))
        # Embree finds the triangle in single precision; the hit on it is solved again in double
        # (the ray against the triangle's plane), so points are as exact as the mesh.
        f = face[hit]
        n = self._normal[f]
        t = np.full(len(O), np.nan)
        t[hit] = np.einsum("ij,ij->i", n, self._v0[f] - O[hit]) / np.einsum("ij,ij->i", n, D[hit])
        return t, np.where(hit, face, -1)
