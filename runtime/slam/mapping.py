"""Map management: features deleted (MonoSLAM's ratio rule, the consistency test, the size
cap), inverse-depth features converted to points, new features added where the motion keeps
them in view, plane normals fitted to the features' looks and to their map neighbours, and the
paper's particle rays refined and promoted."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from kinematics.camera import CameraIntrinsics, in_image, lens_kernel_args, unproject, unproject_jacobian
from kinematics.camera import project as project_points

from .config import MapSettings
from .corners import min_template_std, new_features, noise_sigma
from .features import INVERSE_DEPTH, POINT, inverse_depth
from .features import particles as depth_init
from .filter import FeatureNotMeasurable, add_inverse_depth_features, add_point_feature, point_conversions
from .appearance.normals import fit_normal_kernel
from .measurement import predict_points, predict_uv, ray_from_pixel
from .motion import f_and_dfdx
from .quaternion import quat_to_rotation
from .records import FrameStats
from .appearance import search
from .state import POSE_DIM, SlamNumericalError
from .appearance import first_view_patch, local_plane_normal, patch_half
from .map_feature import MapFeature
from .views import SlamMap, _from_first_view


def cap_victims(excess: int, last_seen: np.ndarray, in_view: np.ndarray, is_point: np.ndarray) -> np.ndarray:
    """The ``excess`` candidates (indices into the (m,) arrays) that leave a map over its size
    cap: those predicted in view this frame last (the frame's tracking rests on them); of the
    rest, inverse-depth features before points, and within each the one seen longest ago (frame
    index ``last_seen``) first. A point out of view is the map's memory of a place, which
    re-observed pulls a drifted pose back; an inverse-depth feature out of view has an
    unsettled depth, and seen again it constrains the pose little."""
    order = np.lexsort((np.asarray(last_seen), np.asarray(is_point, bool), np.asarray(in_view, bool)))
    return order[:max(int(excess), 0)]


def stay_in_view(cam: CameraIntrinsics, margin_px: float, x_v: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(k,) bool: whether each pixel's point (at 1 m) is still inside the image, ``margin_px``
    in, after 0.6 s of the motion model's constant velocity (MonoSLAM places new features
    where the motion will keep them in view)."""
    rays = unproject(cam, uv)
    X = x_v[:3] + (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ quat_to_rotation(x_v[3:7]).T
    x_next, _ = f_and_dfdx(x_v, 0.6)
    uv_next = project_points(cam, (X - x_next[:3]) @ quat_to_rotation(x_next[3:7]))
    return in_image(cam, uv_next, margin=margin_px)      # NaN: outside


class FeatureIds:
    """The session's feature ids: each new feature, ray or target point takes the next."""

    def __init__(self, next_id: int = 0):
        self.next_id = int(next_id)

    def new(self) -> int:
        self.next_id += 1
        return self.next_id - 1


class ImageNoise:
    """The contrast a new feature's template needs to be matched through the camera's noise
    (corners.min_template_std); the noise is estimated from the image every ``noise_every``
    frames, since the exposure's gain moves it slowly. Shared by a session's tracks."""

    def __init__(self, noise_every: int, match_score: float):
        self.noise_every, self.match_score = int(noise_every), float(match_score)
        self._noise: tuple[int, float] | None = None   # (frame, image noise sigma) last estimated

    def contrast_floor(self, g: np.ndarray, frame: int) -> float:
        if self._noise is None or frame - self._noise[0] >= self.noise_every:
            self._noise = (frame, noise_sigma(g))
        return min_template_std(self._noise[1], self.match_score)


class MapManager:
    """One track's map management. cam, settings : the camera and the map's settings;
    sigma_pixel : a match's standard deviation, px; template_px : the templates' side at this
    image width; linearity_threshold : inverse depth converts to a point below it; nis_limit :
    the consistency test's chi-square bound; ids, noise : the session's feature ids and image
    noise."""

    def __init__(self, cam: CameraIntrinsics, settings: MapSettings, sigma_pixel: float, template_px: int,
                 linearity_threshold: float, nis_limit: float, ids: FeatureIds, noise: ImageNoise):
        self.cam, self.settings, self.sigma_pixel = cam, settings, float(sigma_pixel)
        self.template_px, self.linearity_threshold, self.nis_limit = int(template_px), linearity_threshold, nis_limit
        self.ids, self.noise = ids, noise

    def conversions(self, m: SlamMap, st: FrameStats) -> tuple[list, list, list]:
        """The inverse-depth features whose depth is now well represented in Euclidean
        coordinates (Civera et al.'s linearity index) and their points and Jacobians, for
        :meth:`delete` to apply: none if any conversion is not finite."""
        state = m.state
        _, L = m.points_and_linearity()
        ks = np.flatnonzero(L < self.linearity_threshold).tolist()
        ys, Js = point_conversions(state, ks) if ks else ([], [])
        if not all(np.isfinite(y).all() and np.isfinite(J).all() for y, J in zip(ys, Js)):
            ks, ys, Js = [], [], []
        st.converted += len(ks)
        st.initialising = int((state.kinds == INVERSE_DEPTH).sum()) - len(ks)
        return ks, ys, Js

    def delete(self, m: SlamMap, st: FrameStats, frame: int,
               conversions: tuple[list, list, list] = ([], [], [])) -> None:
        """MonoSLAM's rule (inlier matches below ``delete_ratio`` of searches after
        ``delete_min_attempts``), a quicker one for new features that fail from the start, and
        the map's size cap: beyond ``max_features`` natural features go in :func:`cap_victims`'
        order (out of view first, inverse-depth before points, seen longest ago first). The
        ``conversions`` (:meth:`conversions`) are applied in the same rebuild of the state, and
        the rules see the converted features as points."""
        s = self.settings
        state = m.state
        kinds = state.kinds.copy()
        kinds[conversions[0]] = POINT
        inv = np.flatnonzero(kinds == INVERSE_DEPTH)
        behind = set(inv[state.x[state.starts[inv] + 5] < 0].tolist())   # rho < 0
        bad = []
        d = s.deletion
        min_attempts, ratio, young = d.delete_min_attempts, d.delete_ratio, d.delete_young_attempts
        window, nis_limit = d.consistency_window, self.nis_limit
        for k, f in enumerate(m.features):
            if f.known:
                continue
            a, n = f.attempts, f.successes
            if a >= min_attempts and n < ratio * a:
                bad.append(k)
            elif a >= young and n <= a // 4:
                bad.append(k)
            elif len(f.nis) >= window and sum(f.nis) > nis_limit:
                # Its innovations over the window fail the chi-square test: not a fixed point
                # (a T-junction of a near edge and a far background, a reflection).
                bad.append(k)
            elif k in behind:
                bad.append(k)          # its depth went behind the first view: a mismatch's trace
        excess = len(m.features) - len(bad) - s.deletion.max_features
        if excess > 0:
            gone = set(bad)
            keep = np.array([k for k in range(len(m.features)) if k not in gone and not m.features[k].known],
                            np.intp)
            fs = [m.features[k] for k in keep]
            victims = cap_victims(excess, np.array([f.last_seen for f in fs]),
                                  np.array([f.id in m.in_view_ids for f in fs], bool), kinds[keep] == POINT)
            bad += keep[victims].tolist()
        bad = sorted(set(bad))
        ks, ys, Js = conversions
        gone = set(bad)
        keep_conv = [i for i, k in enumerate(ks) if k not in gone]   # a feature removed is not converted
        if keep_conv or bad:
            m.remove(bad, st, ([ks[i] for i in keep_conv], [ys[i] for i in keep_conv], [Js[i] for i in keep_conv]))

    def _occupied(self, m: SlamMap) -> np.ndarray:
        """Pixels new features keep away from: where every feature is predicted, except those
        searched for and not matched this frame (their place is free for new ones)."""
        uv = predict_uv(m.state, np.arange(m.state.n_features), self.cam)
        failed = set(m.last.ids[~m.last.used].tolist()) if m.last is not None else set()
        free = np.array([f.id in failed for f in m.features], bool).reshape(-1)
        occupied = [uv[np.isfinite(uv).all(axis=1) & ~free]]
        occupied += [p.uv0[None] for _, p, _, _ in m.rays]
        return np.concatenate(occupied) if occupied else np.zeros((0, 2))

    def add(self, g: np.ndarray, m: SlamMap, st: FrameStats, frame: int, visible: int) -> None:
        """New features on Shi-Tomasi corners in empty parts of ``g`` when fewer than
        ``visible_min`` were matched (``visible``): inverse-depth features in the state, or
        particle rays (``features = "particles"``)."""
        s, cam = self.settings, self.cam
        if s.features == "particles":
            n = min(s.depth_init.max_initialising - len(m.rays), s.measure.new_per_frame)
        else:
            n = min(s.measure.new_per_frame, s.measure.visible_min - visible)
        if n <= 0:
            return
        scale = cam.width / 640.0
        # Where the motion keeps them in view first, else any (MonoSLAM's placement).
        chosen = new_features(g, self._occupied(m), 4 * n, size=self.template_px,
                              min_std=self.noise.contrast_floor(g, frame),
                              min_distance=s.measure.min_distance_px * scale,
                              border=max(int(20 * scale), self.template_px),
                              prefer=lambda uv: stay_in_view(cam, s.views.margin_px, m.state.x_v, uv), take=n)
        R0 = quat_to_rotation(m.state.q)
        ph = patch_half(self.template_px)
        if s.features == "particles":
            for uv, tpl in chosen:
                origin, d = ray_from_pixel(m.state.x_v, uv, cam)[:2]
                pi = s.depth_init
                p = depth_init.DepthParticles.create(origin, d, tpl, uv, pi.particles, pi.depth_near_m, pi.depth_far_m)
                m.rays.append((self.ids.new(), p, R0.copy(), first_view_patch(g, uv, ph)))
        elif chosen:
            uvs = np.array([uv for uv, _ in chosen], float)
            rays_cam, J_rays = unproject_jacobian(cam, uvs)     # for the states and the normals
            rays = rays_cam @ R0.T
            ok = np.isfinite(rays).all(axis=1)
            chosen, uvs, rays = [c for c, o in zip(chosen, ok) if o], uvs[ok], rays[ok]
            try:
                added = add_inverse_depth_features(m.state, uvs, cam, *self._depth_prior(m),
                                                   self.sigma_pixel**2, rays=(rays_cam[ok], J_rays[ok]))
            except (FeatureNotMeasurable, SlamNumericalError):
                added = []
            if len(added) == len(chosen):
                for (uv, tpl), ray in zip(chosen, rays):
                    if m.first_mapped is None:
                        m.first_mapped = frame
                    m.features.append(MapFeature(self.ids.new(), tpl, frame, m.state.r.copy(),
                                                    patch=first_view_patch(g, uv, ph), uv0=np.asarray(uv, float),
                                                    R0=R0.copy(), normal=-ray / np.linalg.norm(ray), last_seen=frame))
                st.added += len(added)
            elif added:                                 # cannot happen: the rays were checked above
                m.state.remove_features(added)
        st.initialising = len(m.rays) if s.features == "particles" else int((m.state.kinds == INVERSE_DEPTH).sum())

    def _depth_prior(self, m: SlamMap) -> tuple[float, float]:
        """New inverse-depth features' prior (rho0, sigma_rho), 1/m: centred on the points this
        frame's measurement used (inverse_depth.scene_prior) unless the settings fix it."""
        idp, sv = self.settings.inverse_depth, m.last
        prior = (idp.rho0, idp.sigma_rho)
        if not idp.scene_depth_prior or sv is None:
            return prior
        used = set(sv.ids[sv.used].tolist())         # by id: _delete may have renumbered the map
        ks = [k for k, f in enumerate(m.features) if f.id in used]
        return inverse_depth.scene_prior(m.world_points()[ks], m.state.r, *prior, spread=idp.scene_depth_spread,
                                         relative_width=idp.scene_relative_width)

    def normals_from_views(self, g: np.ndarray, m: SlamMap) -> None:
        """The plane normals of features matched this frame whose view has turned far enough
        from their first, from their appearance (after Molton, Davison and Reid, "Locally planar
        patch features for real-time structure from motion", BMVC 2004): of candidate normals,
        the one whose warp of the first-view patch best matches the image at the match. A
        fronto-parallel guess warps a floor or wall seen obliquely wrongly, and its template
        stops matching a few tens of degrees on."""
        s, cam = self.settings, self.cam
        sv = m.last
        if sv is None or not len(sv.ks):
            return
        feats = m.features
        cand = [(j, k) for j, k in zip(np.flatnonzero(sv.used).tolist(), sv.ks[sv.used].tolist())
                if k < len(feats) and feats[k].id == sv.ids[j] and not feats[k].known
                and feats[k].patch is not None and feats[k].normal is not None]
        if not cand:
            return
        js, ks = np.array(cand).T
        r = m.state.r
        Y = m.world_points()
        r0s = np.array([feats[k].r0 for k in ks], float).reshape(-1, 3)
        angle = np.degrees(np.arccos(_from_first_view(np.ascontiguousarray(Y[ks]), np.asarray(r, float), r0s)[0]))
        gain = angle - np.array([feats[k].normal_view_deg for k in ks])
        nm = s.normals
        due = [i for i in np.argsort(-gain, kind="stable")[:nm.normals_per_frame] if gain[i] >= nm.normal_step_deg]
        if not due:
            return
        R = quat_to_rotation(m.state.x_v[3:7])
        model, lens = lens_kernel_args(cam)
        g32 = np.ascontiguousarray(g, np.float32)
        tilts = np.array([0.0, 20.0, 40.0, 60.0])
        for i in due:
            f = feats[ks[i]]
            n, score, current = fit_normal_kernel(
                g32, f.patch.astype(np.float32, copy=False), self.template_px, f.first_view_rays(cam),
                np.asarray(f.r0, float), np.ascontiguousarray(Y[ks[i]], float), np.asarray(r, float), R, model, lens,
                np.asarray(sv.z[js[i]], float), np.asarray(f.normal, float), tilts, 8, 10.0)
            f.normal_view_deg = float(angle[i])
            if score < current - s.normals.normal_margin:
                f.normal = n / np.linalg.norm(n)

    def normals_from_map(self, m: SlamMap) -> None:
        """Give each natural point feature whose normal was not fitted to its looks
        (normals_from_views) the normal of the plane through it and its map neighbours, facing
        its first view."""
        points = np.flatnonzero(m.state.kinds == POINT)
        if len(points) < 4:
            return
        Y = m.world_points()[points]
        neighbours = cKDTree(Y).query_ball_point(Y, self.settings.normals.plane_radius_m)
        for j, k in enumerate(points):
            f = m.features[k]
            if not f.known and len(neighbours[j]) >= 4 and f.normal_view_deg == 0:
                n = local_plane_normal(Y[neighbours[j]], neighbours[j].index(j), np.inf,
                                       self.settings.normals.plane_tol_m)
                if n is not None:
                    f.normal, f.normal_from_map = (n if n @ (f.r0 - Y[j]) > 0 else -n), True

    # -- particles (the paper's) --
    def refine_rays(self, g: np.ndarray, m: SlamMap, st: FrameStats, frame: int) -> None:
        """The particle rays' depth pdfs updated by their matches in ``g`` (the paper's
        factored sampling); a ray whose pdf has become Gaussian is promoted to a point."""
        s, cam = self.settings, self.cam
        x_v = m.state.x_v
        P_pose = m.state.P[:POSE_DIM, :POSE_DIM]
        R = self.sigma_pixel**2 * np.eye(2)
        keep = []
        for fid, p, R0, patch in m.rays:
            def project(points):
                uv, H_c, valid = predict_points(x_v, points, cam)
                S = np.full((len(points), 2, 2), np.nan)
                S[valid] = H_c[valid] @ P_pose @ np.swapaxes(H_c[valid], 1, 2) + R
                return uv, S

            def match(uv, S):
                ok = np.isfinite(uv).all(axis=1) & np.isfinite(S).all(axis=(1, 2))
                if not ok.any():
                    return None
                lo = (uv[ok] - 3 * np.sqrt(S[ok][:, [0, 1], [0, 1]])).min(axis=0)
                hi = (uv[ok] + 3 * np.sqrt(S[ok][:, [0, 1], [0, 1]])).max(axis=0)
                c, half = (lo + hi) / 2, (hi - lo) / 2
                hit = search(g, p.template, c, np.diag((half / 3) ** 2) + 1e-9, n_sigma=3.0,
                             max_score=s.views.match_score, max_area=120_000)
                return (hit.uv, float(np.prod(2 * half + 1))) if hit.found else None

            depth_init.step(p, project, match, s.depth_init.prune, s.depth_init.outlier)
            if p.is_gaussian(s.depth_init.gauss_ratio) and p.frames >= s.depth_init.min_init_frames:
                self._promote(m, fid, p, R0, patch, st, frame)
            elif p.frames < s.depth_init.max_init_frames and p.failures < 10 and len(p.depths) > 0:
                keep.append((fid, p, R0, patch))
        m.rays = keep
        st.initialising = len(m.rays)

    def _promote(self, m: SlamMap, fid, p, R0, patch, st: FrameStats, frame: int) -> None:
        y = p.origin + p.mean * p.direction
        uv = project_points(self.cam, ((y - m.state.r) @ quat_to_rotation(m.state.q))[None])[0]
        if not np.isfinite(uv).all():
            return
        depth = float(np.linalg.norm(y - m.state.r))
        try:
            add_point_feature(m.state, uv, depth, (self.settings.depth_init.promote_std_gain * p.std) ** 2,
                              self.sigma_pixel**2, self.cam)
        except (SlamNumericalError, FeatureNotMeasurable):
            return
        normal = (p.origin - y) / np.linalg.norm(p.origin - y)
        if m.first_mapped is None:
            m.first_mapped = frame
        m.features.append(MapFeature(fid, p.template, frame, p.origin.copy(), patch=patch, uv0=p.uv0, R0=R0,
                                        normal=normal, last_seen=frame))
        st.added += 1
