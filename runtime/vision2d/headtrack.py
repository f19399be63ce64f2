"""Head tracking (paper section 3, item 2, Fig. 5): follow a person's head (a remote operator, or a
person whose attention the wearable follows) and give its yaw, pitch and roll, which
:func:`runtime.gaze.slaving.head_to_joint_targets` maps onto the wearable's own joints
("slaving", Fig. 5a). The head model and the pose conventions are :mod:`.headmodel`'s.

The tracker follows Fig. 5b: a polyhedral shape model of the head with a learned colour model
guiding a feature tracker.

1. **Start** (:meth:`HeadTracker.start`), with a known pose (the operator looks at the camera:
   :func:`head_pose` with yaw = pitch = roll = 0 at a known distance, or any pose given):
   the model's silhouette under that pose gives the head region; a hue-saturation histogram of the
   head's pixels against the background's is the colour model (a ratio histogram, so background
   colours that also occur on the head are discounted). Shi-Tomasi corners inside the colour blob
   and on model faces facing the camera are back-projected onto the polyhedron (ray-polyhedron
   intersection), giving each corner a 3D
   model point (Embree ray casting, :class:`kinematics.rays.RayCaster`).
2. **Each frame** (:meth:`HeadTracker.update`): the corners are tracked by pyramidal Lucas-Kanade
   with a forward-backward check, started from a constant-velocity prediction, and RANSAC over
   sample matches (``cv2.solvePnPRansac``) gives a first pose. Then the keyframes' corners are
   re-found near that pose: each keyframe's texture around a corner is warped to the current pose
   by the homography of the corner's model face and matched by normalised cross-correlation. A
   second RANSAC over all matches rejects outliers and the pose is refined by Levenberg-Marquardt,
   on the keyframe matches alone when there are enough. Keyframes: the start frame (exact model
   points) and frames whose orientation is far from every earlier keyframe's; without them the
   pose drifts, because every corner back-projected later inherits the pose error of its frame
   (benchmarks/NOTES.md has the figures). Outliers,
   occluded points and points whose face has turned away are dropped; when too few are left (or
   every few frames) new corners are detected where the colour back projection says "head" and
   the model faces the camera, and back-projected with the new pose.
3. **Lost**: too few inliers (or an implausible jump) flags the frame lost; its pose is NaN, not
   the last one. The tracker then re-initialises from the colour blob: the largest head-coloured
   connected region gives the head's direction and, from its area, its range; the orientation is
   taken as the last one tracked (the head is assumed not to have turned much while lost: a
   limitation, said here rather than hidden), corrected by the nearest keyframe's corners searched
   over a wider window when enough are found. That frame is reported lost and ``reinitialised``;
   tracking resumes on the next.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, project, unproject
from kinematics.rays import RayCaster
from kinematics.transforms import rotation_angle

from .headmodel import HeadModel, polyhedral_head, ypr_from_rotation
from .stabilise.estimator import FlowSettings, track_points


# ---------------------------------------------------------------------------------------------
# The tracker
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class HeadTrackerConfig:
    """Parameters of :class:`HeadTracker` (pixels for an image of the camera's size).

    max_features : corners tracked at most. redetect_below : detect new corners when fewer than
    this fraction of ``max_features`` are tracked, and in any case every ``redetect_every`` frames.
    quality_level, min_distance_px : ``cv2.goodFeaturesToTrack``'s. lk_window_px, lk_levels :
    Lucas-Kanade window and pyramid levels. fb_max_px : forward-backward error above which a track
    is dropped. ransac_reproj_px, ransac_iterations : ``cv2.solvePnPRansac``'s threshold and
    iterations. min_inliers, min_inlier_ratio : below either the frame is lost. max_step_rad :
    a rotation between consecutive frames above this is implausible (lost).
    keyframe_features : corners taken from a keyframe (the start frame, whose pose is known, and
    later frames whose orientation is more than ``keyframe_spacing_rad`` from every keyframe's;
    at most ``max_keyframes``). keyframe_reach_rad, max_keyframe_matches : keyframes within this
    angle of the current pose are matched, oldest first (least error), until this many matches.
    min_anchored : with at least this many keyframe inliers the pose is refined on them alone
    (other tracks then only help RANSAC; their model points are refined as running means of their
    back-projections, over at most ``refine_memory`` frames). template_radius_px, search_px,
    min_ncc : a keyframe point is re-found by normalised cross-correlation of a (2 r + 1)^2
    template (the keyframe warped by the homography of the point's model face; small, because a
    larger one spans neighbouring faces, which that homography misplaces, biasing the match) over
    +-``search_px`` around its predicted pixel, accepted above ``min_ncc``. min_facing : a
    corner is back-projected (and kept) only where its face's normal makes ``cos >= min_facing``
    with the direction to the camera (grazing faces give poor 3D points). hist_bins : hue and
    saturation bins of the colour model; min_saturation, min_value : pixels below either (grey,
    dark) have no reliable hue and are left out of the model. colour_threshold : back projection
    (0..255, the ratio histogram's head probability) above which a pixel is head-coloured.
    mask_close_px : closing of the colour mask (features sit on freckles and eyes, whose own
    colours may be outside the model). min_blob_fraction : a colour blob re-initialises only if its
    area is at least this fraction of the head's area at the start. dark_level, bright_level,
    min_contrast : a frame whose mean is below/above the levels, or whose grey standard deviation
    is below ``min_contrast``, is a bad frame (black, saturated, blank).
    """

    max_features: int = 160
    redetect_below: float = 0.75
    redetect_every: int = 4
    quality_level: float = 0.01
    min_distance_px: float = 5.0
    lk_window_px: int = 15
    lk_levels: int = 3
    fb_max_px: float = 0.7
    ransac_reproj_px: float = 2.0
    ransac_iterations: int = 100
    min_inliers: int = 12
    min_inlier_ratio: float = 0.3
    max_step_rad: float = math.radians(25.0)
    keyframe_features: int = 300
    keyframe_spacing_rad: float = math.radians(20.0)
    max_keyframes: int = 40
    min_anchored: int = 12
    keyframe_reach_rad: float = math.radians(45.0)
    max_keyframe_matches: int = 100
    refine_memory: float = 20.0
    template_radius_px: int = 3
    search_px: int = 4
    min_ncc: float = 0.85
    min_facing: float = 0.5
    hist_bins: tuple = (30, 32)
    min_saturation: int = 25
    min_value: int = 25
    colour_threshold: int = 60
    mask_close_px: int = 11
    min_blob_fraction: float = 0.2
    dark_level: float = 6.0
    bright_level: float = 249.0
    min_contrast: float = 2.0

    def __post_init__(self):
        checks = [
            ("max_features", self.max_features >= 8, "at least 8"),
            ("redetect_below", 0 < self.redetect_below <= 1, "in (0, 1]"),
            ("redetect_every", self.redetect_every >= 1, "at least 1"),
            ("lk_window_px", self.lk_window_px >= 5 and self.lk_window_px % 2 == 1, "odd and >= 5"),
            ("min_inliers", self.min_inliers >= 6, "at least 6 (PnP needs 4, RANSAC margin)"),
            ("min_inlier_ratio", 0 <= self.min_inlier_ratio < 1, "in [0, 1)"),
            ("ransac_reproj_px", self.ransac_reproj_px > 0, "positive"),
            ("max_step_rad", self.max_step_rad > 0, "positive"),
            ("min_facing", 0 <= self.min_facing < 1, "in [0, 1)"),
            ("colour_threshold", 0 < self.colour_threshold < 255, "in (0, 255)"),
        ]
        for name, ok, what in checks:
            if not ok:
                raise ValueError(f"HeadTrackerConfig.{name} = {getattr(self, name)!r} must be {what}")

    @property
    def flow(self) -> FlowSettings:
        """The Lucas-Kanade settings of :func:`~runtime.vision2d.stabilise.track_points` (tracks
        that leave the image are kept: PnP can use a corner just past the edge)."""
        return FlowSettings(self.lk_window_px, self.lk_levels, self.fb_max_px, drop_outside=False)


@dataclass
class _Keyframe:
    """A frame kept for re-finding its corners: grey image (H, W) uint8, its pose T_cam_head
    (4, 4) and its corners' model points (m, 3) and face normals (m, 3), head frame."""

    grey: np.ndarray
    T_cam_head: np.ndarray
    points_head: np.ndarray
    normals_head: np.ndarray


@dataclass
class HeadPose:
    """One frame's result.

    frame : index (0 = the start frame). lost : True when the frame has no trustworthy pose
    (too few inliers, a bad frame, an implausible jump); then ``ypr`` and ``T_cam_head`` are NaN.
    ypr : (3,) yaw, pitch, roll, radians (module docstring). T_cam_head : (4, 4), translation in
    metres. inliers : RANSAC inliers (at the start: the corners back-projected). tracked : corners
    that survived the optical flow. reinitialised : the tracker re-started from the colour blob on
    this frame. reason : why the frame is lost or re-initialised, empty otherwise.
    """

    frame: int
    lost: bool
    ypr: np.ndarray
    T_cam_head: np.ndarray
    inliers: int = 0
    tracked: int = 0
    reinitialised: bool = False
    reason: str = ""

    @property
    def yaw(self) -> float:
        return float(self.ypr[0])

    @property
    def pitch(self) -> float:
        return float(self.ypr[1])

    @property
    def roll(self) -> float:
        return float(self.ypr[2])

    @property
    def translation_m(self) -> np.ndarray:
        """(3,) head centre in the camera frame, metres."""
        return self.T_cam_head[:3, 3]


def _nan_pose(frame: int, reason: str, tracked: int = 0, inliers: int = 0, reinit: bool = False) -> HeadPose:
    return HeadPose(frame, True, np.full(3, np.nan), np.full((4, 4), np.nan), inliers, tracked, reinit, reason)


class HeadTracker:
    """Model-based head tracker (module docstring). Use::

        tracker = HeadTracker(camera)                 # default polyhedral head
        first = tracker.start(image0, head_pose((0, 0, 0), distance_m=1.0))
        for image in images:
            pose = tracker.update(image)              # HeadPose; pose.lost is reported
        tracker.counts                                # frames, lost, bad frames, re-initialisations

    camera : CameraIntrinsics of the images (lens distortion is taken into account).
    model : the tracker's polyhedral head (:func:`polyhedral_head` by default).
    config : :class:`HeadTrackerConfig`.
    Images are (H, W, 3) uint8 RGB of the camera's size.
    """

    def __init__(self, camera: CameraIntrinsics, model: HeadModel | None = None,
                 config: HeadTrackerConfig | None = None):
        if not isinstance(camera, CameraIntrinsics):
            raise ValueError("camera must be a kinematics.camera.CameraIntrinsics (e.g. default_camera())")
        self.camera = camera
        self.model = model if model is not None else polyhedral_head()
        if not isinstance(self.model, HeadModel):
            raise ValueError("model must be a HeadModel (e.g. polyhedral_head())")
        self.config = config if config is not None else HeadTrackerConfig()
        self.K = camera.K
        d = camera.distortion
        if camera.model == "brown":
            self.dist = np.array([d["k1"], d["k2"], d["p1"], d["p2"], d["k3"]], float)
            self._undistort_points = False
        else:
            # solvePnP knows only OpenCV's brown model: give it undistorted (pinhole) pixels.
            self.dist = np.zeros(5)
            self._undistort_points = True
        self._rays = RayCaster(self.model.vertices, self.model.faces)
        self._started = False
        self.counts = {"frames": 0, "lost": 0, "bad_frames": 0, "reinitialisations": 0}

    # -- input checks --
    def _check_image(self, image) -> str:
        """'' for a usable frame, else why it is bad; raises for the wrong size or type."""
        if image is None:
            return "bad frame: no image (None)"
        img = np.asarray(image)
        H, W = self.camera.height, self.camera.width
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"image must be (H, W, 3) RGB, got shape {img.shape}; convert grey images to RGB "
                             "(the colour model needs colour)")
        if img.shape[:2] != (H, W):
            raise ValueError(f"image is {img.shape[1]}x{img.shape[0]} but the camera is {W}x{H}; "
                             "give the tracker the intrinsics of these images")
        if img.dtype != np.uint8:
            raise ValueError(f"image must be uint8, got {img.dtype}; scale to 0..255 and convert")
        c = self.config
        m = float(img.mean())
        if m < c.dark_level:
            return "bad frame: black"
        if m > c.bright_level:
            return "bad frame: saturated"
        if float(img[::4, ::4].std()) < c.min_contrast:
            return "bad frame: blank (no contrast)"
        return ""

    # -- geometry --
    def _pixels_to_rays(self, uv: np.ndarray) -> np.ndarray:
        """(n, 3) rays (z = 1) in the optical frame of pixels (n, 2)."""
        xy = unproject(self.camera, uv)
        return xy if xy.shape[1] == 3 else np.column_stack([xy, np.ones(len(xy))])

    def _for_pnp(self, uv: np.ndarray) -> np.ndarray:
        if not self._undistort_points:
            return uv
        r = self._pixels_to_rays(uv)
        return (r[:, :2] / r[:, 2:3]) * [self.camera.fx, self.camera.fy] + [self.camera.cx, self.camera.cy]

    def _facing(self, R_cam_head: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(F,) cos of the angle between each face's normal and the direction to the camera."""
        n_cam = self.model.face_normals @ R_cam_head.T
        c_cam = self.model.face_centres @ R_cam_head.T + t
        to_cam = -c_cam / np.linalg.norm(c_cam, axis=1, keepdims=True)
        return np.einsum("fk,fk->f", n_cam, to_cam)

    def back_project(self, uv, T_cam_head) -> tuple[np.ndarray, np.ndarray]:
        """Model points (n, 3), metres in the head frame, of pixels ``uv`` (n, 2) under pose
        ``T_cam_head`` (4, 4), and a mask (n,) of those that hit a face seen at
        ``cos >= config.min_facing`` (the rest are NaN)."""
        X, _, ok = self._cast(uv, np.asarray(T_cam_head, float))
        return X, ok

    def _region_mask(self, R: np.ndarray, t: np.ndarray, min_facing: float) -> np.ndarray:
        """uint8 mask of the model's faces facing the camera (cos >= min_facing) under (R, t)."""
        H, W = self.camera.height, self.camera.width
        mask = np.zeros((H, W), np.uint8)
        keep = self._facing(R, t) >= min_facing
        if not keep.any():
            return mask
        P = self.model.vertices @ R.T + t
        uv = project(self.camera, P)
        tri = uv[self.model.faces[keep]]
        tri = tri[np.all(np.isfinite(tri), axis=(1, 2))]
        if len(tri):
            cv2.fillPoly(mask, list(np.round(tri * 16).astype(np.int32)), 255, lineType=cv2.LINE_8, shift=4)
        return mask

    # -- colour model --
    def _hsv_valid(self, hsv: np.ndarray) -> np.ndarray:
        c = self.config
        return (hsv[..., 1] >= c.min_saturation) & (hsv[..., 2] >= c.min_value)

    def _learn_colour(self, hsv: np.ndarray, head_mask: np.ndarray) -> None:
        c = self.config
        valid = self._hsv_valid(hsv)
        inside = ((head_mask > 0) & valid).astype(np.uint8)
        # The background: everything outside a margin around the head.
        grown = cv2.dilate(head_mask, np.ones((15, 15), np.uint8))
        outside = ((grown == 0) & valid).astype(np.uint8)
        ranges = [0, 180, 0, 256]
        h_head = cv2.calcHist([hsv], [0, 1], inside, list(c.hist_bins), ranges)
        h_bg = cv2.calcHist([hsv], [0, 1], outside, list(c.hist_bins), ranges)
        if h_head.sum() < 50:
            raise ValueError("the start frame has too few coloured pixels in the head region "
                             f"({int(h_head.sum())}); check the initial pose and that the head is in view")
        # Densities, then P(head | colour) with equal priors (a ratio histogram), as 0..255.
        p_head = h_head / h_head.sum()
        p_bg = h_bg / max(h_bg.sum(), 1.0)
        self.hist = (255.0 * p_head / (p_head + p_bg + 1e-4)).astype(np.float32)
        self.hist[p_head < 1e-4] = 0.0   # colours seen only a few times on the head are noise

    def colour_probability(self, image) -> np.ndarray:
        """(H, W) uint8 back projection of the learned colour model: head probability x 255
        (0 where a pixel's saturation or value is too low for a hue)."""
        hsv = cv2.cvtColor(np.asarray(image), cv2.COLOR_RGB2HSV)
        return self._back_project(hsv)

    def _back_project(self, hsv: np.ndarray) -> np.ndarray:
        prob = cv2.calcBackProject([hsv], [0, 1], self.hist, [0, 180, 0, 256], 1)
        prob[~self._hsv_valid(hsv)] = 0
        return prob

    def _colour_mask(self, prob: np.ndarray) -> np.ndarray:
        k = self.config.mask_close_px
        m = (prob >= self.config.colour_threshold).astype(np.uint8) * 255
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        return cv2.morphologyEx(m, cv2.MORPH_CLOSE, kernel)

    # -- features --
    def _detect(self, grey, mask, existing: np.ndarray, n_max: int) -> np.ndarray:
        c = self.config
        if n_max <= 0:
            return np.zeros((0, 2), np.float32)
        mask = mask.copy()
        for p in existing:
            if np.all(np.isfinite(p)):
                cv2.circle(mask, (int(round(p[0])), int(round(p[1]))), int(c.min_distance_px * 2), 0, -1)
        pts = cv2.goodFeaturesToTrack(grey, n_max, c.quality_level, c.min_distance_px, mask=mask, blockSize=5)
        if pts is None:
            return np.zeros((0, 2), np.float32)
        pts = cv2.cornerSubPix(grey, pts, (3, 3), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.03))
        return pts.reshape(-1, 2)

    def _feature_mask(self, prob, T_cam_head) -> np.ndarray:
        """Where corners may be detected: head-coloured (closed colour mask) and on model faces
        facing the camera, a few pixels inside the model's outline (a corner on the silhouette
        belongs to the background)."""
        region = self._region_mask(T_cam_head[:3, :3], T_cam_head[:3, 3], self.config.min_facing)
        region = cv2.erode(region, np.ones((5, 5), np.uint8))
        return cv2.bitwise_and(region, self._colour_mask(prob))

    def _add_features(self, grey, prob, T_cam_head) -> int:
        """Detect corners where the head is, away from those tracked, back-project them with the
        current pose and append them as unanchored tracks; returns how many were added."""
        mask = self._feature_mask(prob, T_cam_head)
        new = self._detect(grey, mask, self.pts2d, self.config.max_features - len(self.pts2d))
        if len(new) == 0:
            return 0
        X, ok = self.back_project(new, T_cam_head)
        self.pts2d = np.vstack([self.pts2d, new[ok].astype(np.float32)])
        self.pts3d = np.vstack([self.pts3d, X[ok]])
        self.anchor = np.concatenate([self.anchor, np.zeros(int(ok.sum()), bool)])
        self.n_seen = np.concatenate([self.n_seen, np.ones(int(ok.sum()))])
        return int(ok.sum())

    def _cast(self, uv, T_cam_head):
        """Back-projection with the face hit: X (n, 3), face (n,), ok (n,)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        R, t = T_cam_head[:3, :3], T_cam_head[:3, 3]
        rays = self._pixels_to_rays(uv)
        origins = np.broadcast_to(-R.T @ t, rays.shape)
        dirs = rays @ R
        s, face = self._rays.first_hit(origins, dirs)
        ok = face >= 0
        facing = self._facing(R, t)
        ok &= np.where(ok, facing[np.maximum(face, 0)] >= self.config.min_facing, False)
        X = origins + s[:, None] * dirs
        X[~ok] = np.nan
        return X, face, ok

    def _make_keyframe(self, grey, prob, T_cam_head) -> int:
        """Make this frame a keyframe: its corners' model points (back-projected with its pose)
        are re-found in later frames by matching its texture warped to the current pose, so the
        pose does not drift while a keyframe is in view. The start frame, whose pose is given, is
        the first (its points are exact); later ones carry the error of the pose they were made
        with, but that error no longer grows frame by frame."""
        c = self.config
        mask = self._feature_mask(prob, T_cam_head)
        uv = self._detect(grey, mask, np.zeros((0, 2)), c.keyframe_features)
        X, face, ok = self._cast(uv, T_cam_head)
        if ok.sum() >= c.min_inliers:
            self.keyframes.append(_Keyframe(grey.copy(), T_cam_head.copy(), X[ok], self.model.face_normals[face[ok]]))
        return int(ok.sum())

    def _measure_keyframes(self, grey, T_cam_head, search_px: int):
        """Keyframe matches near ``T_cam_head``: model points (m, 3) and pixels (m, 2), from the
        keyframes within ``keyframe_reach_rad`` of it, oldest first (the oldest carry the least
        error; the start frame's none) until ``max_keyframe_matches``; the nearest keyframe if
        none is within reach."""
        c = self.config
        d = np.array([rotation_angle(k.T_cam_head[:3, :3], T_cam_head[:3, :3]) for k in self.keyframes])
        order = [i for i in range(len(d)) if d[i] <= c.keyframe_reach_rad] or [int(np.argmin(d))]
        Xs, uvs, n = [], [], 0
        for i in order:
            kf = self.keyframes[i]
            idx, uv = self._measure_keyframe(kf, grey, T_cam_head, search_px)
            Xs.append(kf.points_head[idx])
            uvs.append(uv)
            n += len(idx)
            if n >= c.max_keyframe_matches:
                break
        return np.vstack(Xs), np.vstack(uvs)

    def _nearest_keyframe(self, T_cam_head) -> "_Keyframe":
        d = [rotation_angle(k.T_cam_head[:3, :3], T_cam_head[:3, :3]) for k in self.keyframes]
        return self.keyframes[int(np.argmin(d))]

    def _measure_keyframe(self, kf: "_Keyframe", grey, T_cam_head, search_px: int):
        """Find the keyframe's points in ``grey`` near their projections under ``T_cam_head``: the
        keyframe around each point is warped by the homography its model face induces between the
        keyframe and the current pose, and matched by normalised cross-correlation over
        +-``search_px``. Returns keyframe indices (m,) and pixels (m, 2)."""
        c = self.config
        r, s = c.template_radius_px, int(search_px)
        R0, t0 = kf.T_cam_head[:3, :3], kf.T_cam_head[:3, 3]
        R, t = T_cam_head[:3, :3], T_cam_head[:3, 3]
        Xc = kf.points_head @ R.T + t
        n_c = kf.normals_head @ R.T
        facing = -np.einsum("nk,nk->n", n_c, Xc) / np.linalg.norm(Xc, axis=1)
        uv = project(self.camera, Xc)
        H_img, W_img = grey.shape
        m = r + s + 2
        vis = (facing >= c.min_facing) & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= m) & \
            (uv[:, 0] < W_img - m) & (uv[:, 1] >= m) & (uv[:, 1] < H_img - m)
        idx = np.flatnonzero(vis)
        idx = idx[self._unoccluded(kf.points_head[idx], T_cam_head)]
        if len(idx) == 0:
            return idx, np.zeros((0, 2))
        # Plane of each point's face in the keyframe camera (n0 . x = d0); relative pose key -> now.
        Xc0 = kf.points_head[idx] @ R0.T + t0
        n0 = kf.normals_head[idx] @ R0.T
        d0 = np.einsum("nk,nk->n", n0, Xc0)
        R_rel = R @ R0.T
        t_rel = t - R_rel @ t0
        K, Kinv = self.K, np.linalg.inv(self.K)
        Hs = K @ (R_rel[None] + t_rel[None, :, None] * n0[:, None, :] / d0[:, None, None]) @ Kinv
        size = 2 * r + 1
        found, out = [], []
        for k, i in enumerate(idx):
            ui = np.round(uv[i]).astype(int)
            shift = np.array([[1.0, 0.0, -(ui[0] - r)], [0.0, 1.0, -(ui[1] - r)], [0.0, 0.0, 1.0]])
            tmpl = cv2.warpPerspective(kf.grey, shift @ Hs[k], (size, size), flags=cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_REPLICATE)
            if cv2.meanStdDev(tmpl)[1][0, 0] < 2.0:   # a flat template cannot be located
                continue
            win = grey[ui[1] - r - s: ui[1] + r + s + 1, ui[0] - r - s: ui[0] + r + s + 1]
            score = cv2.matchTemplate(win, tmpl, cv2.TM_CCOEFF_NORMED)
            _, best, _, (jx, jy) = cv2.minMaxLoc(score)
            if best < c.min_ncc or jx in (0, 2 * s) or jy in (0, 2 * s):
                continue
            # Sub-pixel peak: a parabola through the peak and its neighbours, per axis.
            def peak(a, b, cc):
                den = a - 2 * b + cc
                return 0.0 if abs(den) < 1e-9 else 0.5 * (a - cc) / den
            dx = peak(score[jy, jx - 1], best, score[jy, jx + 1])
            dy = peak(score[jy - 1, jx], best, score[jy + 1, jx])
            found.append(i)
            out.append(uv[i] + [jx - s + dx, jy - s + dy])
        return np.array(found, int), np.array(out, float).reshape(-1, 2)

    def _unoccluded(self, X, T_cam_head) -> np.ndarray:
        """(n,) bool: model points X (n, 3) that the camera sees, not hidden behind another part
        of the head (the nose hides the cheek beside it as the head turns)."""
        if len(X) == 0:
            return np.zeros(0, bool)
        R, t = T_cam_head[:3, :3], T_cam_head[:3, 3]
        cam_h = -R.T @ t
        s, _ = self._rays.first_hit(np.broadcast_to(cam_h, X.shape), X - cam_h)
        # s is the fraction of the way to the point where the first surface is met.
        return np.isfinite(s) & (s > 1.0 - 1e-3)

    def _pnp(self, pts3d, uv, T_guess):
        """RANSAC PnP from ``T_guess`` then LM on the inliers: (T (4, 4), inlier mask) or
        (None, None)."""
        c = self.config
        img_pts = self._for_pnp(np.asarray(uv, float))
        rvec0, _ = cv2.Rodrigues(T_guess[:3, :3])
        tvec0 = T_guess[:3, 3].reshape(3, 1).copy()
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            np.asarray(pts3d, float), img_pts, self.K, self.dist, rvec0, tvec0, useExtrinsicGuess=True,
            iterationsCount=c.ransac_iterations, reprojectionError=c.ransac_reproj_px, confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or inl is None or len(inl) < 6:
            return None, None
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(pts3d[inl], img_pts[inl], self.K, self.dist, rvec, tvec)
        proj, _ = cv2.projectPoints(pts3d, rvec, tvec, self.K, self.dist)
        inliers = np.linalg.norm(proj.reshape(-1, 2) - img_pts, axis=1) < c.ransac_reproj_px
        if inliers.sum() >= 6:
            rvec, tvec = cv2.solvePnPRefineLM(pts3d[inliers], img_pts[inliers], self.K, self.dist, rvec, tvec)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        return T, inliers

    # -- the public steps --
    def start(self, image, T_cam_head) -> HeadPose:
        """Begin tracking on ``image`` with the head at the known pose ``T_cam_head`` (4, 4)
        (:func:`head_pose`): learns the colour model, makes the keyframe and back-projects the
        first corners. Raises ValueError if the image is unusable or the head has no corners."""
        why = self._check_image(image)
        if why:
            raise ValueError(f"cannot start on this image ({why}); start on a frame that shows the head")
        T = np.asarray(T_cam_head, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_cam_head must be a finite (4, 4) pose, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("T_cam_head's rotation is not a rotation matrix (orthonormal, det +1)")
        if T[2, 3] <= 0:
            raise ValueError(f"the head must be in front of the camera (z = {T[2, 3]:g} m); check T_cam_head")
        img = np.ascontiguousarray(image)
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)
        silhouette = self._region_mask(R, T[:3, 3], 0.0)
        if silhouette.sum() == 0:
            raise ValueError("the head model projects outside the image at the given pose; check T_cam_head")
        self._learn_colour(hsv, silhouette)
        grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        prob = self._back_project(hsv)
        self.start_area_px = float(np.count_nonzero(self._colour_mask(prob) & silhouette))
        self.start_range_m = float(np.linalg.norm(T[:3, 3]))
        self.keyframes = []
        n = self._make_keyframe(grey, prob, T)
        if n < self.config.min_inliers:
            raise ValueError(f"only {n} corners on the head at the start (need {self.config.min_inliers}); "
                             "check the pose, the lighting or lower HeadTrackerConfig.quality_level")
        self.pts3d = self.keyframes[0].points_head.copy()
        self.pts2d = project(self.camera, self.pts3d @ R.T + T[:3, 3]).astype(np.float32)
        self.anchor = np.ones(n, bool)
        self.n_seen = np.ones(n)
        self.prev_grey = grey
        self.T_cam_head = T.copy()
        self.T_cam_head_prev = T.copy()
        self.T_cam_head_good = T.copy()
        self.lost = False
        self.frame = 0
        self.since_detect = 0
        self._started = True
        self.counts = {"frames": 1, "lost": 0, "bad_frames": 0, "reinitialisations": 0}
        return HeadPose(0, False, ypr_from_rotation(R), T.copy(), n, n)

    def update(self, image) -> HeadPose:
        """Track the head into the next frame ``image`` (H, W, 3) uint8 RGB; returns its HeadPose.
        A bad frame (None, black, saturated, blank) is reported lost and counted, not raised."""
        if not self._started:
            raise ValueError("call HeadTracker.start(first_image, T_cam_head) before update()")
        self.frame += 1
        self.counts["frames"] += 1
        why = self._check_image(image)
        if why:
            self.counts["bad_frames"] += 1
            return self._lose(why)
        img = np.ascontiguousarray(image)
        grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)
        prob = self._back_project(hsv)
        if self.lost:
            return self._reinitialise(grey, prob)
        result = self._track(grey, prob)
        self.prev_grey = grey
        return result

    def track(self, images, T_cam_head0) -> list[HeadPose]:
        """:meth:`start` on ``images[0]`` at ``T_cam_head0``, :meth:`update` on the rest."""
        out = []
        for k, im in enumerate(images):
            out.append(self.start(im, T_cam_head0) if k == 0 else self.update(im))
        return out

    # -- internals --
    def _lose(self, reason: str, tracked: int = 0, inliers: int = 0) -> HeadPose:
        self.counts["lost"] += 1
        self.lost = True
        return _nan_pose(self.frame, reason, tracked, inliers)

    def _track(self, grey, prob) -> HeadPose:
        c = self.config
        # 1. Optical flow of every track, started from the constant-velocity prediction.
        T_pred = self.T_cam_head @ np.linalg.inv(self.T_cam_head_prev) @ self.T_cam_head
        T_flow = None
        uv_flow, X_flow = np.zeros((0, 2)), np.zeros((0, 3))
        a_flow, s_flow = np.zeros(0, bool), np.zeros(0)
        if len(self.pts2d):
            guess = project(self.camera, self.pts3d @ T_pred[:3, :3].T + T_pred[:3, 3])
            # The backward track starts at the corners' previous pixels, not where the forward one ended.
            uv, good = track_points(self.prev_grey, grey, self.pts2d, c.flow, guess, lambda _: self.pts2d)
            uv_flow, X_flow = uv[good].astype(float), self.pts3d[good]
            a_flow, s_flow = self.anchor[good], self.n_seen[good]
            if len(uv_flow) >= c.min_inliers:
                T_flow, _ = self._pnp(X_flow, uv_flow, T_pred)
        # 2. The nearest keyframe's points, found by warped-template matching near the flow's pose.
        if T_flow is not None and rotation_angle(T_flow[:3, :3], self.T_cam_head[:3, :3]) <= c.max_step_rad:
            T_ref, search = T_flow, c.search_px
        else:
            T_ref, search = T_pred, 2 * c.search_px
        kX, k_uv = self._measure_keyframes(grey, T_ref, search)
        # 3. RANSAC over all matches: the keyframes' and the flow's unanchored tracks.
        free = ~a_flow
        X_all = np.vstack([kX, X_flow[free]])
        uv_all = np.vstack([k_uv, uv_flow[free]])
        anchored = np.concatenate([np.ones(len(kX), bool), np.zeros(int(free.sum()), bool)])
        seen = np.concatenate([np.full(len(kX), np.inf), s_flow[free]])
        n_meas = len(X_all)
        if n_meas < c.min_inliers:
            self._keep_tracks(uv_flow, X_flow, a_flow, s_flow)
            return self._lose(f"too few corners tracked ({n_meas} < {c.min_inliers})", n_meas)
        T, inliers = self._pnp(X_all, uv_all, T_ref)
        n_in = 0 if inliers is None else int(inliers.sum())
        step = np.inf if T is None else rotation_angle(T[:3, :3], self.T_cam_head[:3, :3])
        if T is None or n_in < c.min_inliers or n_in < c.min_inlier_ratio * n_meas or step > c.max_step_rad \
                or T[2, 3] <= 0:
            self._keep_tracks(uv_flow, X_flow, a_flow, s_flow)
            why = (f"implausible jump ({math.degrees(step):.0f} deg in a frame)" if np.isfinite(step)
                   and step > c.max_step_rad else f"too few inliers ({n_in} of {n_meas})")
            return self._lose(why, n_meas, n_in)
        # 4. With enough keyframe inliers the pose rests on them alone: the other tracks' model
        # points were back-projected with earlier estimated poses and would pass their errors on.
        use_anchor = inliers & anchored
        if use_anchor.sum() >= c.min_anchored:
            rvec, tvec = cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1).copy()
            rvec, tvec = cv2.solvePnPRefineLM(X_all[use_anchor], self._for_pnp(uv_all[use_anchor]), self.K,
                                              self.dist, rvec, tvec)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            # ... and that pose refines the unanchored points: each point's model position is the
            # running mean of its back-projections (at most the last ``refine_memory`` count).
            idx = np.flatnonzero(inliers & ~anchored)
            if len(idx):
                Xb, okb = self.back_project(uv_all[idx], T)
                idx, Xb = idx[okb], Xb[okb]
                w = np.minimum(seen[idx], c.refine_memory)
                X_all[idx] = (w[:, None] * X_all[idx] + Xb) / (w[:, None] + 1.0)
                seen[idx] += 1
        R = T[:3, :3]
        # 5. Keep the inliers whose face still faces the camera (a corner rotating onto the
        # silhouette is about to be occluded or sheared).
        cam_h = -R.T @ T[:3, 3]
        _, face = self._rays.first_hit(np.broadcast_to(cam_h, X_all.shape), X_all - cam_h)
        facing = self._facing(R, T[:3, 3])
        keep = inliers & (face >= 0) & (facing[np.maximum(face, 0)] >= 0.5 * c.min_facing)
        self._keep_tracks(uv_all[keep], X_all[keep], anchored[keep], seen[keep])
        self.T_cam_head_prev, self.T_cam_head, self.T_cam_head_good = self.T_cam_head, T, T
        # 6. A new keyframe when the head has turned away from every keyframe's view; new corners
        # where the tracks have thinned out.
        if rotation_angle(self._nearest_keyframe(T).T_cam_head[:3, :3], R) > c.keyframe_spacing_rad \
                and len(self.keyframes) < c.max_keyframes:
            self._make_keyframe(grey, prob, T)
        self.since_detect += 1
        if len(self.pts2d) < c.redetect_below * c.max_features or self.since_detect >= c.redetect_every:
            self._add_features(grey, prob, T)
            self.since_detect = 0
        return HeadPose(self.frame, False, ypr_from_rotation(R), T.copy(), n_in, n_meas)

    def _keep_tracks(self, uv, X, anchored, seen) -> None:
        self.pts2d = np.asarray(uv, np.float32).reshape(-1, 2)
        self.pts3d = np.asarray(X, float).reshape(-1, 3)
        self.anchor = np.asarray(anchored, bool)
        self.n_seen = np.minimum(np.asarray(seen, float), self.config.refine_memory)

    def _reinitialise(self, grey, prob) -> HeadPose:
        """Restart from the largest head-coloured blob (module docstring, item 3)."""
        c = self.config
        mask = self._colour_mask(prob)
        n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask)
        if n <= 1:
            self.counts["lost"] += 1
            return _nan_pose(self.frame, "lost: no head-coloured region to re-initialise from")
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        area = float(stats[k, cv2.CC_STAT_AREA])
        if area < c.min_blob_fraction * self.start_area_px:
            self.counts["lost"] += 1
            return _nan_pose(self.frame, f"lost: largest head-coloured region too small ({area:.0f} px)")
        # Range from the blob's area (area ~ 1 / range^2), direction from its centroid; the
        # orientation is the last one tracked.
        rng = self.start_range_m * math.sqrt(self.start_area_px / area)
        ray = self._pixels_to_rays(centroids[k][None])[0]
        T = np.eye(4)
        T[:3, :3] = self.T_cam_head_good[:3, :3]
        T[:3, 3] = ray / np.linalg.norm(ray) * rng
        self._keep_tracks(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0))
        # The nearest keyframe's points, searched widely around the guessed pose, correct it.
        kf = self._nearest_keyframe(T)
        k_idx, k_uv = self._measure_keyframe(kf, grey, T, 3 * c.search_px)
        if len(k_idx) >= c.min_inliers:
            T_k, inl = self._pnp(kf.points_head[k_idx], k_uv, T)
            if T_k is not None and inl.sum() >= c.min_inliers:
                T = T_k
                self._keep_tracks(k_uv[inl], kf.points_head[k_idx][inl], np.ones(int(inl.sum()), bool),
                                  np.full(int(inl.sum()), np.inf))
        added = self._add_features(grey, prob, T)
        self.counts["lost"] += 1
        if len(self.pts2d) < c.min_inliers:
            return _nan_pose(self.frame, f"lost: only {len(self.pts2d)} corners on the colour blob", added)
        self.counts["reinitialisations"] += 1
        self.prev_grey = grey
        self.T_cam_head = self.T_cam_head_prev = T
        self.lost = False
        self.since_detect = 0
        return _nan_pose(self.frame, "re-initialised from the colour blob (orientation assumed unchanged)",
                         len(self.pts2d), 0, reinit=True)
