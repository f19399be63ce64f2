"""Start-up with the metric scale from the head's own motion: no target, no depth, no IMU scale.

The camera's centre is off the head's axes (the reference head: 58 mm from the elevation axis,
37 mm from the pan axis), so a known head motion moves it along a known path. With the wearer
still, the head goes round the corners of a box in pan and elevation (the caller drives it;
see ``runtime.apps.head_motion``). Corners are tracked through the motion with pyramidal
Lucas-Kanade (forward-backward checked; new corners are taken where the tracked ones thin out),
and a bundle adjustment finds each point's inverse depth along its ray from the frame it was
first seen in, each frame's camera pose being the head model's at the encoders' angles,
``T_mount_cam(q)``, on a mount that drifts a little, as a still wearer's does:

- the mount's turn is the gyro's turn of the camera less the head's, with a constant-rate
  correction (the gyro's bias); without a gyro, a polynomial in time (much weaker: on a near
  planar scene a turn mimics a move). The gyro's axes and clock are first calibrated against the
  encoders (:func:`calibrate_to_encoders`): a gyro's scale error on the head's turns moves every
  point with the head as a wrong map scale does, so the images cannot find it;
- the mount's move is a cubic spline in time with knots a second apart, held near zero by a
  prior. A still wearer's sway and breathing (0.1-0.3 Hz, millimetres) fit such a spline; the
  head's box, a leg every 0.7 s, does not, so the move the head model knows fixes the scale.

So the map's unit comes from the head model's lengths alone. The world frame is the first
camera's centre with the caller's attitude for it (levelled by the IMU's gravity where there is
one). The result is a :class:`~.natural_start.NaturalStart` at the last frame of the motion
(``T_world_cam`` its pose) with ``scale = "head-motion"``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.interpolate import BSpline
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, undistort

from .natural_start import NaturalStart, StartSettings, StartWait, _corners, _ray_covariance, track_forward_backward


@dataclass(frozen=True)
class HeadMotionSettings:
    """How the points of a head-motion start are found and kept.

    corners, corner_min_distance_px, corner_quality : corners sought (at 640 px width), and the
        weakest corner taken as a fraction of the strongest (low: a plain desk's texture counts).
    refill_fraction : new corners are sought when fewer than this fraction of the first frame's
        are still tracked.
    min_points : mapped points a start needs.
    max_points, frame_step : the adjustment takes at most this many of the longest-tracked
        corners, and their sightings in every frame_step-th frame.
    min_frames_seen : frames a corner must be tracked through to be triangulated.
    pixel_sigma : a tracked corner's position noise, px.
    max_reproj_px : a point's largest RMS reprojection error after the adjustment.
    max_depth_rel_sigma : a point is kept when its depth's standard deviation is at most this
        fraction of its depth (an XYZ point is Gaussian only when its depth is well fixed).
    drift_knot_s : the mount's translation is a cubic spline in time with knots this far apart,
        s (a still wearer's sway is slower; the head's motion, faster).
    rotation_order : the degree of the polynomial in time of the mount's rotation vector
        without a gyro; gyro_rotation_order : the rotation's on top of the
        gyro's turn where there is one (1: a constant rate, what the calibration left of its bias).
    gyro_calibration_knot_s : the knot spacing, s, of the spline that takes the wearer's turn
        when the gyro is calibrated against the encoders (:func:`calibrate_to_encoders`).
    gyro_bias_sigma : the standard deviation, rad/s per axis, SLAM gives the bias that calibration
        found (its start's gyro bias).
    drift_sigma_m, drift_sigma_rad : the prior on each coefficient (m, rad over the motion).
    max_drift_m : a solved drift above this means the wearer moved: the start is refused.
    min_baseline_m : the camera's centre must move at least this far in the motion.
    initial_depth_m : where the adjustment starts every point along its ray.
    """

    corners: int = 200
    corner_min_distance_px: float = 14.0
    corner_quality: float = 0.002
    refill_fraction: float = 0.6
    min_points: int = 20
    max_points: int = 200
    frame_step: int = 2
    min_frames_seen: int = 10
    pixel_sigma: float = 0.5
    max_reproj_px: float = 1.5
    max_depth_rel_sigma: float = 0.2
    drift_knot_s: float = 1.0
    rotation_order: int = 4
    gyro_rotation_order: int = 1
    gyro_calibration_knot_s: float = 1.0
    gyro_bias_sigma: float = 0.002
    drift_sigma_m: float = 0.002
    drift_sigma_rad: float = math.radians(3.0)
    max_drift_m: float = 0.03
    min_baseline_m: float = 0.01
    initial_depth_m: float = 1.0


@dataclass(frozen=True)
class HeadMotionResult:
    """A head-motion start.

    start : the map at the last frame (points in the world frame, their pixels there).
    uv_ref : (n, 2) the same points' pixels in the first frame (NaN where a point was first
    seen later). T_world_cam0 : (4, 4) the first camera. T_cam0_cam : (F, 4, 4) every frame's
    solved camera in the first camera's frame. baseline_m : how far the camera's centre moved.
    drift_m, drift_rad : the mount's solved drift at the end of the motion. rms_px : the
    adjustment's RMS reprojection error. tracked : corners tracked long enough to be used.
    """

    start: NaturalStart
    uv_ref: np.ndarray
    T_world_cam0: np.ndarray
    T_cam0_cam: np.ndarray
    baseline_m: float
    drift_m: float
    drift_rad: float
    rms_px: float
    tracked: int


def _running_product(steps: Rotation) -> Rotation:
    """(n + 1) rotations: the identity, then S_0, S_0 S_1, ..., S_0 ... S_{n-1} of the n ``steps``
    (each applied in the frame the ones before left), as a prefix scan: log2(n) vectorised
    passes, each taking every product over twice the span, instead of n matrix products."""
    q = steps.as_quat()                                   # (n, 4) x, y, z, w
    shift = 1
    while shift < len(q):
        a, b = q[:-shift], q[shift:]
        ab = np.empty_like(b)                             # Hamilton products a b, element-wise
        ab[:, :3] = a[:, 3:] * b[:, :3] + b[:, 3:] * a[:, :3] + np.cross(a[:, :3], b[:, :3])
        ab[:, 3] = a[:, 3] * b[:, 3] - np.einsum("ij,ij->i", a[:, :3], b[:, :3])
        q = np.concatenate([q[:shift], ab])
        shift *= 2
    return Rotation.from_quat(np.concatenate([[[0.0, 0.0, 0.0, 1.0]], q]))


class GyroTurns:
    """The camera's turn integrated from gyro rows (k, 7) ``[t, wx, wy, wz, ...]`` (camera frame,
    rad/s; each sample's rate held until the next), relative to time ``t0``, as a function of
    time (within a sample, the fraction of its turn). :meth:`at` takes a correction of
    the gyro's axes and scale (a MEMS gyro's are off by about 1%: on the head's 20 degree turns,
    a tenth of a degree), its bias and its clock offset; :func:`calibrate_to_encoders` finds
    them."""

    def __init__(self, rows: np.ndarray, t0: float):
        rows = np.asarray(rows, float).reshape(-1, 7)
        rows = rows[np.r_[True, np.diff(rows[:, 0]) > 0]]
        if len(rows) < 2:
            raise ValueError("the gyro gave fewer than two samples over the head's motion")
        self.t, self.t0 = rows[:, 0], float(t0)
        self._w, self._dt = rows[:-1, 1:4], np.diff(self.t)[:, None]
        self._cache: tuple[bytes, tuple[Rotation, np.ndarray]] | None = None

    def _turns(self, E: np.ndarray, bias: np.ndarray) -> tuple[Rotation, np.ndarray]:
        """The turn at every sample's stamp (n,) and each sample's own turn, rotation vectors
        (n - 1, 3), for a correction E and a bias (cached: the adjustment asks again and again)."""
        key = E.tobytes() + bias.tobytes()
        if self._cache is None or self._cache[0] != key:
            phi = ((self._w - bias) * self._dt) @ (np.eye(3) + E).T
            self._cache = (key, (_running_product(Rotation.from_rotvec(phi)), phi))
        return self._cache[1]

    def at(self, t: np.ndarray, E: np.ndarray | None = None, delta_s: float = 0.0,
           bias: np.ndarray | None = None) -> np.ndarray:
        """(F, 3, 3) R_cam0_cam at times t (F,) s (held at the ends outside the samples), the
        gyro's rates w taken as (I + E)(w - bias) (E (3, 3), bias (3,) rad/s, default zero) and
        its clock ``delta_s`` late."""
        cum, phi = self._turns(np.zeros((3, 3)) if E is None else np.asarray(E, float),
                               np.zeros(3) if bias is None else np.asarray(bias, float))

        def turn(tau):
            # Within a sample the rate is held: the turn so far, then that fraction of its own.
            tau = np.clip(np.atleast_1d(np.asarray(tau, float)), self.t[0], self.t[-1])
            i = np.clip(np.searchsorted(self.t, tau, side="right") - 1, 0, len(phi) - 1)
            return cum[i] * Rotation.from_rotvec(phi[i] * ((tau - self.t[i]) / self._dt[i, 0])[:, None])

        return (turn(self.t0 + delta_s).inv() * turn(np.asarray(t, float) + delta_s)).as_matrix()


def calibrate_to_encoders(gyro: GyroTurns, t: np.ndarray, M: np.ndarray, knot_s: float = 1.0
                          ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """The gyro's axes correction E (3, 3), clock offset delta (s) and bias (3,) rad/s for
    :meth:`GyroTurns.at`, found against the encoders, and the fit's RMS, rad.

    Through the motion the gyro sees the head's turns (20 degrees, fast, known from the encoders
    through the head model's ``T_mount_cam`` (F, 4, 4) at the frames' times t (F,) s) on top of
    the wearer's (a degree or so, slow). The E and delta that leave the mount's turn (the gyro's
    turn of the camera less the head's) a slow spline in time (knots ``knot_s`` apart) are the
    gyro's own. The bias is the sensor's (it turns with the head), so it is found with them.
    Only the columns of E for the axes the head turns about are well fixed; the others barely
    act on this motion. Huber's loss keeps the frames where a gyro sample straddles a sharp
    reversal from pulling the fit.

    Why first and apart: a gyro scale error e on the head's turn theta(t) turns the camera by
    e theta(t), which moves the image as the head's own parallax r theta(t) / Z does (r the
    camera's radius about the axis, Z the depth): on a near planar scene the adjustment cannot
    tell them apart, and 0.1% of gyro scale is about 3% of map scale at r / Z = 0.03."""
    R_m = M[:, :3, :3]
    B = _spline_basis(t, knot_s)
    # Frames the gyro's samples cover (with room for the clock offset): outside, it says nothing.
    inside = (t >= gyro.t[0] + 0.01) & (t <= gyro.t[-1] - 0.01)

    def residuals(p):
        R_cam = gyro.at(t, p[1:10].reshape(3, 3), p[0], p[10:13])
        R_turn = R_m[0][None] @ R_cam @ np.transpose(R_m, (0, 2, 1))          # the mount's, per the gyro
        W = Rotation.from_rotvec(B @ p[13:].reshape(-1, 3)).as_matrix()
        return Rotation.from_matrix(np.transpose(W, (0, 2, 1)) @ R_turn).as_rotvec()[inside].ravel()

    sol = least_squares(residuals, np.zeros(13 + 3 * B.shape[1]), x_scale=1e-3, loss="huber", f_scale=2e-4)
    p = sol.x
    return p[1:10].reshape(3, 3), float(p[0]), p[10:13], float(np.sqrt(np.mean(sol.fun**2)))


def baseline_m(T_mount_cam: np.ndarray) -> float:
    """The largest distance, m, of the camera's centre from where it started over (F, 4, 4)
    head-model poses: zero for a head whose camera centre lies on its axes."""
    c = T_mount_cam[:, :3, 3]
    return float(np.linalg.norm(c - c[0], axis=1).max())


def _spline_basis(t: np.ndarray, spacing_s: float) -> np.ndarray:
    """(F, m) a cubic B-spline basis over times t (F,) s with knots about ``spacing_s`` apart,
    less its value at the first time (no drift at the first frame)."""
    t = np.asarray(t, float) - t[0]
    span = max(float(t[-1]), 1e-9)
    inner = np.linspace(0.0, span, max(1, int(np.ceil(span / spacing_s))) + 1)
    knots = np.r_[[0.0] * 3, inner, [span] * 3]
    B = BSpline.design_matrix(np.clip(t, 0.0, span), knots, 3).toarray()
    return (B - B[0])[:, 1:]            # the first function is the one at t = 0: no drift there


def _basis(tau: np.ndarray, order: int) -> np.ndarray:
    """(F, order) the drift's basis at normalised times tau (F,) in [0, 1]: Legendre polynomials
    of degree 1..order on [-1, 1], less their value at tau = 0 (no drift at the first frame).
    Orthogonal, each of size about 1, so that one prior sigma fits every coefficient."""
    x = 2.0 * np.asarray(tau, float) - 1.0
    V = np.polynomial.legendre.legvander(x, order)[:, 1:]
    return V - np.polynomial.legendre.legvander(np.array([-1.0]), order)[:, 1:]


@dataclass(frozen=True)
class _Problem:
    """The adjustment's fixed data. tau (F,) normalised times; M (F, 4, 4) head-model poses;
    fi, pj (k,) each sighting's frame and point; xy (k, 2) its normalised coordinates; anchor
    (n,) each point's first frame; m (n, 3) its unit ray there; sigma_n the noise in normalised
    units; rot_order the degree of the mount's rotation vector's polynomial in time
    (:func:`_basis`); B_move (F, m) the basis of its translation (:func:`_spline_basis`); prior
    (n_drift,) sigmas. R_gyro (F, 3, 3) : the camera's turn at the frames as the calibrated
    gyro measured it (R_cam0_cam); then the mount's turn is the gyro's less the head's, times the
    rotation polynomial; without, the polynomial is all of it."""

    tau: np.ndarray
    M: np.ndarray
    fi: np.ndarray
    pj: np.ndarray
    xy: np.ndarray
    anchor: np.ndarray
    m: np.ndarray
    sigma_n: float
    rot_order: int
    B_move: np.ndarray
    prior: np.ndarray
    R_gyro: np.ndarray | None = None

    @property
    def n_rot(self) -> int:
        """The rotation polynomial's parameters."""
        return 3 * self.rot_order

    @property
    def n_drift(self) -> int:
        return self.n_rot + 3 * self.B_move.shape[1]

    def poses(self, d: np.ndarray) -> np.ndarray:
        """(F, 4, 4) T_cam0_cam from drift parameters d: the head model's poses on the mount
        turned by the rotation polynomial and moved by the translation spline."""
        F = len(self.tau)
        w = _basis(self.tau, self.rot_order) @ d[:self.n_rot].reshape(-1, 3)
        b = d[self.n_rot:].reshape(-1, 3)
        D = np.tile(np.eye(4), (F, 1, 1))
        D[:, :3, :3] = Rotation.from_rotvec(w).as_matrix()
        if self.R_gyro is not None:
            R_m = self.M[:, :3, :3]
            R_turn = R_m[0][None] @ self.R_gyro @ np.transpose(R_m, (0, 2, 1))
            D[:, :3, :3] = R_turn @ D[:, :3, :3]
        D[:, :3, 3] = self.B_move @ b
        return np.linalg.inv(self.M[0])[None] @ D @ self.M

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Reprojection residuals in units of the pixel noise, then the drift's prior."""
        nd = self.n_drift
        d, rho = x[:nd], x[nd:]
        T = self.poses(d)
        a, i, j = self.anchor[self.pj], self.fi, self.pj
        # R_i^T (rho (c_a - c_i) + R_a m): the point's direction from camera i, finite as rho -> 0.
        v = rho[j, None] * (T[a, :3, 3] - T[i, :3, 3]) + np.einsum("nij,nj->ni", T[a, :3, :3], self.m[j])
        P = np.einsum("nji,nj->ni", T[i, :3, :3], v)
        z = np.where(P[:, 2] > 1e-6, P[:, 2], 1e-6)
        r = (P[:, :2] / z[:, None] - self.xy) / self.sigma_n
        return np.concatenate([r.ravel(), d / self.prior])

    def jacobian(self, x: np.ndarray, r0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """d residuals / d x at x (residuals r0 there), in two parts: J_d (2k + n_drift, n_drift)
        the drift's columns by forward differences (each moves every pose), and g (2k,) each
        reprojection residual's derivative by its own point's inverse depth, in closed form
        (an inverse depth moves only its point's sightings)."""
        nd, k = self.n_drift, len(self.fi)
        J_d = np.empty((len(r0), nd))
        for c in range(nd):
            xh = x.copy()
            xh[c] += 1e-6
            J_d[:, c] = (self.residuals(xh) - r0) / 1e-6
        d, rho = x[:nd], x[nd:]
        T = self.poses(d)
        a, i, j = self.anchor[self.pj], self.fi, self.pj
        dc = T[a, :3, 3] - T[i, :3, 3]
        v = rho[j, None] * dc + np.einsum("nij,nj->ni", T[a, :3, :3], self.m[j])
        P = np.einsum("nji,nj->ni", T[i, :3, :3], v)
        dP = np.einsum("nji,nj->ni", T[i, :3, :3], dc)
        z = np.where(P[:, 2] > 1e-6, P[:, 2], 1e-6)
        g = (dP[:, :2] / z[:, None] - P[:, :2] * (dP[:, 2] / z**2)[:, None]) / self.sigma_n
        return J_d, g.ravel()


def _huber_weights(r: np.ndarray, k: int, c: float) -> np.ndarray:
    """(2k + m,) IRLS weights of Huber's loss on each sighting's residual pair's norm (scale c);
    the prior rows' weight 1."""
    e = np.sqrt((r[:2 * k].reshape(-1, 2) ** 2).sum(axis=1))
    w = np.where(e <= c, 1.0, c / np.maximum(e, 1e-12))
    return np.r_[np.repeat(w, 2), np.ones(len(r) - 2 * k)]


def _robust_cost(r: np.ndarray, k: int, c: float) -> float:
    e = np.sqrt((r[:2 * k].reshape(-1, 2) ** 2).sum(axis=1))
    return float(np.sum(np.where(e <= c, 0.5 * e**2, c * e - 0.5 * c * c)) + 0.5 * np.sum(r[2 * k:] ** 2))


def _adjust(pb: _Problem, x0: np.ndarray, huber: float = 2.0, iterations: int = 30) -> np.ndarray:
    """Levenberg-Marquardt on Huber's loss (iteratively reweighted), the inverse depths
    eliminated by their Schur complement (each touches only its point's sightings): x (n_drift +
    n,) from x0. Inverse depths are held at 1e-4 /m or more (in front of the camera, at most 10 km)."""
    nd, k = pb.n_drift, len(pb.fi)
    n = len(x0) - nd
    x = x0.copy()
    x[nd:] = np.maximum(x[nd:], 1e-4)
    r = pb.residuals(x)
    cost = _robust_cost(r, k, huber)
    lam = 1e-3
    rows_pt = np.repeat(pb.pj, 2)
    for _ in range(iterations):
        J_d, g = pb.jacobian(x, r)
        w = _huber_weights(r, k, huber)
        wr, wJ = w * r, w[:, None] * J_d
        # Normal equations in blocks: drift-drift, drift-depth, depth-depth (diagonal).
        H_dd = J_d.T @ wJ
        H_dp = np.zeros((nd, n))
        np.add.at(H_dp.T, rows_pt, wJ[:2 * k] * g[:, None])
        h_pp = np.bincount(rows_pt, weights=w[:2 * k] * g * g, minlength=n)
        b_d = J_d.T @ wr
        b_p = np.bincount(rows_pt, weights=wr[:2 * k] * g, minlength=n)
        while True:
            A_dd = H_dd + lam * np.diag(np.diag(H_dd) + 1e-9)
            a_pp = h_pp * (1 + lam) + 1e-9
            S = A_dd - (H_dp / a_pp) @ H_dp.T
            dx_d = np.linalg.solve(S, -(b_d - H_dp @ (b_p / a_pp)))
            dx_p = -(b_p + H_dp.T @ dx_d) / a_pp
            xn = x + np.r_[dx_d, dx_p]
            xn[nd:] = np.maximum(xn[nd:], 1e-4)
            rn = pb.residuals(xn)
            cn = _robust_cost(rn, k, huber)
            if cn < cost:
                break
            lam *= 4.0
            if lam > 1e8:
                return x
        done = cost - cn < 1e-7 * cost
        x, r, cost, lam = xn, rn, cn, max(lam / 3.0, 1e-7)
        if done:
            break
    return x


def _information(pb: _Problem, x: np.ndarray, huber: float = 2.0) -> np.ndarray:
    """(n_drift + n, n_drift + n) the robustly weighted Gauss-Newton information at x."""
    nd, k = pb.n_drift, len(pb.fi)
    n = len(x) - nd
    r = pb.residuals(x)
    J_d, g = pb.jacobian(x, r)
    w = _huber_weights(r, k, huber)
    rows_pt = np.repeat(pb.pj, 2)
    H = np.zeros((nd + n, nd + n))
    H[:nd, :nd] = J_d.T @ (w[:, None] * J_d)
    np.add.at(H[nd:, :nd], rows_pt, (w[:, None] * J_d)[:2 * k] * g[:, None])
    H[:nd, nd:] = H[nd:, :nd].T
    H[nd + np.arange(n), nd + np.arange(n)] = np.bincount(rows_pt, weights=w[:2 * k] * g * g, minlength=n)
    return H


class HeadMotionStart:
    """Feeds frames of a head motion with their head-model poses; :meth:`solve` makes the start.

    cam : the intrinsics and lens. settings : :class:`HeadMotionSettings`.
    """

    def __init__(self, cam: CameraIntrinsics, settings: HeadMotionSettings = HeadMotionSettings()):
        self.cam, self.s = cam, settings
        self._prev: np.ndarray | None = None
        self._tracks: list[np.ndarray] = []     # per frame (N_i, 2) pixels of the N_i tracks so far, NaN once lost
        self._first: np.ndarray = np.zeros(0, int)   # each track's first frame
        self._t: list[float] = []
        self._M: list[np.ndarray] = []
        self._n0 = 0

    @property
    def frames(self) -> int:
        return len(self._t)

    @property
    def times(self) -> list[float]:
        """The frames' times so far, s."""
        return list(self._t)

    def _detect(self, g8: np.ndarray, avoid: np.ndarray) -> np.ndarray:
        """(k, 2) new corners of g8, none within the corner spacing of ``avoid`` (m, 2) px."""
        s = self.s
        mask = np.full(g8.shape, 255, np.uint8)
        r = int(round(s.corner_min_distance_px * self.cam.width / 640.0))
        for u, v in avoid:
            cv2.circle(mask, (int(round(u)), int(round(v))), r, 0, -1)
        return _corners(self.cam, g8, StartSettings(corners=s.corners, corner_min_distance_px=s.corner_min_distance_px),
                        mask, quality=s.corner_quality)

    def add(self, grey: np.ndarray, t: float, T_mount_cam: np.ndarray) -> None:
        """One frame (H, W) grey at time t (s), the camera's pose on the mount (4, 4) from the
        head model at the encoders' angles. The first frame is the reference."""
        g8 = np.clip(grey, 0, 255).astype(np.uint8)
        f = self.frames
        if self._prev is None:
            uv = self._detect(g8, np.empty((0, 2)))
            self._n0 = len(uv)
            self._first = np.zeros(len(uv), int)
        else:
            prev = self._tracks[-1]
            uv = np.full_like(prev, np.nan)
            idx = np.flatnonzero(np.isfinite(prev[:, 0]))
            if len(idx):
                p1, ok = track_forward_backward(self.cam, self._prev, g8, prev[idx])
                uv[idx[ok]] = p1[ok]
            alive = np.isfinite(uv[:, 0])
            if alive.sum() < self.s.refill_fraction * max(self._n0, 1):
                new = self._detect(g8, uv[alive])[: max(self._n0 - int(alive.sum()), 0)]
                if len(new):
                    self._tracks = [np.vstack([u, np.full((len(new), 2), np.nan)]) for u in self._tracks]
                    uv = np.vstack([uv, new])
                    self._first = np.r_[self._first, np.full(len(new), f)]
        self._prev = g8
        self._tracks.append(np.asarray(uv, float))
        self._t.append(float(t))
        self._M.append(np.asarray(T_mount_cam, float))

    def solve(self, R_world_cam0: np.ndarray = np.eye(3), gyro_rows: np.ndarray | None = None
              ) -> HeadMotionResult | StartWait:
        """The start from the frames so far, or why not. R_world_cam0 : (3, 3) the first
        camera's attitude in the world (the IMU's level; identity: the first camera's frame).
        gyro_rows : (k, 7) IMU rows ``[t, wx, wy, wz, ax, ay, az]`` (camera frame) over the
        motion, or None: then the mount's turn is found from the images alone (weaker)."""
        s = self.s
        if self.frames < 3:
            return StartWait("the head has not moved yet")
        M = np.array(self._M)
        base = baseline_m(M)
        if base < s.min_baseline_m:
            return StartWait(f"the camera's centre moved {1e3 * base:.1f} mm in the head's motion (at least "
                             f"{1e3 * s.min_baseline_m:.0f} mm needed): no baseline to fix the scale")
        uv = np.array(self._tracks)                   # (F, N, 2)
        seen = np.isfinite(uv[..., 0])
        use = seen.sum(axis=0) >= s.min_frames_seen
        if use.sum() < s.min_points:
            return StartWait(f"too few corners tracked through the head's motion ({int(use.sum())} of "
                             f"{s.min_points}): point the camera at something textured")
        # The longest-tracked corners, and every other frame: the drift is slow, the sightings many.
        cols = np.flatnonzero(use)
        cols = np.sort(cols[np.argsort(-seen[:, cols].sum(axis=0), kind="stable")[:s.max_points]])
        anchor = self._first[cols]
        xy_a = undistort(self.cam, uv[anchor, cols])
        fin = np.isfinite(xy_a).all(axis=1)
        cols, anchor, xy_a = cols[fin], anchor[fin], xy_a[fin]
        m = np.column_stack([xy_a, np.ones(len(cols))])
        m /= np.linalg.norm(m, axis=1, keepdims=True)
        # Each point by its first frame's ray and its inverse depth: later sightings fix it.
        obs = seen[:, cols].copy()
        obs[anchor, np.arange(len(cols))] = False
        sub = np.zeros(len(obs), bool)
        sub[::s.frame_step] = True
        sub[-1] = True
        obs &= sub[:, None]
        fi, k = np.nonzero(obs)
        xy = undistort(self.cam, uv[fi, cols[k]])
        good = np.isfinite(xy).all(axis=1)
        fi, k, xy = fi[good], k[good], xy[good]
        t = np.array(self._t)
        tau = (t - t[0]) / max(t[-1] - t[0], 1e-9)
        R_gyro, rot_order, bias = None, s.rotation_order, None
        if gyro_rows is not None and len(gyro_rows) >= 2:
            gyro = GyroTurns(gyro_rows, t[0])
            E, delta, bias, _ = calibrate_to_encoders(gyro, t, M, s.gyro_calibration_knot_s)
            R_gyro, rot_order = gyro.at(t, E, delta, bias), s.gyro_rotation_order
        B_move = _spline_basis(t, s.drift_knot_s)
        prior = np.r_[np.full(3 * rot_order, s.drift_sigma_rad), np.full(3 * B_move.shape[1], s.drift_sigma_m)]
        sigma_n = s.pixel_sigma / self.cam.fx
        pb = _Problem(tau, M, fi, k, xy, anchor, m, sigma_n, rot_order, B_move, prior, R_gyro)
        x = np.r_[np.zeros(pb.n_drift), np.full(len(cols), 1.0 / s.initial_depth_m)]
        x = _adjust(pb, x)
        for _ in range(2):
            # Outliers out (a corner that slid along an edge or a silhouette), then solve again.
            n = len(cols)
            r = pb.residuals(x)[:2 * len(pb.fi)].reshape(-1, 2)
            cnt = np.maximum(np.bincount(pb.pj, minlength=n), 1)
            rms_pt = np.sqrt(np.bincount(pb.pj, weights=(r**2).sum(axis=1), minlength=n) / cnt / 2) * s.pixel_sigma
            keep = (rms_pt <= s.max_reproj_px) & (np.bincount(pb.pj, minlength=n) >= s.min_frames_seen - 1)
            if keep.sum() < s.min_points:
                return StartWait(f"the tracked corners disagree with the head's motion ({int(keep.sum())} of "
                                 f"{n} fit within {s.max_reproj_px} px): did the wearer move?")
            if keep.all():
                break
            new = np.cumsum(keep) - 1
            o = keep[pb.pj]
            cols = cols[keep]
            pb = _Problem(tau, M, pb.fi[o], new[pb.pj[o]], pb.xy[o], pb.anchor[keep], pb.m[keep], sigma_n,
                          rot_order, B_move, prior, R_gyro)
            x = _adjust(pb, np.r_[x[:pb.n_drift], x[pb.n_drift:][keep]])
        nd = pb.n_drift
        d, rho = x[:nd], x[nd:]
        T = pb.poses(d)
        D_end = M[0] @ T[-1] @ np.linalg.inv(M[-1])     # the mount's drift at the last frame
        drift_m = float(np.linalg.norm(D_end[:3, 3]))
        drift_rad = float(np.linalg.norm(Rotation.from_matrix(D_end[:3, :3]).as_rotvec()))
        if drift_m > s.max_drift_m:
            return StartWait(f"the wearer moved {100 * drift_m:.1f} cm during the head's motion (at most "
                             f"{100 * s.max_drift_m:.0f} cm): keep still while the head moves")
        res = pb.residuals(x)[:2 * len(pb.fi)]
        rms_px = float(np.sqrt(np.mean(res**2))) * s.pixel_sigma
        # The inverse depths' variances: the Gauss-Newton inverse at the solution, scaled by the
        # residuals' own spread (at least the assumed noise); across each ray, the pixel noise.
        var = max(1.0, float(np.mean(res**2)))
        sd_rho = np.sqrt(np.maximum(np.diag(np.linalg.pinv(_information(pb, x), hermitian=True))[nd:], 0.0) * var)
        rho_safe = np.maximum(rho, 1e-9)
        depth = 1.0 / rho_safe
        ray0 = np.einsum("nij,nj->ni", T[pb.anchor, :3, :3], pb.m)      # in the first camera's frame
        X = T[pb.anchor, :3, 3] + ray0 * depth[:, None]
        sd_depth = sd_rho / rho_safe**2
        last = uv[-1, cols]
        P_last = (X - T[-1, :3, 3]) @ T[-1, :3, :3]
        ok = (rho > 0) & (sd_depth <= s.max_depth_rel_sigma * depth) & np.isfinite(last).all(axis=1) \
            & (P_last[:, 2] > 0.05)
        if ok.sum() < s.min_points:
            return StartWait(f"too few points fixed by the head's motion ({int(ok.sum())} of {s.min_points}): the "
                             "scene is too far for this head's baseline, or too plain")
        cov = _ray_covariance(ray0[ok], sd_depth[ok], depth[ok] * s.pixel_sigma / self.cam.fx)
        T_world_cam0 = np.eye(4)
        T_world_cam0[:3, :3] = R_world_cam0
        R = np.asarray(R_world_cam0, float)
        ns = NaturalStart(frame=self.frames - 1, uv=last[ok], xyz=X[ok] @ R.T, xyz_cov=R[None] @ cov @ R.T[None],
                          scale="head-motion", T_world_cam=T_world_cam0 @ T[-1], gyro_bias=bias,
                          gyro_bias_sigma=s.gyro_bias_sigma)
        return HeadMotionResult(ns, uv[0, cols][ok], T_world_cam0, T, base, drift_m, drift_rad, rms_px, len(cols))


def point_at_pixel(cam: CameraIntrinsics, res: HeadMotionResult, uv: np.ndarray, neighbours: int = 8) -> np.ndarray:
    """(3,) the world point at pixel ``uv`` (2,) of the first frame (a person's click): where its
    ray meets the plane of the mapped points nearest it in that image (their median depth along
    the ray where they do not span a plane)."""
    uv = np.asarray(uv, float).reshape(2)
    seen0 = np.isfinite(res.uv_ref).all(axis=1)
    d = np.linalg.norm(res.uv_ref[seen0] - uv, axis=1)
    near = np.argsort(d)[:max(3, neighbours)]
    Y = res.start.xyz[seen0][near]
    T0 = res.T_world_cam0
    ray = np.r_[undistort(cam, uv[None])[0], 1.0]
    ray = T0[:3, :3] @ (ray / np.linalg.norm(ray))
    o = T0[:3, 3]
    c = Y.mean(axis=0)
    _, sv, Vt = np.linalg.svd(Y - c)
    n = Vt[2]
    if len(Y) >= 3 and sv[1] > 1e-3 and sv[2] < 0.2 * sv[1] and abs(ray @ n) > 0.2:
        return o + ray * float(((c - o) @ n) / (ray @ n))
    return o + ray * float(np.median((Y - o) @ ray))


__all__ = ["HeadMotionResult", "HeadMotionSettings", "GyroTurns", "HeadMotionStart", "baseline_m",
           "point_at_pixel"]
