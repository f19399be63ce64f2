"""The map and its queries: the filter state with each feature's appearance and records, the
rays being initialised, the last active search; which features are in view and how far from
their first views, their world points and covariances."""

from __future__ import annotations

import math

import numpy as np

from kinematics.camera import CameraIntrinsics

from .config import MapSettings
from .features import INVERSE_DEPTH, POINT, inverse_depth
from .kernels import compiled_kernel
from .measurement import Prediction
from .quaternion import quat_to_rotation
from .records import FrameStats, SearchView
from .state import State
from .map_feature import MapFeature


@compiled_kernel()
def _first_view_kernel(Y, r, r0, k):
    """How far point ``Y[k]`` is seen from its first view, the camera now at r (3,) and then at
    ``r0[k]``: the cosine of the angle between the two viewing rays and the ratio of the ranges,
    now over then."""
    a0, a1, a2 = Y[k, 0] - r[0], Y[k, 1] - r[1], Y[k, 2] - r[2]
    b0, b1, b2 = Y[k, 0] - r0[k, 0], Y[k, 1] - r0[k, 1], Y[k, 2] - r0[k, 2]
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    nb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    cos = min(max((a0 * b0 + a1 * b1 + a2 * b2) / max(na * nb, 1e-12), -1.0), 1.0)
    return cos, na / max(nb, 1e-9)


@compiled_kernel(_first_view_kernel)
def _from_first_view(Y, r, r0):
    """:func:`_first_view_kernel` for every point Y (N, 3), first seen from r0 (N, 3): cosines
    (N,) and range ratios (N,)."""
    N = Y.shape[0]
    cos, ratio = np.empty(N), np.empty(N)
    for k in range(N):
        cos[k], ratio[k] = _first_view_kernel(Y, r, r0, k)
    return cos, ratio


@compiled_kernel(_first_view_kernel)
def _views_kernel(uv, valid, Y, r, r0s, known, width, height, margin, cos_lim, cos_lim_known, rmax, rmax_known,
                  angle_unit_deg, log_scale_unit, known_scale):
    """:meth:`SlamMap.views` for the features predicted at ``uv`` (N, 2) (``valid``) inside the
    image (``margin`` px from its edge, as kinematics.camera.in_image): whether each is both in
    the image and seen close enough to its first view (N,), and its noise scale (N,)."""
    N = uv.shape[0]
    ok = np.zeros(N, dtype=np.bool_)
    scale = np.ones(N)
    lo = -0.5 + margin
    for k in range(N):
        u, v = uv[k, 0], uv[k, 1]
        if not (valid[k] and u >= lo and u <= width - 0.5 - margin and v >= lo and v <= height - 0.5 - margin):
            continue
        cos, ratio = _first_view_kernel(Y, r, r0s, k)
        cl, rm = (cos_lim_known, rmax_known) if known[k] else (cos_lim, rmax)
        ok[k] = cos >= cl and ratio >= 1.0 / rm and ratio <= rm
        if known[k]:
            scale[k] = known_scale
        else:
            scale[k] = (1.0 + (math.degrees(math.acos(cos)) / angle_unit_deg) ** 2
                        + (math.log(max(ratio, 1e-9)) / log_scale_unit) ** 2)
    return ok, scale


@compiled_kernel()
def _rolled_shapes(R_world_cam, A, R0, ks):
    """(m, 2, 2) the shapes ``A[ks]`` (first-view image axes) turned by each first view's roll
    about the optic axis to this view: the angle of ``R_world_cam^T R0``'s upper 2 x 2 block."""
    m = ks.shape[0]
    out = np.empty((m, 2, 2))
    for i in range(m):
        k = ks[i]
        # The upper 2 x 2 block of R_world_cam^T R0[k]: (r00 + r11, r10 - r01) is the roll's angle.
        cos_sum, sin_sum = 0.0, 0.0
        for j in range(3):
            cos_sum += R_world_cam[j, 0] * R0[k, j, 0] + R_world_cam[j, 1] * R0[k, j, 1]
            sin_sum += R_world_cam[j, 1] * R0[k, j, 0] - R_world_cam[j, 0] * R0[k, j, 1]
        ang = np.arctan2(sin_sum, cos_sum)
        c, s = np.cos(ang), np.sin(ang)
        a00, a01, a11 = A[k, 0, 0], A[k, 0, 1], A[k, 1, 1]
        # rot A rot^T, rot = [[c, -s], [s, c]]
        out[i, 0, 0] = c * c * a00 - 2.0 * c * s * a01 + s * s * a11
        out[i, 1, 1] = s * s * a00 + 2.0 * c * s * a01 + c * c * a11
        out[i, 0, 1] = c * s * (a00 - a11) + (c * c - s * s) * a01
        out[i, 1, 0] = out[i, 0, 1]
    return out


def warped(warp: str, f: MapFeature) -> bool:
    """Whether feature ``f``'s template is predicted through its plane (MapSettings.warp)."""
    return warp == "all" or (warp == "known" and f.known) or (
        warp == "neighbours" and (f.known or f.normal_from_map or f.normal_view_deg > 0))


class SlamMap:
    """One filter's map: ``state`` (camera and features), ``features`` (N,) their appearance
    and records in the state's order, ``rays`` the particle rays being initialised (id,
    DepthParticles, R0, patch), ``last`` the last frame's search, ``in_view_ids`` the features
    predicted in view at it, ``first_mapped`` the first frame a natural feature was mapped in
    (None: none yet; 0: a map given), so the target's re-acquisition knows whether a map from
    before the target's loss ever existed."""

    def __init__(self, state: State, features: list[MapFeature]):
        self.state = state
        self.features = features
        self.rays: list = []
        self.last: SearchView | None = None
        self.in_view_ids: set[int] = set()
        self.first_mapped = 0 if any(not f.known for f in features) else None
        self._first_views_key: list | None = None
        self._first_views_cache = (np.zeros((0, 3)), np.zeros(0, bool), np.zeros((0, 2, 2)), np.zeros((0, 3, 3)))

    def views(self, pred: Prediction, Y: np.ndarray, cam: CameraIntrinsics, settings: MapSettings,
              sigma_pixel: float) -> tuple[np.ndarray, np.ndarray]:
        """For each feature predicted by ``pred`` (every feature of the map, in order; its point in
        ``Y`` (N, 3)): whether it is in the image and seen close enough to its first view for its
        template to hold (viewing angle and range against the first view's centre), and its
        measurement noise as a multiple of the pixel noise: the template's prediction degrades as
        the view moves from the first (a wrong plane guess warps it wrongly), ``1 + (angle /
        view_noise_angle)^2 + (log range ratio / log view_noise_scale)^2``; the target's points,
        printed corners whose plane is known, are located more closely (``known_sigma_px``)."""
        s = settings.views
        r0s, known = self.first_views()[:2]
        return _views_kernel(pred.uv, pred.valid, Y, self.state.r, r0s, known, float(cam.width),
                             float(cam.height), float(s.margin_px), math.cos(math.radians(s.max_view_angle_deg)),
                             math.cos(math.radians(s.max_view_angle_known_deg)), float(s.max_range_ratio),
                             float(s.max_range_ratio_known), float(s.view_noise_angle_deg),
                             math.log(s.view_noise_scale), (settings.startup.known_sigma_px / sigma_pixel) ** 2)

    def first_views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every feature's first-view centre (N, 3), whether it is a target point (N,), its match
        noise shape (N, 2, 2) and its first view's rotation (N, 3, 3) (the identity for the
        target's points), kept while the map holds the same features (none changes during a
        feature's life)."""
        key = [f.id for f in self.features]
        if self._first_views_key != key:
            # The features kept since the last call keep their rows (by id); only new ones are read.
            was = {fid: i for i, fid in enumerate(self._first_views_key or [])}
            rows = np.array([was.get(fid, -1) for fid in key], np.intp)
            kept = np.flatnonzero(rows >= 0)
            n = len(self.features)
            r0s, known = np.empty((n, 3)), np.empty(n, bool)
            shapes, R0s = np.empty((n, 2, 2)), np.empty((n, 3, 3))
            if len(kept):
                for new, old in zip((r0s, known, shapes, R0s), self._first_views_cache):
                    new[kept] = old[rows[kept]]
            for i in np.flatnonzero(rows < 0).tolist():
                f = self.features[i]
                r0s[i], known[i], shapes[i] = f.r0, f.known, f.noise_shape
                R0s[i] = f.R0 if f.R0 is not None and not f.known else np.eye(3)
            self._first_views_cache = (r0s, known, shapes, R0s)
            self._first_views_key = key
        return self._first_views_cache

    def world_points(self) -> np.ndarray:
        """(N, 3) every feature's point (an inverse-depth feature's at its current depth, at
        most 20 m)."""
        return self.points_and_linearity()[0]

    def point_covariances(self, ks: np.ndarray) -> np.ndarray:
        """(len(ks), 3, 3) features' point covariances, world, m^2 (an inverse-depth feature's
        through its conversion, at an inverse depth of at least 0.05 /m, as world_points)."""
        st = self.state
        cov = np.empty((len(ks), 3, 3))
        for i, k in enumerate(ks):
            sl = st.feature_slice(k)
            P = st.P[sl, sl]
            if st.kinds[k] == INVERSE_DEPTH:
                y = st.feature(k).copy()
                y[5] = max(y[5], 0.05)
                _, J = inverse_depth.to_point(y, st.anchors[k])
                cov[i] = J @ P @ J.T
            else:
                cov[i] = P
        return cov

    def known_in_id_order(self) -> np.ndarray:
        """The target's points' map indices, in the order of their ids (the target's corners')."""
        return np.array(sorted((k for k, f in enumerate(self.features) if f.known), key=lambda k: self.features[k].id),
                        np.intp)

    def points_and_linearity(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) every feature's point (as world_points) and (N,) each inverse-depth feature's
        linearity index from the camera (inf for points)."""
        st = self.state
        return inverse_depth.points_and_linearity_kernel(st.x, st.P, st.kinds, st.starts, st.anchors, st.r, 0.05)

    def noise_shapes(self, ks: np.ndarray) -> np.ndarray:
        """(m, 2, 2) features ``ks``' match noise shapes (MapFeature.noise_shape) turned from their
        first view's image axes into this view's by the camera's roll about its optic axis since."""
        _, _, A, R0 = self.first_views()
        return _rolled_shapes(quat_to_rotation(self.state.q), A, R0, np.asarray(ks, np.intp))

    def remove(self, ks: list[int], st: FrameStats, conversions: tuple[list, list, list] = ([], [], [])) -> None:
        """Features ``ks`` (ascending) out of the state and the map, counted in ``st``, and the
        ``conversions`` to points applied in the same rebuild."""
        self.state.edit_features(remove=ks, convert=conversions[0], kind=POINT, ys_new=conversions[1],
                                 Js=conversions[2])
        for k in reversed(ks):
            del self.features[k]
        st.deleted += len(ks)
