"""What the map keeps of a feature besides its state entries: its first-view appearance, where
it was first seen, its record of matches, and its plane (appearance/ holds what is done with them)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinematics.camera import CameraIntrinsics, unproject

from .appearance.patch import match_noise_shape


@dataclass
class MapFeature:
    """What the map keeps of a feature besides its state entries.

    template : (t, t) float32, its first-view appearance. first_frame : frame it was made in.
    r0 : (3,) the first view's optical centre, world, m (valid-view tests). known : a target
    point. attempts, successes : searches and inlier matches (deletion). patch : (p, p) the
    first view's larger patch (warping), uv0 : its centre pixel, R0 : (3, 3) the first view's
    camera-to-world rotation, normal : (3,) the patch's plane normal (world), normal_from_map :
    fitted to map neighbours, normal_view_deg : the view's angle from the first, degrees, when
    the normal was last fitted to the feature's looks (0: never). rays0 : (4, 3) cached world
    rays of the patch's corners.
    drift : (2,) px, the exponential mean of its residuals after each update, started by its
    first (:meth:`note_residual`); None before any. noise_shape : (2, 2) its matches' noise
    covariance as a multiple of the pixel noise, first-view image axes (:func:`match_noise_shape`
    of its template; the identity for a target point, located by its sides).
    """

    id: int
    template: np.ndarray
    first_frame: int
    r0: np.ndarray
    known: bool = False
    attempts: int = 0
    successes: int = 0
    patch: np.ndarray | None = None
    uv0: np.ndarray | None = None
    R0: np.ndarray | None = None
    normal: np.ndarray | None = None
    normal_from_map: bool = False
    normal_view_deg: float = 0.0
    rays0: np.ndarray | None = None
    last_seen: int = -1
    nis: list = field(default_factory=list)   # normalised innovations of its latest inlier matches
    drift: np.ndarray | None = None
    noise_shape: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        self.noise_shape = np.eye(2) if self.known else match_noise_shape(self.template)

    @property
    def reliability(self) -> float:
        """The chance that its matches are true ones, from its record: inlier matches over
        searches, with a prior of one in two ((successes + 1) / (attempts + 2))."""
        return (self.successes + 1) / (self.attempts + 2)

    def note_residual(self, r: np.ndarray, memory: float) -> None:
        """Fold the residual ``r`` (2,) px, its match less its projection after the frame's
        update, into :attr:`drift` with weight ``memory`` (0..1) for the newest."""
        r = np.asarray(r, float)
        self.drift = r.copy() if self.drift is None else (1.0 - memory) * self.drift + memory * r

    def drift_variance_scale(self, gain: float, sigma2: float) -> float:
        """How much its measurement variance grows for a persistent residual:
        ``1 + gain |drift|^2 / sigma2`` (``sigma2`` px^2, the features' pixel variance). A match
        whose errors are white averages to no drift; one that slides (an occluding contour, a
        template that no longer looks like its first view) keeps its residual's sign and is
        trusted less, where the filter would otherwise take correlated errors as independent."""
        return 1.0 if self.drift is None else 1.0 + gain * float(self.drift @ self.drift) / sigma2

    def first_view_rays(self, cam: CameraIntrinsics) -> np.ndarray:
        """(5, 3) world rays of the first view's template corners and centre (cached)."""
        if self.rays0 is None:
            h = self.template.shape[0] // 2
            c0 = np.asarray(self.uv0, float)
            src = c0 + np.array([[-h, -h], [h, -h], [h, h], [-h, h], [0, 0]], float)
            self.rays0 = unproject(cam, src) @ self.R0.T
        return self.rays0
