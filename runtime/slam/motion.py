"""MonoSLAM's constant-velocity, constant-angular-velocity motion model, its Jacobians, the
process noise, and the EKF prediction of the camera block.

In each step of ``dt`` seconds unknown impulses ``n = (V, Omega)`` hit the camera (``V`` in the
world frame, m/s; ``Omega`` in the camera frame, rad/s), the integrals of white accelerations
over the step: ``P_n = diag(sigma_a^2 dt t0 I3, sigma_alpha^2 dt t0 I3)`` with ``t0`` the step
``sigma_a`` (m/s^2) and ``sigma_alpha`` (rad/s^2) are stated for (``motion_noise_interval``),
where MonoSLAM's ``(sigma dt)^2`` is the same at ``dt = t0``::

    r_new = r + (v + V) dt
    q_new = q * q((w + Omega) dt)      (right-composition: w is in the camera frame)
    v_new = v + V
    w_new = w + Omega
    b_new = b + n_b                    (bias states, if any: random walks)

Each function returns its value with its Jacobians (SceneLib's ``f_and_dfdx``).
"""

from __future__ import annotations

import math

import numpy as np

from .config import SlamConfig
from .kernels import compiled_kernel
from .quaternion import (normalise_quaternion_jacobian, quat_left_kernel, quat_right_kernel,
                         rotvec_to_quat_jacobian_kernel)
from .state import BA_SLICE, BG_SLICE, NOISE_DIM, Q_SLICE, TD_INDEX, SlamNumericalError, State, check_mean


def _check_dt(dt) -> float:
    dt = float(dt)
    if not (math.isfinite(dt) and dt >= 0):
        raise ValueError(f"dt = {dt!r} must be a finite time step >= 0 s")
    return dt


@compiled_kernel(quat_left_kernel, quat_right_kernel, rotvec_to_quat_jacobian_kernel)
def f_kernel(x_v, dt, n):
    """The motion model with impulse ``n`` (6,): x_v_new, F = df/dx_v, G = df/dn (at n)."""
    cd = x_v.shape[0]
    q = x_v[3:7]
    th0 = (x_v[10] + n[3]) * dt
    th1 = (x_v[11] + n[4]) * dt
    th2 = (x_v[12] + n[5]) * dt
    p, dp = rotvec_to_quat_jacobian_kernel(th0, th1, th2)
    L = quat_left_kernel(q[0], q[1], q[2], q[3])
    x_new = x_v.copy()
    for i in range(3):
        x_new[i] = x_v[i] + (x_v[7 + i] + n[i]) * dt
        x_new[7 + i] = x_v[7 + i] + n[i]
        x_new[10 + i] = x_v[10 + i] + n[3 + i]
    x_new[3:7] = L @ p
    dq_dw = (L @ dp) * dt
    F = np.eye(cd)
    for i in range(3):
        F[i, 7 + i] = dt
    F[3:7, 3:7] = quat_right_kernel(p[0], p[1], p[2], p[3])
    F[3:7, 10:13] = dq_dw
    G = np.zeros((cd, 6))
    for i in range(3):
        G[i, i] = dt
        G[7 + i, i] = 1.0
        G[10 + i, 3 + i] = 1.0
    G[3:7, 3:6] = dq_dw
    return x_new, F, G


def f_and_dfdx_dfdn(x_v, dt: float, n=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x_v_new = f(x_v, n)``, ``F = df/dx_v`` and ``G = df/dn`` (cam_dim, 6), at ``n``
    (default zero: the prediction). x_v : (13,) or (19,); dt : s >= 0; n : (6,) (V, Omega)."""
    x_v = np.ascontiguousarray(np.asarray(x_v, dtype=float).reshape(-1))
    n = np.zeros(NOISE_DIM) if n is None else np.asarray(n, dtype=float).reshape(NOISE_DIM)
    return f_kernel(x_v, _check_dt(dt), n)


def f_and_dfdx(x_v, dt: float) -> tuple[np.ndarray, np.ndarray]:
    x_new, F, _ = f_and_dfdx_dfdn(x_v, dt)
    return x_new, F


def noise_covariance(dt: float, cfg: SlamConfig, gain: float = 1.0) -> np.ndarray:
    """``P_n`` (6, 6) of the impulse ``n = (V, Omega)`` over a step of ``dt`` s: variances
    ``sigma^2 dt motion_noise_interval`` (white accelerations), times ``gain^2``."""
    dt = _check_dt(dt)
    span = math.sqrt(dt * cfg.motion.motion_noise_interval)
    sa, sw = gain * cfg.motion.sigma_a * span, gain * cfg.motion.sigma_alpha * span
    return np.diag(np.r_[np.full(3, sa * sa), np.full(3, sw * sw)])


def impulse_sigma(t: np.ndarray, v: np.ndarray, var_v: np.ndarray, lag: float, t0: float) -> float:
    """The standard deviation per axis, m/s^2, of the white acceleration a track's velocity
    estimates show (covariance matching of the process noise, as in Mohamed and Schwarz's
    adaptive Kalman filtering), stated like ``sigma_a`` for steps of ``t0`` s.

    t : (N,) s, increasing; v : (N, 3) m/s, the filter's velocity after each frame; var_v : (N,)
    m^2/s^2, the traces of their covariances. Velocity changes are taken between estimates at
    least ``lag`` s apart (changes from frame to frame are damped by the filter's own lag): a
    white acceleration of ``sigma`` gives ``E|dv|^2 = 3 sigma^2 dt t0`` over ``dt``, and the two
    estimates' errors add their variances, which are taken out. Returns NaN when no pair is
    ``lag`` apart."""
    t = np.asarray(t, float)
    j = np.searchsorted(t, t - lag, side="right") - 1
    k = np.flatnonzero(j >= 0)
    if not len(k):
        return float("nan")
    j = j[k]
    d = v[k] - v[j]
    excess = (np.einsum("ij,ij->i", d, d) - var_v[k] - var_v[j]) / (3.0 * (t[k] - t[j]) * t0)
    return math.sqrt(max(float(np.mean(excess)), 0.0))     # averaged before clipping: unbiased


def turning(cfg: SlamConfig, rate: float) -> bool:
    """Whether a camera turning at ``rate`` rad/s turns fast enough for the impulses to adapt
    (faster than ``adapt_turn_rate``); both adaptations keep the priors otherwise."""
    return rate > cfg.impulses.adapt_turn_rate


def adapted_sigma_a(cfg: SlamConfig, t: np.ndarray, v: np.ndarray, var_v: np.ndarray, turn_rate: float) -> float:
    """The linear impulse, m/s^2, a track should predict with after the velocity history ``t``
    (N,) s, ``v`` (N, 3) m/s, ``var_v`` (N,) (:func:`impulse_sigma`) while turning at
    ``turn_rate`` rad/s: ``adapt_margin`` times the acceleration it shows, within
    ``[sigma_a_min, sigma_a]``; ``sigma_a`` itself when adapting is off, the camera turns slower
    than ``adapt_turn_rate``, or the history spans less than ``adapt_lag`` and half
    ``adapt_window``."""
    if (not cfg.impulses.adapt_sigma_a or not turning(cfg, turn_rate) or len(t) < 2
            or t[-1] - t[0] < cfg.impulses.adapt_lag + 0.5 * cfg.impulses.adapt_window):
        return cfg.motion.sigma_a
    est = impulse_sigma(t, v, var_v, cfg.impulses.adapt_lag, cfg.motion.motion_noise_interval)
    if not math.isfinite(est):
        return cfg.motion.sigma_a
    return min(max(cfg.impulses.adapt_margin * est, cfg.impulses.sigma_a_min), cfg.motion.sigma_a)


def adapted_sigma_alpha(cfg: SlamConfig, t: np.ndarray, w: np.ndarray, var_w: np.ndarray) -> float:
    """The angular impulse, rad/s^2, a track should predict with after the rate history ``t``
    (N,) s, ``w`` (N, 3) rad/s, ``var_w`` (N,) rad^2/s^2 (the filter's estimates after each frame
    and the traces of their covariances; the last is now): ``adapt_alpha_margin`` times the
    mean angular acceleration over the last ``adapt_alpha_lag`` s, within ``[sigma_alpha,
    sigma_alpha_max]`` (never below the prior), while the camera turns faster than
    ``adapt_turn_rate`` (a gaze shift; a walker's sway, under 0.7 rad/s, keeps the prior). The
    rate's change counts only beyond the two estimates' own errors (their variances taken out,
    as in covariance matching). ``sigma_alpha`` itself when adapting is off, the camera turns
    slower, or the history spans less than half the lag. A steady angular acceleration
    ``alpha`` changes the rate by ``alpha dt`` a step, a ``1 / margin`` sigma impulse at
    ``margin alpha``."""
    if not cfg.impulses.adapt_sigma_alpha or len(t) < 2 or not turning(cfg, float(np.linalg.norm(w[-1]))):
        return cfg.motion.sigma_alpha
    j = int(np.searchsorted(t, t[-1] - 1.05 * cfg.impulses.adapt_alpha_lag))   # a frame's jitter allowed
    span = float(t[-1] - t[j])
    if span < 0.5 * cfg.impulses.adapt_alpha_lag:
        return cfg.motion.sigma_alpha
    d = w[-1] - w[j]
    excess = float(d @ d) - float(var_w[-1]) - float(var_w[j])
    if not math.isfinite(excess):
        return cfg.motion.sigma_alpha
    est = math.sqrt(max(excess, 0.0)) / span
    imp, sigma_alpha = cfg.impulses, cfg.motion.sigma_alpha
    return min(max(imp.adapt_alpha_margin * est, sigma_alpha), max(imp.sigma_alpha_max, sigma_alpha))


def bias_walk(P_vv: np.ndarray, dt: float, cfg: SlamConfig) -> None:
    """Add the bias random walks' variance over ``dt`` to a 19-number camera block's covariance
    (in place): ``gyro_bias_walk^2 dt`` and ``accel_bias_walk^2 dt`` per axis."""
    if len(P_vv) > BA_SLICE.start:
        for sl, s in ((BG_SLICE, cfg.imu.gyro_bias_walk), (BA_SLICE, cfg.imu.accel_bias_walk)):
            idx = np.arange(sl.start, sl.stop)
            P_vv[idx, idx] += s * s * dt
    if len(P_vv) > TD_INDEX:
        P_vv[TD_INDEX, TD_INDEX] += cfg.imu.time_offset_walk**2 * dt


def process_noise(x_v, dt: float, cfg: SlamConfig, gain: float = 1.0) -> np.ndarray:
    """``Q = G P_n G^T`` (+ the bias walks), the process noise of one step at the prior."""
    _, _, G = f_and_dfdx_dfdn(x_v, dt)
    Q = G @ noise_covariance(dt, cfg, gain) @ G.T
    bias_walk(Q, dt, cfg)
    return Q


def predict(state: State, dt: float, cfg: SlamConfig, noise_gain: float = 1.0) -> None:
    """The EKF prediction over ``dt`` seconds, in place: ``x_v <- f(x_v)``,
    ``P_vv <- F P_vv F^T + Q``, ``P_vy <- F P_vy`` (features do not move); then ``q`` is
    renormalised with its Jacobian. On a numerical failure :class:`SlamNumericalError` is raised
    and the state is unchanged. ``noise_gain`` scales the impulses (a lost track)."""
    cd = state.cam_dim
    x_v_new, F, G = f_and_dfdx_dfdn(state.x[:cd], dt)
    P_vv = state.P[:cd, :cd]
    P_new = F @ P_vv @ F.T + G @ noise_covariance(dt, cfg, noise_gain) @ G.T
    bias_walk(P_new, dt, cfg)
    apply_camera_prediction(state, x_v_new, F, P_new, "predict")


@compiled_kernel()
def _camera_rows_kernel(P, F, P_vv_new, J):
    """The camera's rows (cd, n) of ``T (F P F^T + Q) T^T`` with the features' columns ``F P_vy``
    (``P_vv_new`` the camera block before symmetrising, T the identity but the quaternion's
    normalisation Jacobian ``J`` on q), the camera block exactly symmetric."""
    cd = F.shape[0]
    q0 = Q_SLICE.start
    rows = np.dot(F, np.ascontiguousarray(P[:cd, :]))
    for a in range(cd):
        for b in range(cd):
            rows[a, b] = 0.5 * (P_vv_new[a, b] + P_vv_new[b, a])
    rows[q0:q0 + 4, :] = np.dot(J, np.ascontiguousarray(rows[q0:q0 + 4, :]))   # T P T^T, T = J on q: the q rows ...
    cols = np.dot(np.ascontiguousarray(rows[:, q0:q0 + 4]), J.T)  # ... and, in the camera block, its columns
    rows[:, q0:q0 + 4] = cols
    for a in range(cd):
        for b in range(a + 1, cd):
            v = 0.5 * (rows[a, b] + rows[b, a])
            rows[a, b] = v
            rows[b, a] = v
    return rows


def apply_camera_prediction(state: State, x_v_new: np.ndarray, F: np.ndarray, P_vv_new: np.ndarray,
                            where: str) -> None:
    """Write a prediction of the camera block into the state: ``x_v <- x_v_new``,
    ``P_vv <- P_vv_new`` (symmetrised), ``P_vy <- F P_vy``; then ``q`` is renormalised with its
    Jacobian (``where`` names the step in errors). Only the camera's rows and columns change, so
    they are computed and checked first and then written in place (O(n) per camera row); on a
    numerical failure :class:`SlamNumericalError` is raised and the state is unchanged. Shared
    by the constant-velocity and the inertial predictions."""
    cd = state.cam_dim
    P = state.P
    x_v = np.array(x_v_new, float)
    q_unit, J = normalise_quaternion_jacobian(x_v[Q_SLICE])
    x_v[Q_SLICE] = q_unit
    rows = _camera_rows_kernel(P, np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(P_vv_new, dtype=float), J)
    x = state.x.copy()
    x[:cd] = x_v
    check_mean(x, where, state.describe)
    if not np.isfinite(rows).all():
        i, j = np.argwhere(~np.isfinite(rows))[0]
        raise SlamNumericalError(f"covariance P has NaN/Inf after {where}, first at ({i}, {j}) "
                                 f"({state.describe(int(i))} / {state.describe(int(j))})")
    d = np.diag(rows[:, :cd])
    if d.min() < 0:
        i = int(np.argmin(d))
        raise SlamNumericalError(f"covariance P has a negative variance P[{i},{i}] = {d[i]:.3g} after {where} "
                                 f"({state.describe(i)})")
    P[:cd, :] = rows
    P[:, :cd] = rows.T                  # written as the transpose: P stays exactly symmetric
    state.x = x


def apply_quaternion_jacobian(P: np.ndarray, J: np.ndarray) -> None:
    """``P <- T P T^T`` in place for a symmetric ``P``, ``T`` the identity except ``J`` (4, 4) on
    the quaternion block (rows and columns 3:7 only, O(n)); ``P`` stays exactly symmetric."""
    rows = J @ P[Q_SLICE, :]
    qq = rows[:, Q_SLICE] @ J.T
    rows[:, Q_SLICE] = 0.5 * (qq + qq.T)
    P[Q_SLICE, :] = rows
    P[:, Q_SLICE] = rows.T


def normalise_quaternion(state: State) -> None:
    """Renormalise the state's ``q`` in place and apply the normalisation Jacobian to ``P``."""
    q_new, J = normalise_quaternion_jacobian(state.x[Q_SLICE])
    state.x[Q_SLICE] = q_new
    apply_quaternion_jacobian(state.P, J)
