"""The map features' appearance: each feature's first-view template and the larger patch around
it, and the template predicted for the current view by the homography its plane induces between
the two views (MonoSLAM's template warping): the known target's plane for its corners, the plane
the feature's map neighbours fit for natural features (``MapSettings.warp``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args, project_point_kernel, unproject

from .kernels import compiled_kernel
from .quaternion import quat_to_rotation
from .search import extract_template


#: A match's noise variance along its template's weakest gradient direction is at most this
#: many times that across its strongest: an edge's position along itself, 10 px standard
#: deviation for a 1 px pixel noise.
MAX_NOISE_ELONGATION = 100.0


def match_noise_shape(template: np.ndarray, max_ratio: float = MAX_NOISE_ELONGATION) -> np.ndarray:
    """(2, 2) the shape of a match's noise covariance in the template's image axes (u, v), as a
    multiple of the pixel noise's variance. A match places a template only as well as its
    gradients constrain it (the aperture problem): the Cramer-Rao bound of an SSD match is
    ``sigma_n^2 M^-1``, ``M`` the sum of ``g g^T`` over the template (its structure tensor).
    Scaled so that the direction of the strongest gradients keeps the pixel noise (variance 1)
    and the weakest gets the ratio of M's eigenvalues, at most ``max_ratio``: a corner stays
    near isotropic, an edge's match is uncertain along the edge. A flat template: ``max_ratio I``."""
    t = np.asarray(template, float)
    gu = 0.5 * (t[1:-1, 2:] - t[1:-1, :-2])       # central differences inside the border
    gv = 0.5 * (t[2:, 1:-1] - t[:-2, 1:-1])
    a, b, c = float(np.vdot(gu, gu)), float(np.vdot(gu, gv)), float(np.vdot(gv, gv))
    half_gap = math.hypot(0.5 * (a - c), b)
    w_max, w_min = 0.5 * (a + c) + half_gap, 0.5 * (a + c) - half_gap
    if not (math.isfinite(w_max) and w_max > 0):
        return max_ratio * np.eye(2)
    ratio = min(w_max / max(w_min, w_max / max_ratio), max_ratio)
    # The strongest direction, (cos, sin) of the angle 0.5 atan2(2b, a - c); the weakest across it.
    angle = 0.5 * math.atan2(2.0 * b, a - c)
    strong = np.array([math.cos(angle), math.sin(angle)])
    weak = np.array([-strong[1], strong[0]])
    return np.outer(strong, strong) + ratio * np.outer(weak, weak)


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


def patch_half(template_px: int) -> int:
    """Half-size of the stored first-view patch: room to warp the template (20 for 15 px)."""
    return 3 * (template_px // 2) - 1


def first_view_patch(image: np.ndarray, uv, half: int) -> np.ndarray | None:
    """The (2 half + 1)^2 patch centred exactly on uv (see search.extract_template), or None
    near the border."""
    return extract_template(image, uv, 2 * half + 1)


def warped_template(f: MapFeature, x_v: np.ndarray, y: np.ndarray, cam: CameraIntrinsics) -> np.ndarray:
    """The feature's template as the current camera ``x_v`` should see it: the first-view patch
    warped by the homography its plane (through the point ``y`` (3,), normal ``f.normal``)
    induces between the two views (computed through the lens model at the patch's corners).
    Falls back to the stored template when the feature has no patch or the warp degenerates."""
    if f.patch is None or f.normal is None:
        return f.template
    h = f.template.shape[0] // 2
    ph = f.patch.shape[0] // 2
    c0 = np.asarray(f.uv0, float)       # the template's and the patch's exact centre
    src = c0 + np.array([[-h, -h], [h, -h], [h, h], [-h, h], [0, 0]], float)
    model, params = lens_kernel_args(cam)
    uvc = plane_corners_kernel(f.first_view_rays(cam), f.normal, f.r0, y, x_v[:3], quat_to_rotation(x_v[3:7]), model, params)
    if not np.all(np.isfinite(uvc)):
        return f.template
    uv, centre = uvc[:4], uvc[4]
    side = np.linalg.norm(uv[1] - uv[0]) / (2 * h)
    if not 0.5 < side < 2.0:                              # the template is no longer valid
        return f.template
    src_p = (src[:4] - (c0 - ph)).astype(np.float32)
    dst_t = (uv - (centre - h)).astype(np.float32)
    M = cv2.getPerspectiveTransform(src_p, dst_t)
    return cv2.warpPerspective(f.patch, M, (2 * h + 1, 2 * h + 1), flags=cv2.INTER_LINEAR)


@compiled_kernel(project_point_kernel)
def plane_corners_kernel(rays0, normal, r0, y, r, R, model, params):
    """Pixels (5, 2) in the current view of the first view's patch corners (rows 0-3) and centre
    (row 4) on the plane through ``y`` with ``normal`` (their world rays ``rays0`` (5, 3) from
    ``r0``); all NaN when the warp is invalid (a ray parallel to the plane, a point behind either
    camera). The centre is where the first view's template centre lands, not ``y``'s projection:
    the estimate of ``y`` drifts off that ray, and centring on it would bias the match by the
    estimate's own error."""
    out = np.full((5, 2), np.nan)
    c = normal[0] * (y[0] - r0[0]) + normal[1] * (y[1] - r0[1]) + normal[2] * (y[2] - r0[2])
    for i in range(5):
        den = normal[0] * rays0[i, 0] + normal[1] * rays0[i, 1] + normal[2] * rays0[i, 2]
        if abs(den) < 1e-6:
            return np.full((5, 2), np.nan)
        lam = c / den
        if not lam > 0:
            return np.full((5, 2), np.nan)
        X0, X1, X2 = r0[0] + lam * rays0[i, 0], r0[1] + lam * rays0[i, 1], r0[2] + lam * rays0[i, 2]
        d0, d1, d2 = X0 - r[0], X1 - r[1], X2 - r[2]
        px = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        py = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        pz = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        res = project_point_kernel(model, params, px, py, pz)
        out[i, 0], out[i, 1] = res[0], res[1]
    return out


def local_plane_normal(Y: np.ndarray, k: int, radius: float, tol: float, min_points: int = 4) -> np.ndarray | None:
    """Unit normal (3,) of the plane fitted (least squares) to point ``k`` of ``Y`` (n, 3), m,
    and the points within ``radius`` m of it, if there are at least ``min_points`` of them and
    they are coplanar: RMS distance from the plane at most ``tol`` m, and spread along two
    directions (the second singular value at least 3 times the smallest). Otherwise None."""
    near = np.flatnonzero(np.linalg.norm(Y - Y[k], axis=1) < radius)
    if len(near) < min_points:
        return None
    _, sv, Vt = np.linalg.svd(Y[near] - Y[near].mean(axis=0), full_matrices=False)
    if sv[-1] / math.sqrt(len(near)) > tol or sv[1] < 3 * sv[-1]:
        return None
    return Vt[-1]
