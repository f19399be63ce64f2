"""The stabiliser: visual (and inertial) stabilisation with a software fovea (paper, section 3
item 1, Fig. 4), frame by frame; :mod:`.runner` runs it over a sequence.

Each frame's rotation relative to the previous one is measured from the static background:
Shi-Tomasi corners of the previous frame are tracked into the current one by pyramidal
Lucas-Kanade (with a forward-backward check), undistorted to bearing vectors through the
sequence's lens model, and a rotation-only model is fitted robustly (RANSAC over 2-point samples,
then a Kabsch/Wahba fit on the inliers). An optional IMU (gyro in the camera frame) predicts the
rotation, which pre-warps the flow search so that large rotations are tracked; vision measures
the rest (the paper: "accelerometers were used to take out gross rotation, and vision is used to
remove any remainder"). The rotations are chained into the orientation relative to the first
frame, which moves a software fovea (a window of the full image) so as to cancel it.

Frames and conventions
----------------------
cam
    the camera's optical frame at a given image: x right, y down, z forward.
``R_prev_cur``
    (3, 3) the current camera's orientation in the previous camera's frame: it maps a direction
    expressed in the current frame to the previous one, ``f_prev = R_prev_cur @ f_cur`` for a
    static direction (a point at infinity). With ground truth ``R_world_cam`` per frame it is
    ``R_world_prev.T @ R_world_cur``.
``R_cam0_cam``
    (3, 3) the orientation relative to the first frame (the product of the ``R_prev_cur``).
``R_cam0_ref``
    (3, 3) the fovea's reference orientation: a virtual camera that the fovea shows. It is the
    first frame's (hold still, the default) or follows the camera with a leak (see
    :func:`follow_reference`).
pixels
    OpenCV convention (the centre of pixel (0, 0) at (0, 0)), as kinematics.camera.

Angles are radians inside, times seconds, image motion pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, project, undistort
from kinematics.transforms import nearest_rotation

from .. import images

# Why a frame was flagged (StepResult.reason / RotationResult.reason).
OK = "ok"
FEW_CORNERS_PREV = "few corners in the reference frame"
FEW_TRACKS = "few corners tracked into the frame"
FEW_INLIERS = "few rotation inliers"


@dataclass(frozen=True)
class StabiliseSettings:
    """What the stabiliser may be tuned by (one place, no literals in the code).

    max_corners : corners detected per frame (cv2.goodFeaturesToTrack maxCorners).
    quality : Shi-Tomasi quality level, a fraction of the best corner's score.
    min_distance_px : minimum spacing between corners, pixels.
    block_size_px : Shi-Tomasi window, pixels.
    lk_window_px : Lucas-Kanade window side, pixels (odd).
    lk_levels : pyramid levels above the full image (0 = no pyramid).
    fb_threshold_px : a track is kept only if tracking it back lands within this of its start.
    ransac_threshold_rad : a bearing pair is an inlier of a rotation if the angle between the
        previous bearing and the rotated current one is below this (radians; 0.002 rad is about
        1 pixel at f = 514.7 pixels).
    ransac_iterations : 2-point hypotheses per frame.
    refine_iterations : Kabsch refits on the inliers (each re-selecting the inliers).
    min_corners : fewer corners than this in a frame (black, saturated, textureless) flags it.
    min_inliers : fewer rotation inliers than this flags the frame.
    seed : the RANSAC sampler's seed (results are reproducible).
    leak_per_s : how fast the fovea's reference orientation follows the camera, 1/s: each frame it
        moves the fraction 1 - exp(-leak_per_s dt) of the way (slerp) to the camera's current
        orientation, so intentional panning is followed with time constant 1 / leak_per_s while
        faster shake is cancelled. 0 (default) holds the first frame's view still.
    derotate : also turn the fovea window about its centre to cancel the rotation about the
        viewing direction (roll), which a window that only slides cannot cancel. False (default)
        is the paper's fovea: a window repositioned in the full image.
    """

    max_corners: int = 400
    quality: float = 0.01
    min_distance_px: float = 8.0
    block_size_px: int = 7
    lk_window_px: int = 21
    lk_levels: int = 3
    fb_threshold_px: float = 0.5
    ransac_threshold_rad: float = 0.002
    ransac_iterations: int = 100
    refine_iterations: int = 3
    min_corners: int = 20
    min_inliers: int = 12
    seed: int = 0
    leak_per_s: float = 0.0
    derotate: bool = False

    def __post_init__(self):
        def need(ok, name, why):
            if not ok:
                raise ValueError(f"StabiliseSettings.{name} = {getattr(self, name)!r} {why}")

        for name in ("max_corners", "block_size_px", "ransac_iterations", "min_corners"):
            need(isinstance(getattr(self, name), (int, np.integer)) and getattr(self, name) >= 1,
                 name, "must be an integer >= 1")
        need(isinstance(self.lk_window_px, (int, np.integer)) and self.lk_window_px >= 3
             and self.lk_window_px % 2 == 1, "lk_window_px", "must be an odd integer >= 3, e.g. 21")
        need(isinstance(self.lk_levels, (int, np.integer)) and 0 <= self.lk_levels <= 8,
             "lk_levels", "must be an integer in 0..8, e.g. 3")
        need(isinstance(self.refine_iterations, (int, np.integer)) and self.refine_iterations >= 0,
             "refine_iterations", "must be an integer >= 0")
        need(isinstance(self.min_inliers, (int, np.integer)) and self.min_inliers >= 3, "min_inliers",
             "must be an integer >= 3 (a rotation needs at least 2 bearings, a check a third)")
        need(0.0 < self.quality < 1.0, "quality", "must be in (0, 1), e.g. 0.01")
        for name in ("min_distance_px", "fb_threshold_px", "ransac_threshold_rad"):
            v = getattr(self, name)
            need(math.isfinite(v) and v > 0, name, "must be a positive finite number")
        need(self.ransac_threshold_rad < 0.5, "ransac_threshold_rad",
             "is an angle in radians and must be small (e.g. 0.002 rad, about 1 pixel)")
        need(math.isfinite(self.leak_per_s) and self.leak_per_s >= 0, "leak_per_s",
             "must be >= 0 (1/s; 0 holds the fovea's view still)")

    @property
    def flow(self) -> "FlowSettings":
        """The Lucas-Kanade settings of :func:`track_points`."""
        return FlowSettings(self.lk_window_px, self.lk_levels, self.fb_threshold_px)


@dataclass(frozen=True)
class FlowSettings:
    """Pyramidal Lucas-Kanade with a forward-backward check (:func:`track_points`).

    window_px : window side, pixels (odd). levels : pyramid levels above the full image.
    fb_threshold_px : a track is kept only if tracking it back lands within this of its start.
    drop_outside : also drop tracks that end outside the image (the head tracker keeps them:
        LK follows a corner up to a window past the edge, and its PnP can use the point).
    """

    window_px: int
    levels: int
    fb_threshold_px: float
    drop_outside: bool = True


# ---------------------------------------------------------------------------------------------
# Corners and tracks
# ---------------------------------------------------------------------------------------------

def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image of an (H, W) grey or (H, W, 3) RGB uint8 image."""
    return images.to_grey(image, require_uint8=True)


def detect_corners(grey: np.ndarray, settings: StabiliseSettings) -> np.ndarray:
    """Shi-Tomasi corners of a grey image.

    grey : (H, W) uint8. Returns (N, 2) float32 pixels; (0, 2) for a black, saturated or
    textureless image (where cv2.goodFeaturesToTrack returns None).
    """
    pts = cv2.goodFeaturesToTrack(grey, maxCorners=settings.max_corners, qualityLevel=settings.quality,
                                  minDistance=settings.min_distance_px, blockSize=settings.block_size_px)
    if pts is None:
        return np.zeros((0, 2), np.float32)
    return pts.reshape(-1, 2).astype(np.float32)


def track_points(prev_grey: np.ndarray, cur_grey: np.ndarray, uv_prev: np.ndarray,
                 flow: FlowSettings, uv_cur_guess: np.ndarray | None = None,
                 uv_back_guess_fn=None) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade tracks with a forward-backward check.

    prev_grey, cur_grey : (H, W) uint8. uv_prev : (N, 2) pixels in prev_grey.
    flow : the window, pyramid and forward-backward threshold (``StabiliseSettings.flow``).
    uv_cur_guess : optional (N, 2) initial guesses in cur_grey (e.g. the gyro's prediction); the
        search then starts there (cv2.OPTFLOW_USE_INITIAL_FLOW), so motions larger than the
        pyramid's reach are tracked.
    uv_back_guess_fn : optional function (M, 2) current pixels -> (M, 2) guesses in prev_grey for
        the backward track (the inverse prediction). Starting the backward track from the
        prediction, not from uv_prev, keeps the check independent of where the track began.
    Returns uv_cur (N, 2) float32 pixels and ok (N,) bool: tracked both ways, back within
    fb_threshold_px of the start, and (with drop_outside) inside the image.
    """
    n = len(uv_prev)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(uv_prev, np.float32).reshape(-1, 1, 2)
    lk = dict(winSize=(flow.window_px, flow.window_px), maxLevel=flow.levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    if uv_cur_guess is not None:
        guess = np.ascontiguousarray(uv_cur_guess, np.float32).reshape(-1, 1, 2)
        good_guess = np.isfinite(guess).all(axis=2)
        guess[~good_guess[:, 0]] = p0[~good_guess[:, 0]]
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_grey, cur_grey, p0, guess.copy(),
                                              flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    else:
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_grey, cur_grey, p0, None, **lk)
    if uv_back_guess_fn is not None:
        back = np.array(uv_back_guess_fn(p1.reshape(-1, 2)), np.float32).reshape(-1, 1, 2)  # a copy: written below
        bad = ~np.isfinite(back).all(axis=2)[:, 0]
        back[bad] = p1[bad]
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur_grey, prev_grey, p1, back.copy(),
                                               flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    else:
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur_grey, prev_grey, p1, None, **lk)
    uv_cur = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < flow.fb_threshold_px)
    if flow.drop_outside:
        h, w = cur_grey.shape[:2]
        ok &= (uv_cur[:, 0] >= 0) & (uv_cur[:, 0] <= w - 1) & (uv_cur[:, 1] >= 0) & (uv_cur[:, 1] <= h - 1)
    return uv_cur, ok


def bearings(cam: CameraIntrinsics, uv: np.ndarray) -> np.ndarray:
    """Unit bearing vectors (optical frame) of pixels through the camera's lens model.

    uv : (N, 2) pixels. Returns (N, 3) unit vectors, NaN rows where undistort has no answer.
    """
    xy = undistort(cam, np.asarray(uv, np.float64).reshape(-1, 2))
    f = np.column_stack([xy, np.ones(len(xy))])
    return f / np.linalg.norm(f, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Rotation-only model
# ---------------------------------------------------------------------------------------------
# Why a direct rotation fit and not the infinite homography: the paper fits H = K R K^-1 and
# decomposes it, but an 8-dof homography fitted to noisy, slightly parallax-laden matches absorbs
# part of the error into its 5 non-rotational dofs (scale, shear, perspective) and the projection
# onto SO(3) afterwards is not the best rotation for the data. Fitting the 3-dof rotation to the
# bearings directly (Wahba's problem, solved in closed form by Kabsch's SVD) is the exact model,
# needs minimal samples of 2 instead of 4 (far fewer RANSAC draws for the same confidence), takes
# its threshold as an angle, and works on bearings, so any lens model of formats.md (fisheye
# beyond 90 degrees too) is handled without a pixel-space homography.

def kabsch(f_prev: np.ndarray, f_cur: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rotations with f_prev ~ R f_cur (Wahba's problem), batched.

    f_prev, f_cur : (..., N, 3) unit vectors. weights : optional (..., N) non-negative.
    Returns R : (..., 3, 3) proper rotations minimising sum w |f_prev - R f_cur|^2.
    """
    if weights is None:
        B = np.einsum("...ni,...nj->...ij", f_prev, f_cur)
    else:
        B = np.einsum("...n,...ni,...nj->...ij", weights, f_prev, f_cur)
    U, _, Vt = np.linalg.svd(B)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(B.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    return U @ D @ Vt


def angular_residuals(R_prev_cur: np.ndarray, f_prev: np.ndarray, f_cur: np.ndarray) -> np.ndarray:
    """Angles (radians) between f_prev and R f_cur.

    R_prev_cur : (..., 3, 3); f_prev, f_cur : (N, 3) unit. Returns (..., N).
    """
    g = np.einsum("...ij,nj->...ni", R_prev_cur, f_cur)
    c = np.einsum("...ni,ni->...n", g, f_prev)
    s = np.linalg.norm(np.cross(g, f_prev), axis=-1)
    return np.arctan2(s, c)


def fit_rotation(f_prev: np.ndarray, f_cur: np.ndarray, settings: StabiliseSettings,
                 rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Robust rotation-only fit: MSAC over 2-point samples, then Kabsch refits on the inliers.

    f_prev, f_cur : (N, 3) unit bearings of the same static points, previous and current frame.
    Returns R_prev_cur (3, 3) and inliers (N,) bool. With N < 2 returns identity, no inliers.
    All hypotheses are solved and scored at once (batched SVD, one (M, N) residual array).
    """
    n = len(f_prev)
    if n < 2:
        return np.eye(3), np.zeros(n, bool)
    rng = rng if rng is not None else np.random.default_rng(settings.seed)
    m = settings.ransac_iterations
    i = rng.integers(0, n, m)
    j = (i + rng.integers(1, n, m)) % n  # a second, different point
    idx = np.stack([i, j], axis=1)
    R_h = kabsch(f_prev[idx], f_cur[idx])                       # (M, 3, 3)
    thr = settings.ransac_threshold_rad
    res = angular_residuals(R_h, f_prev, f_cur)                 # (M, N)
    # MSAC: truncated quadratic cost, so among hypotheses with as many inliers the tighter wins.
    cost = np.minimum(res, thr) ** 2
    best = int(np.argmin(cost.sum(axis=1)))
    R = R_h[best]
    inl = res[best] < thr
    for _ in range(settings.refine_iterations):
        if inl.sum() < 2:
            break
        R = kabsch(f_prev[inl], f_cur[inl])
        new = angular_residuals(R, f_prev, f_cur) < thr
        if np.array_equal(new, inl):
            break
        inl = new
    return R, inl


@dataclass
class RotationResult:
    """The rotation between two frames.

    R_prev_cur : (3, 3). inliers : number of corner tracks agreeing with it. tracked : tracks that
    passed the forward-backward check. corners : corners found in the previous frame.
    flagged : too few corners, tracks or inliers (R_prev_cur is then the prediction, or identity).
    reason : why flagged (OK if not). inlier_uv_prev, inlier_uv_cur : (K, 2) pixels of the inliers.
    """

    R_prev_cur: np.ndarray
    inliers: int
    tracked: int
    corners: int
    flagged: bool
    reason: str = OK
    inlier_uv_prev: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    inlier_uv_cur: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


def predict_pixels(cam: CameraIntrinsics, uv_prev: np.ndarray, R_prev_cur: np.ndarray) -> np.ndarray:
    """Where static points at infinity seen at uv_prev appear after the camera rotates by
    R_prev_cur. uv_prev : (N, 2) pixels. Returns (N, 2) pixels, NaN where there is no image."""
    f_prev = bearings(cam, uv_prev)
    return project(cam, f_prev @ R_prev_cur)  # f_cur = R^T f_prev, row-wise f_prev @ R


def frame_rotation(prev_grey: np.ndarray, cur_grey: np.ndarray, cam: CameraIntrinsics,
                   settings: StabiliseSettings, uv_prev: np.ndarray | None = None,
                   R_prev_cur_pred: np.ndarray | None = None,
                   rng: np.random.Generator | None = None) -> RotationResult:
    """Measure the rotation between two frames from the static background.

    prev_grey, cur_grey : (H, W) uint8. uv_prev : optional (N, 2) corners of prev_grey (detected
    here if None). R_prev_cur_pred : optional (3, 3) predicted rotation (the integrated gyro): it
    pre-warps the flow search and is returned when the frame is flagged. Never raises for a bad
    image: a black, saturated or textureless frame is flagged.
    """
    R_fallback = np.eye(3) if R_prev_cur_pred is None else np.asarray(R_prev_cur_pred, float)
    if uv_prev is None:
        uv_prev = detect_corners(prev_grey, settings)
    n_c = len(uv_prev)
    if n_c < settings.min_corners:
        return RotationResult(R_fallback, 0, 0, n_c, True, FEW_CORNERS_PREV)
    guess = back_fn = None
    if R_prev_cur_pred is not None:
        guess = predict_pixels(cam, uv_prev, R_prev_cur_pred)
        R_cur_prev_pred = np.asarray(R_prev_cur_pred, float).T
        back_fn = lambda uv: predict_pixels(cam, uv, R_cur_prev_pred)  # noqa: E731
    uv_cur, ok = track_points(prev_grey, cur_grey, uv_prev, settings.flow, guess, back_fn)
    if ok.sum() < settings.min_corners:
        return RotationResult(R_fallback, 0, int(ok.sum()), n_c, True, FEW_TRACKS)
    f_prev = bearings(cam, uv_prev[ok])
    f_cur = bearings(cam, uv_cur[ok])
    good = np.isfinite(f_prev).all(axis=1) & np.isfinite(f_cur).all(axis=1)
    f_prev, f_cur = f_prev[good], f_cur[good]
    R, inl = fit_rotation(f_prev, f_cur, settings, rng)
    n_in = int(inl.sum())
    up, uc = uv_prev[ok][good][inl], uv_cur[ok][good][inl]
    if n_in < settings.min_inliers:
        return RotationResult(R_fallback, n_in, int(ok.sum()), n_c, True, FEW_INLIERS, up, uc)
    return RotationResult(R, n_in, int(ok.sum()), n_c, False, OK, up, uc)


# ---------------------------------------------------------------------------------------------
# IMU
# ---------------------------------------------------------------------------------------------

def gyro_rotation(t_imu: np.ndarray, gyro: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """The rotation R_prev_cur from time t0 to t1 by integrating body-frame (camera-frame) rates.

    t_imu : (N,) s, increasing; gyro : (N, 3) rad/s in the camera frame (imu.txt's wx wy wz).
    The rate is interpolated linearly between samples (held at the ends) and integrated exactly
    for each piece's midpoint rate: R = exp(w1 dt1) exp(w2 dt2) ... (body rates multiply on the
    right). Returns (3, 3); identity if t1 <= t0 or no samples.
    """
    t_imu = np.asarray(t_imu, float)
    gyro = np.asarray(gyro, float).reshape(-1, 3)
    if t1 <= t0 or len(t_imu) == 0:
        return np.eye(3)
    inner = t_imu[(t_imu > t0) & (t_imu < t1)]
    grid = np.concatenate([[t0], inner, [t1]])
    mid = 0.5 * (grid[:-1] + grid[1:])
    w = np.column_stack([np.interp(mid, t_imu, gyro[:, k]) for k in range(3)])
    steps = Rotation.from_rotvec(w * np.diff(grid)[:, None])
    R = Rotation.identity()
    for s in steps:  # a handful of samples per frame; composition order matters
        R = R * s
    return R.as_matrix()


# ---------------------------------------------------------------------------------------------
# Software fovea
# ---------------------------------------------------------------------------------------------

@dataclass
class FoveaWindow:
    """Where the fovea sits in the full image.

    centre : (2,) float, pixels (OpenCV convention), the window's centre after clamping.
    angle_rad : the window's turn about its centre (image x towards image y), 0 unless derotating.
    clamped : the wanted centre would have put the window (partly) outside the image.
    wanted : (2,) float, the centre before clamping (NaN components if the reference direction is
        behind the camera).
    """

    centre: np.ndarray
    angle_rad: float
    clamped: bool
    wanted: np.ndarray


def follow_reference(R_cam0_ref: np.ndarray, R_cam0_cam: np.ndarray, fraction: float) -> np.ndarray:
    """Leaky integrator of the fovea's reference orientation: slerp the fraction (0..1) of the
    way from R_cam0_ref to R_cam0_cam. fraction 0 holds the reference still."""
    if fraction <= 0.0:
        return R_cam0_ref
    d = Rotation.from_matrix(R_cam0_ref.T @ R_cam0_cam).as_rotvec()
    return R_cam0_ref @ Rotation.from_rotvec(fraction * d).as_matrix()


def fovea_window(cam: CameraIntrinsics, R_cam0_cam: np.ndarray, R_cam0_ref: np.ndarray,
                 size: tuple[int, int], derotate: bool = False) -> FoveaWindow:
    """Place the fovea so that it shows the reference view.

    The reference's centre ray (the ray through the image centre in the reference orientation,
    the first frame's when the reference holds still) is projected into the current image; that
    is the fovea's centre. With derotate, the window also turns by the image angle of the
    reference's "down" direction there, cancelling roll. The centre is clamped so that the whole
    (turned) window lies in the image.

    size : (width, height) of the fovea, pixels, smaller than the image.
    """
    fw, fh = size
    c_img = np.array([[(cam.width - 1) / 2.0, (cam.height - 1) / 2.0]])
    d_ref = bearings(cam, c_img)[0]                                  # centre ray, reference frame
    R_cam_ref = R_cam0_cam.T @ R_cam0_ref
    d = R_cam_ref @ d_ref
    wanted = project(cam, d[None])[0]
    angle = 0.0
    if derotate and np.isfinite(wanted).all():
        down = R_cam_ref @ np.cross(d_ref, [1.0, 0.0, 0.0])          # reference image "down" at the centre
        down /= np.linalg.norm(down)
        eps = 1e-3
        p2 = project(cam, (d + eps * down)[None])[0]
        if np.isfinite(p2).all():
            v = p2 - wanted
            angle = math.atan2(-v[0], v[1])                           # 0 when "down" is image +y
    centre = wanted.copy()
    if not np.isfinite(centre).all():
        # The reference looks behind the camera: push the window towards its side of the image.
        centre = c_img[0] + 1e6 * np.nan_to_num(np.sign(d[:2]))
    ca, sa = abs(math.cos(angle)), abs(math.sin(angle))
    hx = 0.5 * (ca * fw + sa * fh)                                   # half extents of the turned window
    hy = 0.5 * (sa * fw + ca * fh)
    lo = np.array([hx - 0.5, hy - 0.5])
    hi = np.array([cam.width - 0.5 - hx, cam.height - 0.5 - hy])
    clamped_centre = np.clip(centre, lo, np.maximum(lo, hi))
    clamped = bool(np.any(np.abs(clamped_centre - centre) > 1e-9)) or not np.isfinite(wanted).all()
    return FoveaWindow(clamped_centre, angle, clamped, wanted)


def crop_fovea(image: np.ndarray, window: FoveaWindow, size: tuple[int, int]) -> np.ndarray:
    """The fovea's pixels: (fh, fw) or (fh, fw, 3), bilinear, so the window moves by sub-pixels.

    Output pixel (x, y) samples the image at centre + Rot(angle) ((x, y) - ((fw-1)/2, (fh-1)/2)).
    """
    fw, fh = size
    c, s = math.cos(window.angle_rad), math.sin(window.angle_rad)
    o = np.array([(fw - 1) / 2.0, (fh - 1) / 2.0])
    A = np.array([[c, -s], [s, c]])
    b = window.centre - A @ o
    M = np.hstack([A, b[:, None]])
    return cv2.warpAffine(image, M, (fw, fh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


# ---------------------------------------------------------------------------------------------
# The stabiliser, frame by frame
# ---------------------------------------------------------------------------------------------

@dataclass
class StepResult:
    """One frame through the stabiliser.

    t : s. R_prev_cur : (3, 3) relative to the previous processed frame. R_cam0_cam : (3, 3)
    relative to the first. window : the fovea. fovea : its image. flagged, reason, inliers : as
    RotationResult (inliers 0 for the first frame). R_imu : (3, 3) or None, the gyro's prediction
    R_prev_cur.
    """

    t: float
    R_prev_cur: np.ndarray
    R_cam0_cam: np.ndarray
    window: FoveaWindow
    fovea: np.ndarray
    flagged: bool
    reason: str
    inliers: int
    R_imu: np.ndarray | None = None


class Stabiliser:
    """Frame-by-frame stabilisation: feed images with :meth:`step`.

    camera : the intrinsics (any lens model). fovea : (width, height), pixels, smaller than the
    image. settings : StabiliseSettings.

    Tracking is against a reference frame: the previous frame normally. When a frame is flagged
    and has too few corners of its own (black, saturated, textureless, blurred) the reference
    stays the last good frame, so the next good frame is measured against it and the orientation
    recovers; when it has corners (the matching failed, e.g. a scene cut) it becomes the reference.
    """

    def __init__(self, camera: CameraIntrinsics, fovea: tuple[int, int] = (320, 240),
                 settings: StabiliseSettings | None = None):
        self.camera = camera
        self.settings = settings or StabiliseSettings()
        self.fovea_size = check_fovea(fovea, camera)
        self.rng = np.random.default_rng(self.settings.seed)
        self.R_cam0_cam = np.eye(3)
        self.R_cam0_ref = np.eye(3)     # the fovea's reference orientation
        self._key = None                # (t, grey, corners, R_cam0_key)
        self._t_prev = None

    @property
    def reference_t(self) -> float | None:
        """Time (s) of the frame the next one is measured against; None before the first."""
        return None if self._key is None else self._key[0]

    def step(self, t: float, image: np.ndarray, gyro: tuple[np.ndarray, np.ndarray] | None = None) -> StepResult:
        """Process one image taken at time t (s).

        image : (H, W) or (H, W, 3) uint8, the camera's size.
        gyro : optional (t_imu (N,), w (N, 3) rad/s) covering the time since the reference frame;
            its integral predicts the rotation (pre-warping the flow search), and stands in for
            the rotation when vision fails.
        """
        grey = to_grey(image)
        if grey.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"image is {grey.shape[1]}x{grey.shape[0]} but the camera is "
                             f"{self.camera.width}x{self.camera.height}; pass the camera of this sequence")
        corners = detect_corners(grey, self.settings)
        R_imu = None
        if self._key is None:
            R_prev_cur, flagged, reason, inliers = np.eye(3), len(corners) < self.settings.min_corners, OK, 0
            if flagged:
                reason = FEW_CORNERS_PREV
            self._key = (t, grey, corners, np.eye(3))
        else:
            t_key, g_key, c_key, R_cam0_key = self._key
            R_key_pred = None
            if gyro is not None:
                R_key_pred = gyro_rotation(gyro[0], gyro[1], t_key, t)
                R_imu = gyro_rotation(gyro[0], gyro[1], self._t_prev, t)
            res = frame_rotation(g_key, grey, self.camera, self.settings, c_key, R_key_pred, self.rng)
            flagged, reason, inliers = res.flagged, res.reason, res.inliers
            if not flagged:
                R_cam0_cur = R_cam0_key @ res.R_prev_cur
            elif R_key_pred is not None:
                R_cam0_cur = R_cam0_key @ R_key_pred          # the gyro carries a failed frame
            else:
                R_cam0_cur = self.R_cam0_cam                  # passed through: no rotation
            R_prev_cur = self.R_cam0_cam.T @ R_cam0_cur
            self.R_cam0_cam = nearest_rotation(R_cam0_cur)
            keep_key = flagged and len(corners) < self.settings.min_corners and res.reason != FEW_CORNERS_PREV
            if not keep_key:
                self._key = (t, grey, corners, self.R_cam0_cam)
            dt = t - self._t_prev
            if self.settings.leak_per_s > 0 and dt > 0:
                self.R_cam0_ref = follow_reference(self.R_cam0_ref, self.R_cam0_cam,
                                                   1.0 - math.exp(-self.settings.leak_per_s * dt))
        self._t_prev = t
        window = fovea_window(self.camera, self.R_cam0_cam, self.R_cam0_ref, self.fovea_size,
                              self.settings.derotate)
        crop = crop_fovea(image, window, self.fovea_size)
        return StepResult(t, R_prev_cur, self.R_cam0_cam.copy(), window, crop, flagged, reason, inliers, R_imu)


def check_fovea(fovea, camera: CameraIntrinsics) -> tuple[int, int]:
    """(width, height) of a fovea that fits in the camera's image, or a ValueError saying why."""
    try:
        fw, fh = (int(v) for v in fovea)
        ok = all(float(v) == int(v) for v in fovea)
    except (TypeError, ValueError):
        raise ValueError(f"fovea = {fovea!r} must be (width, height) in pixels, e.g. (320, 240)") from None
    if not ok or fw < 16 or fh < 16:
        raise ValueError(f"fovea = {fovea!r} must be whole pixels, at least 16x16, e.g. (320, 240)")
    if fw >= camera.width or fh >= camera.height:
        raise ValueError(f"fovea {fw}x{fh} does not fit inside the {camera.width}x{camera.height} image "
                         f"with room to move; choose a smaller fovea, e.g. "
                         f"{camera.width // 2}x{camera.height // 2}")
    return fw, fh
