"""Where to look next when the task is to map (``--task explore``): the next fixation chosen over
the head's reachable cone by the information it is expected to bring (issue 49, part 2).

The objective
-------------
For each candidate view ``c`` (a direction on a grid about the mount's forward axis, fixated at
the map's median depth, whose joint angles the fixation IK finds within the joint ranges), the
camera's pose there is the present one moved by the head's known motion, and its covariance the
filter's carried through that motion. The mapped features predicted in that image (the filter's
own measurement model, in the image with a margin; at most ``measure_max``, the most uncertain
first, as MonoSLAM measures) give an EKF update with the filter's own Jacobians and pixel noise
``sigma_pixel``. The score is

    score(c) = I_pose(c) + w_new * empty(c) * [n_visible(c) >= min_visible]

* ``I_pose = 0.5 (log det Sigma - log det Sigma+)`` nats: the mutual information between the
  camera pose (6x6: position and the world-frame rotation error, from the r, q block) and the
  predicted measurements; 0 for a view with no mapped feature.
* ``empty`` : the fraction of the image's cells (``cells``) where no mapped feature is predicted:
  where SLAM would add new features (it starts them in empty parts of the image), growing the map;
  counted only where enough mapped features stay in view for SLAM to keep its pose through the
  move (``min_visible``). ``w_new`` (``novelty_nats``) is the worth, in nats, of a wholly new view.

Candidates within ``min_shift_deg`` of the present optic axis are left out (the present view is
measured every frame anyway); a candidate the head cannot reach is not a candidate.

Also :func:`viewing_cone_sr`, the solid angle the map's features span seen from the head.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from kinematics import HeadGeometry, forward_kinematics
from kinematics.camera import CameraIntrinsics, in_image

from ..gaze.estimate import UP, ik_point
from ..gaze.prompts import Prompt, turn_prompt, turned_mount
from ..slam.layout import FEATURE_DIMS, POSE_DIM
from ..slam.measurement import predict
from ..slam.quaternion import quat_from_rotation, quat_multiply, quat_to_rotation, rotation_derivatives
from ..slam.state import State


@dataclass(frozen=True)
class ExploreSettings:
    """azimuth_deg, elevation_deg : the candidate grid about the mount's forward axis (the optic
    axis at zero joint angles), turned about world up and then tilted, degrees (start, stop,
    step). margin_px : how far inside the image a feature must be predicted to count. cells :
    (columns, rows) the image's grid for the sparse-map term. novelty_nats : the worth of a view
    with no mapped feature in any cell, nats. min_visible : mapped features a view must keep for
    its novelty to count. measure_max : features in one predicted update, at most (SLAM's own).
    min_shift_deg : candidates nearer the present optic axis are left out. default_depth_m : the
    fixation depth with no map in front. around_deg : the azimuths (start, stop, step) of the
    views all round the wearer that :func:`choose_beyond_reach` scores. ask_margin_nats : a view
    beyond the head's reach must score this much more than the best within it for the wearer to
    be asked to turn."""

    azimuth_deg: tuple[float, float, float] = (-80.0, 80.0, 20.0)
    elevation_deg: tuple[float, float, float] = (-40.0, 40.0, 20.0)
    margin_px: float = 12.0
    cells: tuple[int, int] = (4, 3)
    novelty_nats: float = 0.5
    min_visible: int = 8
    measure_max: int = 60
    min_shift_deg: float = 10.0
    default_depth_m: float = 1.0
    around_deg: tuple[float, float, float] = (-180.0, 160.0, 20.0)
    ask_margin_nats: float = 0.25

    def __post_init__(self):
        for name in ("azimuth_deg", "elevation_deg", "around_deg"):
            a, b, s = getattr(self, name)
            if not (math.isfinite(a) and math.isfinite(b) and a <= b and s > 0):
                raise ValueError(f"ExploreSettings.{name} = {(a, b, s)} must be (start, stop, step) with start <= stop "
                                 f"and step > 0, degrees")
        if not (self.margin_px >= 0 and self.novelty_nats >= 0 and self.min_shift_deg >= 0
                and self.ask_margin_nats >= 0):
            raise ValueError("ExploreSettings: margin_px, novelty_nats, min_shift_deg and ask_margin_nats must be >= 0")
        if not (self.cells[0] >= 1 and self.cells[1] >= 1 and self.measure_max >= 1 and self.min_visible >= 0):
            raise ValueError("ExploreSettings: cells must be >= 1 each, measure_max >= 1, min_visible >= 0")
        if not self.default_depth_m > 0:
            raise ValueError(f"ExploreSettings.default_depth_m = {self.default_depth_m} must be positive, m")


@dataclass(frozen=True)
class ViewScores:
    """Scores of views (n of them): pose_info (n,) nats, n_visible (n,) mapped features predicted
    in the image, empty (n,) the fraction of the image's cells with none, along (n,) nats: the
    information about the pose along one direction, ``0.5 ln(w' Sigma w / w' Sigma+ w)`` (zeros
    when no direction was given)."""

    pose_info: np.ndarray
    n_visible: np.ndarray
    empty: np.ndarray
    along: np.ndarray


@dataclass(frozen=True)
class ExploreChoice:
    """The candidates and the choice. directions_world (n, 3) unit; points_world (n, 3) m, the
    fixation points; reachable (n,); q (n, 3) rad (NaN where unreachable); pose_info, empty,
    n_visible, score (n,) (score -inf where not a candidate); best : the chosen index, -1 if none."""

    directions_world: np.ndarray
    points_world: np.ndarray
    reachable: np.ndarray
    q: np.ndarray
    pose_info: np.ndarray
    empty: np.ndarray
    n_visible: np.ndarray
    score: np.ndarray
    best: int

    @property
    def target(self) -> np.ndarray | None:
        """(3,) the chosen fixation point, m, world (None if no candidate)."""
        return None if self.best < 0 else self.points_world[self.best].copy()


def _moved_pose(x: np.ndarray, T_cam_cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera block's r, q moved by a known relative pose (4, 4) (the head's motion):
    ``r' = r + R(q) t``, ``q' = q * q_rel``. Returns x' (the r, q entries replaced) and
    J (7, 7) = d(r', q')/d(r, q)."""
    r, q = x[0:3], x[3:7]
    t, q_rel = T_cam_cand[:3, 3], quat_from_rotation(T_cam_cand[:3, :3])
    x_new = x.copy()
    x_new[0:3] = r + quat_to_rotation(q) @ t
    x_new[3:7] = quat_multiply(q, q_rel)
    J = np.zeros((POSE_DIM, POSE_DIM))
    J[0:3, 0:3] = np.eye(3)
    J[0:3, 3:7] = (rotation_derivatives(q) @ t).T
    J[3:7, 3:7] = np.stack([quat_multiply(e, q_rel) for e in np.eye(4)], axis=1)   # linear in q
    return x_new, J


def _pose_projection(q: np.ndarray) -> np.ndarray:
    """(6, 7): (r, q) perturbations to (position, world-frame rotation vector): ``dtheta =
    2 vec(dq * conj(q))`` (a small rotation applied on the left)."""
    qc = np.array([q[0], -q[1], -q[2], -q[3]]) / float(q @ q)
    G = np.zeros((6, POSE_DIM))
    G[0:3, 0:3] = np.eye(3)
    G[3:6, 3:7] = 2.0 * np.stack([quat_multiply(e, qc)[1:] for e in np.eye(4)], axis=1)
    return G


def _logdet(A: np.ndarray) -> float:
    sign, ld = np.linalg.slogdet(A)
    return ld if sign > 0 else -np.inf


def score_views(state: State, cam: CameraIntrinsics, T_cam_cands: np.ndarray, sigma_pixel: float,
                margin_px: float = 12.0, measure_max: int = 60, cells: tuple[int, int] = (4, 3),
                direction: np.ndarray | None = None) -> ViewScores:
    """The expected pose information of views of the map in ``state``.

    state : SLAM's state (camera block, then features). T_cam_cands : (n, 4, 4) each candidate
    camera pose relative to the present one (the head's motion). sigma_pixel : the measurement
    noise, px per axis. direction : (6,) a direction in the pose's (position m, world rotation
    rad) space whose information is scored too (``ViewScores.along``). Returns
    :class:`ViewScores`; the objective is the module docstring's.
    """
    T_cam_cands = np.asarray(T_cam_cands, float).reshape(-1, 4, 4)
    if not sigma_pixel > 0:
        raise ValueError(f"sigma_pixel = {sigma_pixel} must be positive, px")
    w = None if direction is None else np.asarray(direction, float).reshape(6)
    out_along = []
    n_f = state.n_features
    ks = np.arange(n_f, dtype=np.intp)
    dims = FEATURE_DIMS[state.kinds] if n_f else np.zeros(0, np.intp)
    out_info, out_vis, out_empty = [], [], []
    cw, ch = cells
    for T in T_cam_cands:
        x_new, J = _moved_pose(state.x, T)
        pred = predict(state, ks, cam, x=x_new) if n_f else None
        vis = np.zeros(0, bool) if pred is None else pred.valid & in_image(cam, pred.uv, margin_px)
        sel = np.flatnonzero(vis)
        occupied = set()
        for u, v in (pred.uv[sel] if len(sel) else np.zeros((0, 2))):
            occupied.add((min(int(u * cw / cam.width), cw - 1), min(int(v * ch / cam.height), ch - 1)))
        out_vis.append(len(sel))
        out_empty.append(1.0 - len(occupied) / (cw * ch))
        if not len(sel):
            out_info.append(0.0)
            out_along.append(0.0)
            continue
        # The covariance over the pose and the seen features, the pose carried through the head's motion.
        cols = np.concatenate([np.arange(POSE_DIM)] + [np.arange(state.starts[k], state.starts[k] + dims[k])
                                                       for k in sel])
        P = state.P[np.ix_(cols, cols)].copy()
        P[:POSE_DIM, :] = J @ P[:POSE_DIM, :]
        P[:, :POSE_DIM] = P[:, :POSE_DIM] @ J.T
        H = np.zeros((2 * len(sel), len(cols)))
        c = POSE_DIM
        for i, k in enumerate(sel):
            H[2 * i:2 * i + 2, :POSE_DIM] = pred.H_c[k]
            H[2 * i:2 * i + 2, c:c + dims[k]] = pred.H_f[k][:, :dims[k]]
            c += dims[k]
        if len(sel) > measure_max:
            # The most uncertain predictions first: they teach the filter most (MonoSLAM's rule).
            PHt = P @ H.T
            s_tr = np.einsum("ij,ji->i", H, PHt).reshape(-1, 2).sum(axis=1)
            keep = np.sort(np.argsort(-s_tr)[:measure_max])
            H = H[np.ravel(np.stack([2 * keep, 2 * keep + 1], axis=1))]
        PHt = P @ H.T
        S = H @ PHt + sigma_pixel**2 * np.eye(len(H))
        G = _pose_projection(x_new[3:7])
        A = G @ PHt[:POSE_DIM]
        Sigma = G @ P[:POSE_DIM, :POSE_DIM] @ G.T
        Sigma_post = Sigma - A @ np.linalg.solve(S, A.T)
        out_info.append(max(0.0, 0.5 * (_logdet(Sigma) - _logdet(0.5 * (Sigma_post + Sigma_post.T)))))
        if w is not None:
            before, after = float(w @ Sigma @ w), float(w @ Sigma_post @ w)
            out_along.append(0.5 * math.log(before / after) if before > 0 and after > 0 else 0.0)
    along = np.array(out_along, float) if w is not None else np.zeros(len(out_info))
    return ViewScores(np.array(out_info, float), np.array(out_vis, int), np.array(out_empty, float), along)


def grid_angles(settings: ExploreSettings) -> tuple[np.ndarray, np.ndarray]:
    """The settings' grid, azimuth-major: each direction's azimuth and elevation (n,), (n,) rad
    (``azimuth_deg`` and ``elevation_deg``, each (start, stop, step) degrees, both ends in)."""
    az = np.radians(np.arange(settings.azimuth_deg[0], settings.azimuth_deg[1] + 1e-9, settings.azimuth_deg[2]))
    el = np.radians(np.arange(settings.elevation_deg[0], settings.elevation_deg[1] + 1e-9, settings.elevation_deg[2]))
    A, E = np.meshgrid(az, el, indexing="ij")
    return A.ravel(), E.ravel()


def candidate_directions(head: HeadGeometry, T_world_mount: np.ndarray, settings: ExploreSettings) -> np.ndarray:
    """(n, 3) world unit directions on the settings' grid: the mount's forward axis (the optic
    axis at zero joint angles, levelled) turned by each azimuth about world up, then tilted by
    each elevation."""
    R_wm = np.asarray(T_world_mount, float)[:3, :3]
    f = R_wm @ forward_kinematics(head, np.zeros(3)).optic_axis
    f_h = f - (f @ UP) * UP
    if np.linalg.norm(f_h) < 1e-6:              # the mount looking straight up or down: its x
        f_h = R_wm[:, 0] - (R_wm[:, 0] @ UP) * UP
    f_h /= np.linalg.norm(f_h)
    left = np.cross(UP, f_h)
    A, E = grid_angles(settings)
    d = (np.cos(E) * np.cos(A))[:, None] * f_h + (np.cos(E) * np.sin(A))[:, None] * left + np.sin(E)[:, None] * UP
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(frozen=True)
class CandidateViews:
    """The views the head can turn to: directions (n, 3) world unit, points (n, 3) m the
    fixation points (at the map's median depth), reachable (n,), q (n, 3) rad (NaN where
    unreachable), T_cam_cand (n, 4, 4) each view's camera pose relative to the present one, and
    candidate (n,): reachable and at least ``min_shift_deg`` from the present optic axis."""

    directions: np.ndarray
    points: np.ndarray
    reachable: np.ndarray
    q: np.ndarray
    T_cam_cand: np.ndarray
    candidate: np.ndarray


def candidate_views(head: HeadGeometry, T_world_mount: np.ndarray, q_current: np.ndarray,
                    settings: ExploreSettings = ExploreSettings(),
                    map_points_world: np.ndarray | None = None) -> CandidateViews:
    """The settings' grid of directions, fixated at the map's median depth from the camera
    (``map_points_world`` (N, 3) m; None: ``default_depth_m``), each solved by the fixation IK
    from ``q_current`` (3,) rad on the mount's pose ``T_world_mount`` (4, 4)."""
    T_world_mount = np.asarray(T_world_mount, float)
    q_current = np.asarray(q_current, float)
    pose_now = forward_kinematics(head, q_current)
    T_world_cam_now = T_world_mount @ pose_now.T_mount_cam
    c_world = T_world_cam_now[:3, 3]
    depth = settings.default_depth_m
    if map_points_world is not None and len(map_points_world):
        dist = np.linalg.norm(np.asarray(map_points_world, float) - c_world, axis=1)
        dist = dist[np.isfinite(dist) & (dist > 0.05)]
        if len(dist):
            depth = float(np.median(dist))
    D = candidate_directions(head, T_world_mount, settings)
    n = len(D)
    pts = c_world + depth * D
    axis_now = T_world_cam_now[:3, 2]
    reach = np.zeros(n, bool)
    Q = np.full((n, 3), np.nan)
    T_rel = np.tile(np.eye(4), (n, 1, 1))
    T_cam_world = np.linalg.inv(T_world_cam_now)
    for i, p in enumerate(pts):
        res = ik_point(head, p, T_world_mount, q_current)
        if not res.reachable:
            continue
        reach[i] = True
        Q[i] = res.q
        T_rel[i] = T_cam_world @ T_world_mount @ forward_kinematics(head, res.q).T_mount_cam
    far = np.degrees(np.arccos(np.clip(D @ axis_now, -1, 1))) >= settings.min_shift_deg
    return CandidateViews(D, pts, reach, Q, T_rel, reach & far)


def choose_fixation(head: HeadGeometry, cam: CameraIntrinsics, state: State, T_world_mount: np.ndarray,
                    q_current: np.ndarray, sigma_pixel: float, settings: ExploreSettings = ExploreSettings(),
                    map_points_world: np.ndarray | None = None) -> ExploreChoice:
    """The next fixation: the candidate with the highest score (module docstring).

    head, cam : the head and its camera. state : SLAM's state (its camera block is the present
    camera pose). T_world_mount : (4, 4) the mount's pose. q_current : (3,) rad, the head's
    commanded angles (the IK starts there, and the present optic axis is read there).
    sigma_pixel : the filter's measurement noise, px. map_points_world : (N, 3) m, the map's
    points (for the median depth; None: the features' own points are not read, the default
    depth is used).
    """
    c = candidate_views(head, T_world_mount, q_current, settings, map_points_world)
    n, cand = len(c.directions), c.candidate
    info = np.zeros(n)
    empty = np.ones(n)
    nvis = np.zeros(n, int)
    if cand.any():
        s = score_views(state, cam, c.T_cam_cand[cand], sigma_pixel, settings.margin_px, settings.measure_max,
                        settings.cells)
        info[cand], empty[cand], nvis[cand] = s.pose_info, s.empty, s.n_visible
    score = info + settings.novelty_nats * empty * (nvis >= settings.min_visible)
    score = np.where(cand, score, -np.inf)
    best = int(np.argmax(score)) if cand.any() else -1
    return ExploreChoice(c.directions, c.points, c.reachable, c.q, info, empty, nvis, score, best)


@dataclass(frozen=True)
class BeyondReach:
    """The best view out of the head's reach now, were the wearer to turn as ``prompt`` asks:
    its fixation point (3,) m, its score (nats, as explore's), and the prompt (a ``turn``)."""

    point_world: np.ndarray
    score: float
    prompt: Prompt


def choose_beyond_reach(head: HeadGeometry, cam: CameraIntrinsics, state: State, T_world_mount: np.ndarray,
                        q_current: np.ndarray, sigma_pixel: float, settings: ExploreSettings = ExploreSettings(),
                        map_points_world: np.ndarray | None = None) -> BeyondReach | None:
    """The best view all round the wearer (``around_deg`` azimuths from the mount's forward
    axis, explore's elevations) that the head cannot reach now, scored as explore scores its candidates with
    the wearer turned to face it (the camera where the head would put it on the turned mount),
    and the request to make that turn. None if no such view. One fixation IK per direction: the
    wearer prompts' smallest-turn search (up to 80 solves each) would stall the control step."""
    around = ExploreSettings(azimuth_deg=settings.around_deg, elevation_deg=settings.elevation_deg,
                             min_shift_deg=0.0, default_depth_m=settings.default_depth_m)
    c = candidate_views(head, T_world_mount, q_current, around, map_points_world)
    az, _ = grid_angles(around)                # each candidate's azimuth from the mount's forward axis
    T_world_mount = np.asarray(T_world_mount, float)
    T_cam_world = np.linalg.inv(T_world_mount @ forward_kinematics(head, np.asarray(q_current, float)).T_mount_cam)
    ks, T_rel = [], []
    for k in np.flatnonzero(~c.reachable):
        T_turned = turned_mount(T_world_mount, float(az[k]))
        res = ik_point(head, c.points[k], T_turned, q_current)
        if res.reachable:
            ks.append(k)
            T_rel.append(T_cam_world @ T_turned @ forward_kinematics(head, res.q).T_mount_cam)
    if not ks:
        return None
    s = score_views(state, cam, np.array(T_rel), sigma_pixel, settings.margin_px, settings.measure_max, settings.cells)
    score = s.pose_info + settings.novelty_nats * s.empty * (s.n_visible >= settings.min_visible)
    b = int(np.argmax(score))
    k = ks[b]
    return BeyondReach(c.points[k].copy(), float(score[b]), turn_prompt(float(az[k])))


def viewing_cone_sr(points_world: np.ndarray, centre_world: np.ndarray) -> float:
    """The solid angle, sr, of the convex cone spanned by the directions from ``centre_world``
    (3,) to ``points_world`` (N, 3): the area of the spherical convex hull of the unit
    directions. Directions more than 85 degrees from their mean are left out (the hull is taken
    in the gnomonic projection about the mean, which needs them in front); 0 with fewer than 3."""
    d = np.asarray(points_world, float).reshape(-1, 3) - np.asarray(centre_world, float)
    d = d[np.isfinite(d).all(axis=1) & (np.linalg.norm(d, axis=1) > 1e-9)]
    if len(d) < 3:
        return 0.0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    m = d.mean(axis=0)
    m /= np.linalg.norm(m)
    d = d[d @ m > math.cos(math.radians(85.0))]
    if len(d) < 3:
        return 0.0
    e1 = np.cross(m, [1.0, 0, 0] if abs(m[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    g = np.stack([d @ e1, d @ e2], axis=1) / (d @ m)[:, None]     # gnomonic: great circles -> lines
    try:
        hull = ConvexHull(g)
    except QhullError:
        return 0.0                                       # the directions lie on one great circle
    v = d[hull.vertices]                                  # counter-clockwise in the projection
    # The spherical polygon's area as a fan of triangles from the mean (Van Oosterom-Strackee).
    total = 0.0
    for a, b in zip(v, np.roll(v, -1, axis=0)):
        num = float(m @ np.cross(a, b))
        den = 1.0 + float(m @ a) + float(a @ b) + float(b @ m)
        total += 2.0 * math.atan2(num, den)
    return abs(total)
