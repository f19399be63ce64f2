"""Occlusion queries against a triangle mesh with Intel Embree (the engine trimesh uses).

trimesh's ``RayMeshIntersector`` answers "does the ray hit anything" by finding the first
hit; Embree's occlusion query stops at any hit and takes a maximum distance, which is what
field of view (rays to infinity) and line of sight (rays to a point) need, and is faster. The
scene is the same embreex scene trimesh builds; tests check the two agree.
"""

from __future__ import annotations

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh


class Occluder:
    """A static triangle mesh for occlusion queries.

    vertices : (V, 3) float, metres. faces : (F, 3) int.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.scene = rtcore_scene.EmbreeScene()
        # Embree works in single precision; keep the triangles alive with the scene.
        self._triangles = np.ascontiguousarray(np.asarray(vertices, np.float64)[faces], dtype=np.float32)
        TriangleMesh(self.scene, self._triangles)

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
