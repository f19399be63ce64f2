"""The wearer as the twin sees it: segment meshes and their world poses over time.

The twin does not pose bodies itself: whoever builds the wearer (the ``wvr`` command, from the
placement body and its motions, or a file) hands over each segment's world-from-rest transform
over time, so the head moves with the body exactly as placement computed. Between samples the
poses are interpolated by C2 splines (cubic for positions, RotationSpline for orientations),
so velocities and accelerations, and hence the IMU, are smooth whatever the source rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline


class WearerError(ValueError):
    """A wearer that cannot be used; the message says what was expected."""


@dataclass
class Wearer:
    """Segment meshes (rest pose, body frame) and segment poses over time (world frame).

    segments : (S,) names. vertices : (V, 3) rest pose, m. faces : (F, 3). face_segment : (F,).
    joints : (S, 3) joint centres, rest pose, m. t : (T,) s, increasing.
    G_world_rest : (T, S, 4, 4) world-from-rest transform of every segment at every time.
    """

    segments: tuple[str, ...]
    vertices: np.ndarray
    faces: np.ndarray
    face_segment: np.ndarray
    joints: np.ndarray
    t: np.ndarray
    G_world_rest: np.ndarray
    _splines: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        S = len(self.segments)
        if self.G_world_rest.shape != (len(self.t), S, 4, 4):
            raise WearerError(f"G_world_rest must have shape (T, {S}, 4, 4) for {len(self.t)} times, "
                              f"got {self.G_world_rest.shape}")
        if len(self.t) < 4 or np.any(np.diff(self.t) <= 0):
            raise WearerError("a wearer track needs at least 4 samples at increasing times")

    def index(self, segment: str) -> int:
        try:
            return self.segments.index(segment)
        except ValueError:
            raise WearerError(f"unknown segment {segment!r}; the wearer has {list(self.segments)}") from None

    def _spline(self, s: int):
        if s not in self._splines:
            G = self.G_world_rest[:, s]
            self._splines[s] = (CubicSpline(self.t, G[:, :3, 3], axis=0),
                                RotationSpline(self.t, Rotation.from_matrix(G[:, :3, :3])))
        return self._splines[s]

    def pose(self, segment: int, t) -> np.ndarray:
        """World-from-rest transform(s) of one segment at time(s) t: (4, 4) or (n, 4, 4)."""
        t = np.clip(np.asarray(t, float), self.t[0], self.t[-1])
        pos, rot = self._spline(segment)
        T = np.zeros(t.shape + (4, 4))
        T[..., :3, :3] = rot(t).as_matrix()
        T[..., :3, 3] = pos(t)
        T[..., 3, 3] = 1.0
        return T

    def poses(self, t: float) -> np.ndarray:
        """(S, 4, 4) every segment at time t (for rendering)."""
        return np.stack([self.pose(s, t) for s in range(len(self.segments))])

    def segment_mesh(self, s: int) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (n, 3) rest frame, faces (m, 3)) of one segment, re-indexed."""
        f = self.faces[self.face_segment == s]
        used, inv = np.unique(f, return_inverse=True)
        return self.vertices[used], inv.reshape(-1, 3)

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, segments=np.array(self.segments), vertices=self.vertices, faces=self.faces,
                            face_segment=self.face_segment, joints=self.joints, t=self.t, G_world_rest=self.G_world_rest)

    @classmethod
    def load(cls, path: str | Path) -> "Wearer":
        try:
            d = np.load(path)
            return cls(tuple(str(s) for s in d["segments"]), d["vertices"], d["faces"], d["face_segment"],
                       d["joints"], d["t"], d["G_world_rest"])
        except (OSError, KeyError, ValueError) as e:
            raise WearerError(f"{path}: not a wearer file ({e})") from None
