"""Inertial prediction: when the sequence has an IMU (``imu.txt`` of shared/formats.md, gyro and
specific force in the camera's optical frame), its samples replace the constant-velocity
model's guesses between frames.

The constant-velocity model (motion.py) treats every acceleration as an unknown impulse; a
monocular map then holds its scale only through the features, and loses it where they are
replaced quickly (a walk past a bench). Integrating the accelerometer ties the velocity, and so
the scale, to metres; the gyro carries the orientation through frames with few matches. For
each IMU sample interval ``d`` (s), with ``omega`` (rad/s) and ``f`` (m/s^2) the sample's gyro
and specific force, camera frame::

    a      = R(q) f + g                    (g = (0, 0, -9.81) m/s^2, world)
    r_new  = r + v d + a d^2 / 2
    v_new  = v + a d
    q_new  = q * q(omega d)
    w_new  = omega                         (the state's w is the latest measured rate)

The sensor noise enters as white noise on ``f`` and ``omega`` (densities ``imu_accel_noise``,
m/s^2/sqrt(Hz), and ``imu_gyro_noise``, rad/s/sqrt(Hz), from :class:`SlamConfig`) and covers
unmodelled effects (biases, the samples being held over their interval) through the same
densities; there are no bias states, so an IMU with large biases needs larger densities.
"""

from __future__ import annotations

import numpy as np

from .motion import apply_camera_prediction
from .state import (CAMERA_DIM, CAMERA_SLICE, DEFAULT_CONFIG, SlamConfig, State, compiled_kernel, quat_left_kernel, quat_right_kernel, rotation_derivatives_kernel,
                    rotation_kernel, rotvec_to_quat_jacobian_kernel)

GRAVITY = np.array([0.0, 0.0, -9.81])


@compiled_kernel(rotation_kernel, rotation_derivatives_kernel, quat_left_kernel, quat_right_kernel,
                 rotvec_to_quat_jacobian_kernel)
def imu_step_kernel(x_v, omega, f, d):
    """Compiled body of :func:`imu_step_and_jacobians` (the equations of the module docstring)."""
    q = x_v[3:7]
    R = rotation_kernel(q[0], q[1], q[2], q[3])
    a = R @ f + GRAVITY
    p, dp_dtheta = rotvec_to_quat_jacobian_kernel(omega[0] * d, omega[1] * d, omega[2] * d)
    L = quat_left_kernel(q[0], q[1], q[2], q[3])
    x_new = np.empty(13)
    x_new[0:3] = x_v[0:3] + x_v[7:10] * d + 0.5 * a * d * d
    x_new[3:7] = L @ p
    x_new[7:10] = x_v[7:10] + a * d
    x_new[10:13] = omega
    D = rotation_derivatives_kernel(q[0], q[1], q[2], q[3])
    da_dq = np.empty((3, 4))                                         # d(R(q) f)/dq
    for k in range(4):
        da_dq[:, k] = D[k] @ f
    F = np.eye(13)
    for i in range(3):
        F[i, 7 + i] = d
        F[10 + i, 10 + i] = 0.0                                      # w is replaced by the sample
    F[0:3, 3:7] = 0.5 * d * d * da_dq
    F[7:10, 3:7] = d * da_dq
    F[3:7, 3:7] = quat_right_kernel(p[0], p[1], p[2], p[3])
    G = np.zeros((13, 6))
    G[0:3, 0:3] = 0.5 * d * d * R
    G[7:10, 0:3] = d * R
    G[3:7, 3:6] = (L @ dp_dtheta) * d
    for i in range(3):
        G[10 + i, 3 + i] = 1.0
    return x_new, F, G


def imu_step_and_jacobians(x_v, omega, f, d: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One IMU interval: ``x_v_new`` (13,), ``F = dx_v_new/dx_v`` (13, 13) and
    ``G = dx_v_new/d(f, omega)`` (13, 6).

    x_v : (13,) camera block. omega : (3,) rad/s, f : (3,) m/s^2 (camera frame). d : s >= 0.
    """
    return imu_step_kernel(np.asarray(x_v, float).reshape(CAMERA_DIM), np.asarray(omega, float).reshape(3),
                           np.asarray(f, float).reshape(3), float(d))


@compiled_kernel(imu_step_kernel)
def _propagate_kernel(x_v, P_vv, ds, omegas, fs, sa, sg):
    """The camera block and its covariance through every interval, and the product of the
    intervals' Jacobians (for the camera-map cross-covariance)."""
    F_total = np.eye(13)
    for j in range(len(ds)):
        d = ds[j]
        x_v, F, G = imu_step_kernel(x_v, omegas[j], fs[j], d)
        # White noise of density s over d seconds: a sample mean with variance s^2 / d.
        Pn = np.zeros((6, 6))
        for i in range(3):
            Pn[i, i] = sa * sa / d
            Pn[3 + i, 3 + i] = sg * sg / d
        P_vv = F @ P_vv @ F.T + G @ Pn @ G.T
        F_total = F @ F_total
    return x_v, P_vv, F_total


def imu_intervals(imu: np.ndarray, t0: float, t1: float) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Split ``(t0, t1]`` at the IMU sample times: a list of ``(d, omega, f)``, each interval
    using the latest sample at or before its start (zero-order hold). ``imu`` : (k, 7) rows
    ``[t, wx, wy, wz, ax, ay, az]`` sorted by time, which must include a sample at or before t0.
    """
    imu = np.asarray(imu, float).reshape(-1, 7)
    times = imu[:, 0]
    i = int(np.searchsorted(times, t0, side="right")) - 1
    if i < 0:
        raise ValueError(f"no IMU sample at or before t = {t0:.6f} s")
    out, t = [], t0
    while t < t1:
        t_next = times[i + 1] if i + 1 < len(imu) and times[i + 1] < t1 else t1
        if t_next > t:
            out.append((t_next - t, imu[i, 1:4], imu[i, 4:7]))
        t = t_next
        if i + 1 < len(imu) and times[i + 1] <= t:
            i += 1
    return out


def predict_imu(state: State, imu: np.ndarray, t0: float, t1: float, cfg: SlamConfig = DEFAULT_CONFIG,
                noise_gain: float = 1.0) -> None:
    """The EKF prediction from ``t0`` to ``t1`` through the IMU samples, in place.

    ``P_vv`` is propagated interval by interval with each interval's noise, and the camera-map
    cross-covariance by the product of the intervals' Jacobians; then ``q`` is renormalised with
    its Jacobian and the guard runs. ``noise_gain`` scales the noise densities (lost track).
    """
    steps = imu_intervals(imu, t0, t1)
    sa, sg = noise_gain * cfg.imu_accel_noise, noise_gain * cfg.imu_gyro_noise
    ds = np.array([d for d, _, _ in steps])
    omegas = np.array([w for _, w, _ in steps]).reshape(-1, 3)
    fs = np.array([f for _, _, f in steps]).reshape(-1, 3)
    x_v, P_vv, F_total = _propagate_kernel(state.x[CAMERA_SLICE].copy(), state.P[CAMERA_SLICE, CAMERA_SLICE].copy(),
                                           ds, omegas, fs, sa, sg)
    apply_camera_prediction(state, x_v, F_total, P_vv, "inertial predict", cfg)
