"""Start-up from natural features: no printed target, no saved map.

Two ways in, both giving a :class:`NaturalStart` (the first camera's frame is the world frame,
a set of mapped points with their covariances) or a :class:`StartWait` that says why not yet:

- **depth** (:func:`depth_start`): the first frame that has a registered depth image (TUM RGB-D's
  16-bit PNGs) and enough corners on valid, locally smooth depth. The points are the corners
  back-projected at their measured depth; metric. A structured-light or time-of-flight depth's
  noise grows with the square of the range (Khoshelham and Elberink, "Accuracy and resolution of
  Kinect depth data", 2012: sigma_z = 1.45e-3 z^2 m at z m), so each point's covariance is that
  along its ray and the pixel's noise across it.
- **two views** (:class:`TwoViewStart`): corners of a reference frame tracked with pyramidal
  Lucas-Kanade (forward-backward checked) until the views have enough parallax; the essential
  matrix (five-point RANSAC, OpenCV) gives the relative pose, the inliers are triangulated, and
  the start is accepted only when most points are seen under a useful angle. Where a homography
  explains the matches as well (ORB-SLAM's R_H: most of the view on one plane, a desk, a wall,
  a floor) the essential matrix is near-degenerate and its pose can be tens of degrees off, so
  the pose is the homography's decomposition under which most points triangulate, when clearly
  better than the next (ORB-SLAM's choice); a pure rotation or a too-short baseline waits.
  The scale is arbitrary (the points' median depth set to 1 m) unless the caller supplies it.

The EKF then starts at the reference frame with its camera fixed (the gauge), the points as
features; frames between the reference and the accepting frame are kept by the caller and
replayed, so every frame from the reference on gets a pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, in_image, undistort

#: Depth noise of a structured-light sensor, sigma_z = DEPTH_NOISE_K z^2 (m, z in m).
DEPTH_NOISE_K = 1.45e-3


@dataclass(frozen=True)
class StartSettings:
    """How a natural start is made (the `start` group of the SLAM's settings).

    corners : corners sought in the reference frame, at most.
    corner_min_distance_px : between two corners, at 640 px width (scaled with the image).
    min_points : mapped points a start needs.
    min_parallax_deg : the median angle between the two views' rays of the triangulated points.
    max_reproj_px : a triangulated point's largest reprojection error in either view.
    pixel_sigma : a corner's position noise, px.
    max_frames : frames a two-view start tries from one reference before taking a new one.
    homography_ratio : the two-view start waits while a homography explains the matches nearly as
        well as the essential matrix (ORB-SLAM's R_H = S_H / (S_H + S_F) above this).
    min_depth_m, max_depth_m : depth readings used by the depth start.
    depth_smooth_rel : a depth reading is used where its 5 x 5 neighbourhood's spread is under this
        fraction of it (a corner on a depth edge reads the far or the near side).
    """

    corners: int = 120
    corner_min_distance_px: float = 20.0
    min_points: int = 30
    min_parallax_deg: float = 1.5
    max_reproj_px: float = 2.0
    pixel_sigma: float = 1.0
    max_frames: int = 90
    homography_ratio: float = 0.45
    min_depth_m: float = 0.2
    max_depth_m: float = 8.0
    depth_smooth_rel: float = 0.03


@dataclass(frozen=True)
class NaturalStart:
    """A map to start from, in the reference camera's frame (the world frame).

    frame : index of the reference frame among those given to the starter.
    uv : (n, 2) the points' pixels in the reference frame.
    xyz : (n, 3) the points, world frame, m (or the arbitrary unit when ``scale`` is "arbitrary").
    xyz_cov : (n, 3, 3) their covariances.
    scale : "depth", "head-motion" or "arbitrary": what fixed the unit.
    v_world : (3,) the camera's velocity at the reference frame as the two views saw it, m/s (zero
        for a depth start).
    T_world_cam : (4, 4) the camera's pose at that frame; None: the world is its frame (the
        head-motion start's world is the motion's first camera, levelled).
    gyro_bias : (3,) the gyro's bias, camera frame, rad/s, where the start found it (the head-motion
        start, against the encoders), and gyro_bias_sigma its standard deviation per axis; None:
        SLAM takes it from a still stretch before the start, if any.
    """

    frame: int
    uv: np.ndarray
    xyz: np.ndarray
    xyz_cov: np.ndarray
    scale: str
    v_world: np.ndarray = field(default_factory=lambda: np.zeros(3))
    T_world_cam: np.ndarray | None = None
    gyro_bias: np.ndarray | None = None
    gyro_bias_sigma: float = 0.0


@dataclass(frozen=True)
class StartWait:
    """No start yet: ``reason`` says why, in words for the console and stats.json."""

    reason: str


def _corners(cam: CameraIntrinsics, grey: np.ndarray, s: StartSettings, mask: np.ndarray | None = None,
             quality: float = 0.01) -> np.ndarray:
    """(k, 2) Shi-Tomasi corners, strongest first, 20 px from the border (at 640 px width), none
    weaker than ``quality`` times the strongest, none where ``mask`` (H, W) uint8 is 0."""
    scale = cam.width / 640.0
    border = int(round(20 * scale))
    m = np.zeros(grey.shape, np.uint8)
    m[border:-border, border:-border] = 255
    if mask is not None:
        m &= mask
    pts = cv2.goodFeaturesToTrack(np.asarray(grey, np.float32), maxCorners=s.corners, qualityLevel=quality,
                                  minDistance=s.corner_min_distance_px * scale, mask=m, blockSize=5)
    return np.empty((0, 2)) if pts is None else pts.reshape(-1, 2).astype(float)


def track_forward_backward(cam: CameraIntrinsics, prev8: np.ndarray, cur8: np.ndarray, uv: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Points uv (k, 2) px of the 8-bit image prev8 tracked into cur8 by pyramidal Lucas-Kanade
    (21 px window, 3 levels): (k, 2) where they went, and (k,) which to keep: found both ways,
    tracked back to within 0.5 px of where they started, and 4 px inside the image."""
    lk = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev8, cur8, uv.astype(np.float32), None, **lk)
    p0, st0, _ = cv2.calcOpticalFlowPyrLK(cur8, prev8, p1, None, **lk)
    ok = (st1.ravel() == 1) & (st0.ravel() == 1) & (np.linalg.norm(p0 - uv, axis=1) < 0.5)
    ok &= in_image(cam, p1.astype(float), margin=4)
    return p1.astype(float), ok


def _ray_covariance(rays: np.ndarray, sigma_along: np.ndarray, sigma_across: np.ndarray) -> np.ndarray:
    """(n, 3, 3) covariances with standard deviation ``sigma_along`` along each unit ray (n, 3) and
    ``sigma_across`` across it (m)."""
    P_along = rays[:, :, None] * rays[:, None, :]
    P_across = np.eye(3)[None] - P_along
    return sigma_along[:, None, None] ** 2 * P_along + sigma_across[:, None, None] ** 2 * P_across


def depth_start(cam: CameraIntrinsics, grey: np.ndarray, depth_m: np.ndarray, frame: int = 0,
                settings: StartSettings = StartSettings()) -> NaturalStart | StartWait:
    """A metric start from one frame and its registered depth image.

    grey : (H, W) the frame; depth_m : (H, W) float depth along the optic axis, m (0 or NaN where
    there is no reading). Corners on valid depth whose neighbourhood is smooth are back-projected."""
    s = settings
    if depth_m.shape != grey.shape:
        raise ValueError(f"depth image is {depth_m.shape[1]}x{depth_m.shape[0]}, the frame "
                         f"{grey.shape[1]}x{grey.shape[0]}: the depth must be registered to the colour image")
    d = np.where(np.isfinite(depth_m), depth_m, 0.0).astype(np.float32)
    valid = (d >= s.min_depth_m) & (d <= s.max_depth_m)
    # A reading is kept where every neighbour is valid and they agree (no depth edge, no hole).
    k = np.ones((5, 5), np.uint8)
    lo = cv2.erode(np.where(valid, d, np.float32(np.inf)), k)
    hi = cv2.dilate(np.where(valid, d, np.float32(0.0)), k)
    smooth = valid & np.isfinite(lo) & ((hi - lo) <= s.depth_smooth_rel * d)
    uv = _corners(cam, grey, s, (smooth * 255).astype(np.uint8))
    if len(uv) < s.min_points:
        why = ("too few corners on valid depth" if smooth.mean() > 0.2 else "the depth image is mostly empty")
        return StartWait(f"{why} ({len(uv)} of the {s.min_points} a start needs)")
    z = d[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)].astype(float)
    xy = undistort(cam, uv)
    xyz = np.column_stack([xy * z[:, None], z])
    rays = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    rng = np.linalg.norm(xyz, axis=1)
    # Depth noise along the ray (z-noise scaled to range), the pixel's noise across it.
    sigma_along = DEPTH_NOISE_K * z**2 * rng / z
    sigma_across = rng * s.pixel_sigma / cam.fx
    return NaturalStart(frame, uv, xyz, _ray_covariance(rays, sigma_along, sigma_across), "depth")


def triangulate(R_b_a: np.ndarray, t_b_a: np.ndarray, xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
    """(n, 3) points in camera a's frame from normalised image points (n, 2) in cameras a and b,
    where X_b = R_b_a X_a + t_b_a (linear, OpenCV's DLT)."""
    P_a = np.hstack([np.eye(3), np.zeros((3, 1))])
    P_b = np.hstack([R_b_a, t_b_a.reshape(3, 1)])
    X = cv2.triangulatePoints(P_a, P_b, xy_a.T.astype(float), xy_b.T.astype(float))
    return (X[:3] / X[3]).T


def _parallax_deg(X_a: np.ndarray, R_b_a: np.ndarray, t_b_a: np.ndarray) -> np.ndarray:
    """(n,) the angle (deg) between the rays from the two centres to each point (camera a frame)."""
    c_b = -R_b_a.T @ t_b_a                      # camera b's centre in a's frame
    ra = X_a / np.linalg.norm(X_a, axis=1, keepdims=True)
    rb = X_a - c_b
    rb /= np.linalg.norm(rb, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(ra * rb, axis=1), -1.0, 1.0)))


@dataclass(frozen=True)
class TwoViewGeometry:
    """The relative pose of two views and the points triangulated from them.

    R_b_a (3, 3), t_b_a (3,) unit length: X_b = R_b_a X_a + t_b_a. keep (n,) bool: the matches
    triangulated and accepted; X_a (k, 3) those points in camera a's frame, in units of the
    baseline; parallax_deg (k,)."""

    R_b_a: np.ndarray
    t_b_a: np.ndarray
    keep: np.ndarray
    X_a: np.ndarray
    parallax_deg: np.ndarray


#: A homography's best pose is taken when the next best triangulates fewer than this fraction
#: of its points (ORB-SLAM's 0.75).
PLANE_AMBIGUITY = 0.75
#: ... and when the essential matrix's pose is within this rotation (deg; ten times it in the
#: translation's direction) of it.
AGREE_DEG = 1.0


def _unit(t: np.ndarray) -> np.ndarray:
    """A two-view translation (3,) made unit length (the baseline's scale is not observable)."""
    return t / max(float(np.linalg.norm(t)), 1e-12)


def _triangulated(R: np.ndarray, t: np.ndarray, xy_a: np.ndarray, xy_b: np.ndarray, cand: np.ndarray,
                  s: StartSettings, fx: float):
    """The matches ``cand`` (n,) bool triangulated under the pose ``R, t`` (t unit): (R, t, cand,
    X (k, 3) in a's frame, ok (k,) in front of both views within max_reproj_px, parallax (k,) deg)."""
    X = triangulate(R, t, xy_a[cand], xy_b[cand])
    Xb = X @ R.T + t
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = (X[:, 2] > 0) & (Xb[:, 2] > 0)
        err_a = np.linalg.norm(X[:, :2] / X[:, 2:3] - xy_a[cand], axis=1) * fx
        err_b = np.linalg.norm(Xb[:, :2] / Xb[:, 2:3] - xy_b[cand], axis=1) * fx
    ok &= (err_a < s.max_reproj_px) & (err_b < s.max_reproj_px)
    return R, t, cand, X, ok, _parallax_deg(X, R, t)


def two_view_geometry(cam: CameraIntrinsics, uv_a: np.ndarray, uv_b: np.ndarray,
                      settings: StartSettings = StartSettings()) -> TwoViewGeometry | StartWait:
    """The relative pose and points of two views from matched pixels (n, 2) each, or why not."""
    s = settings
    n = len(uv_a)
    if n < s.min_points:
        return StartWait(f"too few matches between the views ({n} of {s.min_points})")
    xy_a, xy_b = undistort(cam, uv_a), undistort(cam, uv_b)
    thr = s.max_reproj_px / cam.fx
    E, inl = cv2.findEssentialMat(xy_a, xy_b, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.999, threshold=thr)
    if E is None or E.shape != (3, 3) or inl is None or int(inl.sum()) < s.min_points:
        return StartWait("no essential matrix explains the matches (too little motion or too few matches)")
    # ORB-SLAM's model choice: a homography that explains the matches as well means a planar
    # scene or a rotation with no baseline, where the essential matrix's pose is unreliable.
    H, inl_h = cv2.findHomography(xy_a, xy_b, cv2.RANSAC, thr)
    n_e, n_h = int(inl.sum()), int(inl_h.sum()) if inl_h is not None else 0
    ratio_h = n_h / max(n_h + n_e, 1)
    _, R_e, t_e, inl_pose = cv2.recoverPose(E, xy_a, xy_b, np.eye(3), mask=inl.copy())
    t_e = _unit(t_e.ravel())
    if ratio_h > s.homography_ratio:
        # A plane (or most of the view on one): the essential matrix is degenerate there and its
        # pose can be tens of degrees off, so the pose is the homography's (ORB-SLAM's choice),
        # the decomposition under which most points triangulate, if clearly the best (the points
        # off the plane, the essential matrix's inliers, tell its two poses apart).
        tries = []
        if H is not None:
            _, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
            cand = (inl_h.ravel() > 0) | (inl.ravel() > 0)
            tries = [_triangulated(Rh, _unit(th.ravel()), xy_a, xy_b, cand, s, cam.fx) for Rh, th in zip(Rs, ts)]
        counts = sorted((int(tr[4].sum()) for tr in tries), reverse=True)
        if not counts or counts[0] < s.min_points:
            # A homography explains the views: a turn or too short a baseline.
            return StartWait("not enough parallax yet (the views differ by a turn, or the camera has barely moved): "
                             "move the camera sideways, not only turn it")
        if len(counts) > 1 and counts[1] >= PLANE_AMBIGUITY * counts[0]:
            return StartWait(f"a homography explains the motion (R_H {ratio_h:.2f}) and two of its poses fit alike: a "
                             "flat scene; waiting for more parallax")
        R, t, good, X, ok, par = max(tries, key=lambda tr: int(tr[4].sum()))
        # The essential matrix's pose must agree with it: where they differ the views are
        # still ambiguous, and more parallax tells them apart.
        d_rot = np.degrees(np.arccos(np.clip((np.trace(R_e @ R.T) - 1) / 2, -1.0, 1.0)))
        d_dir = np.degrees(np.arccos(np.clip(t_e @ t, -1.0, 1.0)))
        if d_rot > AGREE_DEG or d_dir > 10 * AGREE_DEG:
            return StartWait(f"a homography explains the motion (R_H {ratio_h:.2f}) and its pose and the essential "
                             f"matrix's differ ({d_rot:.1f} deg, {d_dir:.0f} deg in direction): waiting for more "
                             "parallax")
    else:
        R, t, good, X, ok, par = _triangulated(R_e, t_e, xy_a, xy_b, inl_pose.ravel() > 0, s, cam.fx)
    if ok.sum() < s.min_points:
        return StartWait(f"too few points triangulate in front of both views ({int(ok.sum())} of {s.min_points})")
    med = float(np.median(par[ok]))
    if med < s.min_parallax_deg:
        return StartWait(f"not enough parallax yet (median {med:.2f} deg of {s.min_parallax_deg:g}): move the camera "
                         "sideways, not only turn it")
    if ratio_h > s.homography_ratio and med < 2 * s.min_parallax_deg:
        return StartWait(f"a homography explains the motion as well (R_H {ratio_h:.2f}): a flat scene or a turn; "
                         "waiting for more parallax")
    # Points seen under too small an angle have depths the geometry does not fix: left out.
    ok &= par >= 0.5 * s.min_parallax_deg
    keep = np.zeros(n, bool)
    keep[np.flatnonzero(good)[ok]] = True
    return TwoViewGeometry(R, t, keep, X[ok], par[ok])


class TwoViewStart:
    """Feeds frames; returns a :class:`NaturalStart` once two views give a map (in the reference
    frame's camera frame, the scale arbitrary: the points' median depth 1), else a
    :class:`StartWait`. Keeps the reference frame's index; the caller keeps the frames from it on."""

    def __init__(self, cam: CameraIntrinsics, settings: StartSettings = StartSettings()):
        self.cam, self.s = cam, settings
        self.ref_frame: int | None = None
        self._ref_uv = np.empty((0, 2))
        self._prev: np.ndarray | None = None
        self._uv = np.empty((0, 2))
        self._t_ref = 0.0
        self._frames = 0

    def _reset(self, grey: np.ndarray, frame: int, t: float) -> StartWait:
        uv = _corners(self.cam, grey, self.s)
        if len(uv) < self.s.min_points:
            self.ref_frame = None
            return StartWait(f"too few corners in view ({len(uv)} of {self.s.min_points}): point the camera at "
                             "something textured")
        self.ref_frame, self._ref_uv, self._uv, self._prev = frame, uv, uv.copy(), grey
        self._t_ref, self._frames = t, 0
        return StartWait("reference frame taken; waiting for parallax")

    def add(self, grey: np.ndarray, frame: int, t: float) -> NaturalStart | StartWait:
        """One frame (H, W) grey, its index and time (s)."""
        g8 = np.clip(grey, 0, 255).astype(np.uint8)
        if self.ref_frame is None:
            return self._reset(g8, frame, t)
        self._frames += 1
        p1, ok = track_forward_backward(self.cam, self._prev, g8, self._uv)
        self._ref_uv, self._uv, self._prev = self._ref_uv[ok], p1[ok], g8
        if len(self._uv) < self.s.min_points or self._frames > self.s.max_frames:
            lost = len(self._uv) < self.s.min_points
            w = self._reset(g8, frame, t)
            return StartWait("the views lost their matches; " + w.reason) if lost else w
        geo = two_view_geometry(self.cam, self._ref_uv, self._uv, self.s)
        if isinstance(geo, StartWait):
            return geo
        # Arbitrary unit: the points' median depth in the reference view is 1.
        k = 1.0 / float(np.median(geo.X_a[:, 2]))
        X = geo.X_a * k
        c_b = -geo.R_b_a.T @ geo.t_b_a * k
        rng = np.linalg.norm(X, axis=1)
        rays = X / rng[:, None]
        # Depth along the ray from the angle between the views: sigma_d = d sigma_theta / sin(parallax),
        # sigma_theta the pixel noise's angle seen from either view.
        sigma_theta = self.s.pixel_sigma / self.cam.fx
        sigma_along = rng * np.sqrt(2.0) * sigma_theta / np.sin(np.radians(geo.parallax_deg))
        cov = _ray_covariance(rays, sigma_along, rng * sigma_theta)
        dt = max(t - self._t_ref, 1e-6)
        return NaturalStart(self.ref_frame, self._ref_uv[geo.keep], X, cov, "arbitrary", v_world=c_b / dt)


__all__ = ["DEPTH_NOISE_K", "NaturalStart", "StartSettings", "StartWait", "TwoViewGeometry", "TwoViewStart",
           "depth_start", "track_forward_backward", "triangulate", "two_view_geometry"]
