"""The metric scale and gravity of a map started from natural features, from the IMU.

A camera-only start fixes the map's unit arbitrarily (its points' median depth). The
accelerometer measures metric acceleration, so the camera's trajectory in map units and the IMU's
integrated motion between the same frames give the scale once the camera accelerates
(Mur-Artal and Tardos, "Visual-inertial monocular SLAM with map reuse", 2017, section IV-A: the
linear initialisation; velocities eliminated over triplets of frames). For three frames 1, 2, 3
with positions p (map units), camera-to-world rotations R, intervals dt12, dt23 and the IMU's
pre-integrated velocity and position changes dv, dp (IMU frame of the first of each pair):

    s [(p2 - p1) dt23 - (p3 - p2) dt12] + g (dt12 dt23^2 + dt12^2 dt23) / 2
        = R1 dp12 dt23 - R2 dp23 dt12 - R1 dv12 dt12 dt23

linear in the scale s (metres per map unit) and gravity g (world frame, m/s^2, |g| = 9.81). The
least-squares solution over every triplet is refined with g's magnitude fixed (Gauss-Newton over
s and g's direction). imu.txt is in the camera's frame (shared/formats.md), so R is the camera's;
the lever arm between the IMU and the optical centre is neglected, and the accelerometer's bias
(a BMI088's: up to 0.1 m/s^2, against the 1-3 m/s^2 a wearer's walk gives) is estimated with
them, held near zero by a prior, since only the camera's turns separate it from gravity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kinematics.transforms import skew

#: Standard gravity, m/s^2.
GRAVITY_M_S2 = 9.80665
#: Frames an estimate takes are this far apart at least, s (a longer interval averages the
#: positions' noise).
STRIDE_S = 0.3


@dataclass(frozen=True)
class ScaleEstimate:
    """scale : metres per map unit. g_world : (3,) gravity in the map's (first camera's) frame,
    m/s^2. sigma_rel : the scale's relative standard deviation from the fit's residuals.
    triplets : frame triplets used. excitation : RMS of the map's acceleration term, m/s^2 (small:
    the camera barely accelerated and the scale is weakly observed)."""

    scale: float
    g_world: np.ndarray
    sigma_rel: float
    triplets: int
    excitation: float
    accel_bias: np.ndarray = None


def _so3_exp(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-9:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def preintegrate(t_imu: np.ndarray, gyro: np.ndarray, accel: np.ndarray, t0: float, t1: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dR, dv, dp): the IMU's rotation, velocity and position change from t0 to t1 in its frame at
    t0 (gravity not removed), from samples (k,) times, (k, 3) rad/s and m/s^2, linear between
    stamps (each step takes the rate and force at its middle)."""
    dR, dv, dp = np.eye(3), np.zeros(3), np.zeros(3)
    i = max(int(np.searchsorted(t_imu, t0, side="right")) - 1, 0)
    t = t0
    last = len(t_imu) - 1
    while t < t1 - 1e-12 and i <= last:
        t_next = min(t_imu[i + 1] if i < last else t1, t1)
        h = t_next - t
        if h > 0:
            if i < last:
                # The samples' values at the step's midpoint, interpolated between stamps i and i + 1.
                c = ((t + t_next) / 2 - t_imu[i]) / (t_imu[i + 1] - t_imu[i])
                w, f = gyro[i] + c * (gyro[i + 1] - gyro[i]), accel[i] + c * (accel[i + 1] - accel[i])
            else:
                w, f = gyro[i], accel[i]
            R_mid = dR @ _so3_exp(w * h / 2)
            a = R_mid @ f
            dp = dp + dv * h + 0.5 * a * h * h
            dv = dv + a * h
            dR = dR @ _so3_exp(w * h)
        t = t_next
        i += 1
    return dR, dv, dp


def kept_frames(t: np.ndarray, stride_s: float = STRIDE_S) -> list[int]:
    """Indices of the frames (n,) s an estimate takes: the first, then each at least ``stride_s``
    after the last taken."""
    keep = [0]
    for k in range(1, len(t)):
        if t[k] - t[keep[-1]] >= stride_s:
            keep.append(k)
    return keep


def estimate_scale(t: np.ndarray, p: np.ndarray, R: np.ndarray, t_imu: np.ndarray, gyro: np.ndarray,
                   accel: np.ndarray, stride_s: float = STRIDE_S, bias_sigma: float = 0.2) -> ScaleEstimate | None:
    """The scale and gravity from the camera's poses (n,) times s, (n, 3) positions in map units,
    (n, 3, 3) camera-to-world rotations, and the IMU's samples (camera frame). Frames are taken
    ``stride_s`` apart (:func:`kept_frames`). None with fewer than three such frames inside the
    IMU's span."""
    keep = [k for k in kept_frames(t, stride_s) if t_imu[0] <= t[k] <= t_imu[-1]]
    if len(keep) < 3:
        return None
    tk = t[keep]
    pre = [preintegrate(t_imu, gyro, accel, tk[i], tk[i + 1]) for i in range(len(tk) - 1)]
    return solve_scale(tk, p[keep], R[keep], pre, bias_sigma)


def solve_scale(tk: np.ndarray, pk: np.ndarray, Rk: np.ndarray, pre: list, bias_sigma: float = 0.2
                ) -> ScaleEstimate | None:
    """:func:`estimate_scale`'s solution from its frames (m,) s, (m, 3), (m, 3, 3) (three or more)
    and the IMU's pre-integration (dR, dv, dp) over each interval between them (m - 1)."""
    A, b, half, Bb = [], [], [], []
    for i in range(len(tk) - 2):
        d12, d23 = tk[i + 1] - tk[i], tk[i + 2] - tk[i + 1]
        _, dv12, dp12 = pre[i]
        _, _, dp23 = pre[i + 1]
        lam = (pk[i + 1] - pk[i]) * d23 - (pk[i + 2] - pk[i + 1]) * d12
        beta = 0.5 * np.eye(3) * (d12 * d23**2 + d12**2 * d23)
        # The IMU's side: an accelerometer measures specific force (the acceleration less g).
        gam = Rk[i] @ dp12 * d23 - Rk[i + 1] @ dp23 * d12 - Rk[i] @ dv12 * d12 * d23
        A.append(np.column_stack([lam, beta]))
        b.append(gam)
        # A constant accelerometer bias b_a adds R dt^2/2 to dp and R dt to dv (the turn within an
        # interval neglected): its column on the left-hand side.
        Bb.append(0.5 * Rk[i] * d12**2 * d23 - 0.5 * Rk[i + 1] * d23**2 * d12 - Rk[i] * d12**2 * d23)
        half.append(0.5 * d12 * d23 * (d12 + d23))
    A, b, Bb = np.vstack(A), np.concatenate(b), np.vstack(Bb)
    lam, beta = A[:, 0], A[:, 1:]
    # The map's positions are the noisy side (a filter's, differenced twice); the IMU's side is
    # nearly exact over these intervals. So lam is the observation and the unknowns are k = 1/s and
    # g: lam = k (gam + Bb b_a - beta g), where least squares is unbiased (regressing the IMU on
    # the positions instead would shrink s by the positions' noise, errors-in-variables).
    x, *_ = np.linalg.lstsq(np.column_stack([b, -beta]), lam, rcond=None)
    k = float(x[0])
    if not np.isfinite(k) or abs(k) < 1e-12:
        return None
    g = x[1:] / k
    if np.linalg.norm(g) < 1e-6:
        return None
    # Gravity's magnitude known: Gauss-Newton over k, g's direction (two angles) and the
    # accelerometer's bias, the bias held near zero by a prior of ``bias_sigma`` (it is observed
    # only as the camera turns); the prior's weight from the residuals of the fit without it.
    g = g / np.linalg.norm(g) * GRAVITY_M_S2
    b_a = np.zeros(3)
    w_prior = 0.0

    def residual(k, g, b_a):
        return lam - k * (b + Bb @ b_a - beta @ g)

    for it in range(2):
        for _ in range(20):
            r = residual(k, g, b_a)
            u = np.cross(g, [1.0, 0.0, 0.0] if abs(g[0]) < 0.9 * GRAVITY_M_S2 else [0.0, 1.0, 0.0])
            u /= np.linalg.norm(u)
            v = np.cross(g / GRAVITY_M_S2, u)
            Jg = k * beta @ (-skew(g) @ np.column_stack([u, v]))
            J = np.column_stack([-(b + Bb @ b_a - beta @ g), Jg, -k * Bb if it else np.zeros_like(Bb)])
            Jp = np.hstack([np.zeros((3, 3)), w_prior * np.eye(3)])
            dx, *_ = np.linalg.lstsq(np.vstack([J, Jp]), -np.concatenate([r, w_prior * b_a]), rcond=None)
            k += dx[0]
            g = _so3_exp(u * dx[1] + v * dx[2]) @ g
            b_a = b_a + dx[3:]
            if np.abs(dx).max() < 1e-12:
                break
        # The prior's weight: the bias's residual columns carry k, so a bias of bias_sigma weighs
        # as much as one residual's spread.
        sigma_r = float(np.sqrt(np.mean(np.square(residual(k, g, b_a)))))
        w_prior = sigma_r / (bias_sigma * abs(k))
    r = residual(k, g, b_a)
    J = np.vstack([np.column_stack([-(b + Bb @ b_a - beta @ g), k * beta @ (-skew(g) @ np.column_stack([u, v])),
                                    -k * Bb]),
                   np.hstack([np.zeros((3, 3)), w_prior * np.eye(3)])])
    dof = max(len(r) - 6, 1)
    cov = np.linalg.pinv(J.T @ J) * float(r @ r) / dof
    s = 1.0 / k
    # The camera's own acceleration (metric), RMS: lam is its second difference in map units.
    lam_norm = np.linalg.norm(lam.reshape(-1, 3), axis=1) / np.array(half)
    excitation = float(abs(s) * np.sqrt(np.mean(lam_norm**2)))
    return ScaleEstimate(s, g, float(np.sqrt(max(cov[0, 0], 0.0)) / abs(k)), len(tk) - 2, excitation, b_a)


def gravity_aligned(g_world: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation R_up_world taking the map's frame to one whose z axis points up (against
    gravity), turning least (its yaw is the map's)."""
    z = -np.asarray(g_world, float) / np.linalg.norm(g_world)
    c = float(z[2])
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    # The rotation taking z to e_z about their common normal (Rodrigues with v = z x e_z).
    v = np.cross(z, [0.0, 0.0, 1.0])
    V = skew(v)
    return np.eye(3) + V + V @ V / (1.0 + c)
