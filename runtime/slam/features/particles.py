"""Feature initialisation by factored sampling (paper, section 4.2).

A new feature is a 3D ray from the camera centre of its first view; its depth is a set of
particles (100, uniform over 0.5 to 5 m indoors). Each later frame every particle is projected
into the image with its own innovation covariance, the template is searched once over the
region the particles' ellipses cover, and each particle is reweighted by the likelihood of that
match under its ellipse (Bayes); the weakest particles are pruned deterministically, which
sharpens the distribution fast and shrinks the search. When the depth pdf is well approximated
by a Gaussian -- its standard deviation below ``gauss_ratio`` (0.3) of its mean, the test
MonoSLAM uses -- the ray becomes a 3D point with that mean depth and variance. While a ray, the
feature does not update the camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass
class DepthParticles:
    """A partially initialised feature.

    origin : (3,) camera centre at the first view (world, m). direction : (3,) unit ray (world).
    depths : (N,) metres. weights : (N,) summing to 1. template : (15, 15) appearance.
    uv0 : (2,) where it was first seen. frames : frames since creation.
    """

    origin: np.ndarray
    direction: np.ndarray
    depths: np.ndarray
    weights: np.ndarray
    template: np.ndarray
    uv0: np.ndarray
    frames: int = 0
    failures: int = 0
    history: list = field(default_factory=list)

    @classmethod
    def create(cls, origin, direction, template, uv0, n: int = 100, near: float = 0.5, far: float = 5.0):
        depths = np.linspace(near, far, n)
        return cls(np.asarray(origin, float), np.asarray(direction, float) / np.linalg.norm(direction), depths,
                   np.full(n, 1.0 / n), template, np.asarray(uv0, float))

    def points(self) -> np.ndarray:
        """(N, 3) the particles as world points."""
        return self.origin + self.depths[:, None] * self.direction

    @property
    def mean(self) -> float:
        return float(self.weights @ self.depths)

    @property
    def std(self) -> float:
        return float(np.sqrt(max(self.weights @ (self.depths - self.mean) ** 2, 0.0)))

    def is_gaussian(self, gauss_ratio: float = 0.3) -> bool:
        return self.std < gauss_ratio * self.mean


def reweight(p: DepthParticles, z: np.ndarray, uv: np.ndarray, S: np.ndarray, prune: float = 0.01,
             outlier: float = 0.0, area_px: float = 1.0) -> None:
    """Bayes update of the particle weights by a match z (2,) given each particle's predicted
    measurement uv (N, 2) and innovation covariance S (N, 2, 2); then prune particles whose
    weight is below ``prune`` times the largest. Particles behind the camera (NaN) get zero."""
    d = z - uv
    ok = np.all(np.isfinite(d), axis=1)
    like = np.zeros(len(d))
    Si = np.linalg.inv(S[ok])
    m2 = np.einsum("ni,nij,nj->n", d[ok], Si, d[ok])
    like[ok] = np.exp(-0.5 * m2) / (2 * np.pi * np.sqrt(np.linalg.det(S[ok])))
    # A wrong match (repeated texture, an occluding contour) is explained by a uniform density
    # over the searched area with probability ``outlier``, so that one bad frame cannot prune
    # the true depth for good.
    like[ok] = (1.0 - outlier) * like[ok] + outlier / max(area_px, 1.0)
    w = p.weights * like
    if w.sum() <= 0 or not np.isfinite(w.sum()):
        p.failures += 1
        return
    w /= w.sum()
    keep = w >= prune * w.max()
    p.depths, p.weights = p.depths[keep], w[keep] / w[keep].sum()


def step(p: DepthParticles, project: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
         match: Callable[[np.ndarray, np.ndarray], np.ndarray | None], prune: float = 0.01,
         outlier: float = 0.0) -> None:
    """One frame: ``project(points (N, 3)) -> (uv (N, 2), S (N, 2, 2))`` predicts the particles;
    ``match(uv, S) -> (z (2,), searched area px^2) or None`` searches the template over their
    ellipses."""
    p.frames += 1
    uv, S = project(p.points())
    found = match(uv, S)
    if found is None:
        p.failures += 1
        return
    z, area = found
    reweight(p, np.asarray(z, float), uv, S, prune, outlier, area)
    p.history.append((p.mean, p.std))
