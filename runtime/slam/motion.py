"""MonoSLAM's constant-velocity, constant-angular-velocity motion model, its Jacobians, the
process noise and the EKF prediction.

In each step of ``dt`` seconds unknown white impulses ``n = (V, Omega) = dt (a, alpha)`` hit
the camera (``a`` in the world frame, m/s^2; ``alpha`` in the camera frame, rad/s^2; uncorrelated,
``P_n = diag((sigma_a dt)^2 I3, (sigma_alpha dt)^2 I3)`` from :class:`SlamConfig`)::

    r_new = r + (v + V) dt
    q_new = q * q((w + Omega) dt)      (right-composition: w is in the camera frame)
    v_new = v + V
    w_new = w + Omega

with ``q(theta)`` the rotation-vector-to-quaternion map (:func:`rotvec_to_quat_jacobian`).
``q_new`` is a unit quaternion whenever ``q`` is; to stop rounding drift the prediction then
renormalises ``q`` and applies the normalisation Jacobian to the covariance.

Each function returns its value together with its Jacobian (SceneLib's ``f_and_dfdx``), and
each Jacobian is computed beside the function it differentiates.
"""

from __future__ import annotations

import math

import numpy as np

from .state import (
    CAMERA_DIM,
    CAMERA_SLICE,
    DEFAULT_CONFIG,
    NOISE_DIM,
    Q_SLICE,
    R_SLICE,
    V_SLICE,
    W_SLICE,
    SlamConfig,
    State,
    check_covariance,
    check_mean,
    compiled_kernel,
    quat_left_matrix,
    quat_right_matrix,
    rotvec_to_quat_jacobian,
)


def _check_dt(dt) -> float:
    dt = float(dt)
    if not (math.isfinite(dt) and dt >= 0):
        raise ValueError(f"dt = {dt!r} must be a finite time step >= 0 s")
    return dt


def _check_x_v(x_v) -> np.ndarray:
    x_v = np.asarray(x_v, dtype=float).reshape(-1)
    if x_v.shape != (CAMERA_DIM,):
        raise ValueError(f"x_v must have {CAMERA_DIM} numbers (r, q wxyz, v, w), got {x_v.shape}")
    return x_v


def f_and_dfdx_dfdn(x_v, dt: float, n=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The motion model with an explicit impulse: ``x_v_new = f(x_v, n)``, its Jacobian
    ``F = df/dx_v`` (13, 13) and ``G = df/dn`` (13, 6), both at the given ``n``.

    x_v : (13,) camera block (see state.py). dt : s, >= 0. n : (6,) ``(V, Omega)``, m/s and
    rad/s (default zero: the prediction).
    """
    x_v = _check_x_v(x_v)
    dt = _check_dt(dt)
    n = np.zeros(NOISE_DIM) if n is None else np.asarray(n, dtype=float).reshape(NOISE_DIM)
    r, q, v, w = x_v[R_SLICE], x_v[Q_SLICE], x_v[V_SLICE], x_v[W_SLICE]
    V, Om = n[:3], n[3:]

    p, dp_dtheta = rotvec_to_quat_jacobian((w + Om) * dt)
    x_new = np.concatenate([r + (v + V) * dt, quat_left_matrix(q) @ p, v + V, w + Om])

    dq_dw = quat_left_matrix(q) @ dp_dtheta * dt   # d(q * p(theta))/dw, theta = (w + Omega) dt
    F = np.eye(CAMERA_DIM)
    F[R_SLICE, V_SLICE] = dt * np.eye(3)
    F[Q_SLICE, Q_SLICE] = quat_right_matrix(p)    # d(q * p)/dq
    F[Q_SLICE, W_SLICE] = dq_dw

    G = np.zeros((CAMERA_DIM, NOISE_DIM))
    G[R_SLICE, 0:3] = dt * np.eye(3)
    G[Q_SLICE, 3:6] = dq_dw                         # Omega enters exactly as w does
    G[V_SLICE, 0:3] = np.eye(3)
    G[W_SLICE, 3:6] = np.eye(3)
    return x_new, F, G


def f_and_dfdx(x_v, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The noise-free prediction ``x_v_new = f(x_v, 0)`` (13,) and ``F = df/dx_v`` (13, 13)."""
    x_new, F, _ = f_and_dfdx_dfdn(x_v, dt)
    return x_new, F


def dfdn(x_v, dt: float) -> np.ndarray:
    """``G = df/dn`` (13, 6) at ``n = 0``: how the impulse ``(V, Omega)`` moves the state."""
    return f_and_dfdx_dfdn(x_v, dt)[2]


def noise_covariance(dt: float, cfg: SlamConfig = DEFAULT_CONFIG) -> np.ndarray:
    """``P_n`` (6, 6) = diag((sigma_a dt)^2 I3, (sigma_alpha dt)^2 I3), the covariance of the
    impulse ``n = dt (a, alpha)``."""
    dt = _check_dt(dt)
    return np.diag(np.r_[np.full(3, (cfg.sigma_a * dt) ** 2), np.full(3, (cfg.sigma_alpha * dt) ** 2)])


def process_noise(x_v, dt: float, cfg: SlamConfig = DEFAULT_CONFIG) -> np.ndarray:
    """``Q = G P_n G^T`` (13, 13), the process noise of one step, at the prior ``x_v``."""
    G = dfdn(x_v, dt)
    return G @ noise_covariance(dt, cfg) @ G.T


@compiled_kernel()
def normalise_quaternion_kernel(q0, q1, q2, q3):
    """``q / |q|`` (4,) and its Jacobian ``(|q|^2 I - q q^T) / |q|^3`` (4, 4) from the four
    components, and whether ``|q|^2`` was finite and > 0 (if not, the arrays are NaN). Compiled
    (numba) so that the EKF's sequential update can call it from its own kernel; from Python use
    :func:`normalise_quaternion_jacobian`."""
    q = np.array([q0, q1, q2, q3])
    nrm2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    J = np.empty((4, 4))
    if not (np.isfinite(nrm2) and nrm2 > 0):
        J[:] = np.nan
        return np.full(4, np.nan), J, False
    nrm = math.sqrt(nrm2)
    for i in range(4):
        for j in range(4):
            J[i, j] = ((nrm2 if i == j else 0.0) - q[i] * q[j]) / (nrm2 * nrm)
    return q / nrm, J, True


def normalise_quaternion_jacobian(q) -> tuple[np.ndarray, np.ndarray]:
    """``q / |q|`` (4,) and its Jacobian ``(|q|^2 I - q q^T) / |q|^3`` (4, 4)."""
    q = np.asarray(q, dtype=float).reshape(4)
    q_unit, J, ok = normalise_quaternion_kernel(q[0], q[1], q[2], q[3])
    if not ok:
        raise ValueError(f"cannot normalise the quaternion {q.tolist()}")
    return q_unit, J


def normalise_quaternion(state: State) -> None:
    """Renormalise the state's ``q`` in place and apply the normalisation Jacobian ``J`` to the
    covariance: ``P_qq <- J P_qq J^T``, ``P_q,rest <- J P_q,rest`` (only the 4 rows and columns
    of ``q`` change, O(n))."""
    q_new, J = normalise_quaternion_jacobian(state.x[Q_SLICE])
    state.x[Q_SLICE] = q_new
    apply_quaternion_jacobian(state.P, J)


def apply_quaternion_jacobian(P: np.ndarray, J: np.ndarray) -> None:
    """``P <- T P T^T`` in place for a symmetric ``P`` (n, n), where ``T`` is the identity except
    ``J`` (4, 4) on the quaternion block: rows and columns 3:7 only, O(n).

    The q columns are written as the transpose of the q rows and the 4x4 block is symmetrised,
    so a symmetric ``P`` stays exactly symmetric (and :func:`check_covariance` can skip its
    n x n symmetrisation)."""
    rows = J @ P[Q_SLICE, :]                  # (4, n): the q rows of T P
    qq = rows[:, Q_SLICE] @ J.T               # J P_qq J^T
    rows[:, Q_SLICE] = 0.5 * (qq + qq.T)
    P[Q_SLICE, :] = rows
    P[:, Q_SLICE] = rows.T


def predict(state: State, dt: float, cfg: SlamConfig = DEFAULT_CONFIG) -> None:
    """The EKF prediction over ``dt`` seconds, in place.

    ``x_v <- f(x_v)``; ``P_vv <- F P_vv F^T + Q``; ``P_vy <- F P_vy`` (features do not move, so
    their block is unchanged); then ``q`` is renormalised with its Jacobian and the guard runs.
    On a numerical failure :class:`SlamNumericalError` is raised and the state is unchanged.
    """
    x_v = state.x[CAMERA_SLICE]
    x_v_new, F, G = f_and_dfdx_dfdn(x_v, dt)
    Q = G @ noise_covariance(dt, cfg) @ G.T
    P_vv = state.P[CAMERA_SLICE, CAMERA_SLICE]
    apply_camera_prediction(state, x_v_new, F, F @ P_vv @ F.T + Q, "predict", cfg)


def apply_camera_prediction(state: State, x_v_new: np.ndarray, F: np.ndarray, P_vv_new: np.ndarray, where: str,
                            cfg: SlamConfig = DEFAULT_CONFIG) -> None:
    """Write a prediction of the camera block into the state, in place: ``x_v <- x_v_new``,
    ``P_vv <- P_vv_new`` (symmetrised), ``P_vy <- F P_vy`` (features do not move); then ``q`` is
    renormalised with its Jacobian and the guard runs (``where`` names the step in its errors).
    On a numerical failure :class:`SlamNumericalError` is raised and the state is unchanged.
    Shared by the constant-velocity and the inertial predictions."""
    x = state.x.copy()
    x[CAMERA_SLICE] = x_v_new
    P = state.P.copy()
    rows = F @ P[CAMERA_SLICE, :]             # (13, n): the camera rows of F P
    rows[:, CAMERA_SLICE] = 0.5 * (P_vv_new + P_vv_new.T)
    P[CAMERA_SLICE, :] = rows
    P[:, CAMERA_SLICE] = rows.T               # P_yv F^T = (F P_vy)^T: written as the transpose,
                                              # so a symmetric P stays exactly symmetric

    q_unit, J = normalise_quaternion_jacobian(x[Q_SLICE])
    x[Q_SLICE] = q_unit
    apply_quaternion_jacobian(P, J)

    check_mean(x, where)
    state.P = check_covariance(P, where, cfg)
    state.x = x
