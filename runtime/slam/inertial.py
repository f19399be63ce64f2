"""Inertial prediction: when the sequence has an IMU (``imu.txt`` of shared/formats.md, gyro and
specific force in the camera's optical frame), its samples drive the prediction between frames
instead of the constant-velocity model's guesses.

For each IMU sample interval ``d`` (s), with ``omega_m`` (rad/s) and ``f_m`` (m/s^2) the sample's
gyro and specific force, and the bias states ``b_g``, ``b_a`` (zero without them)::

    omega  = omega_m - b_g,  f = f_m - b_a
    a      = k (R(q) f + g)                (g = (0, 0, -9.81) m/s^2, world)
    r_new  = r + v d + a d^2 / 2
    v_new  = v + a d
    q_new  = q * q(omega d)
    w_new  = omega                         (the state's w is the latest corrected rate)
    b_new  = b                             (+ their random walks, motion.bias_walk)

White noise on ``f_m`` and ``omega_m`` (densities ``imu_accel_noise``, ``imu_gyro_noise``)
enters through ``G = dx_new/d(f, omega)``.

``k`` is 1 in a metric map. A map started from natural features has its own unit and the first
camera's frame: there ``k`` (map units per metre) and ``g`` (gravity in that frame, m/s^2) are
states, started from the IMU's estimates when the IMU is handed the map (imu_handover.py), and
refined by every frame from then: a degree off in gravity's direction is 0.17 m/s^2 of
acceleration that would otherwise go into the scale.

The samples are checked as they arrive (:class:`ImuStream`): non-finite values, values beyond
a MEMS part's range (spikes) and samples out of time order are dropped and counted; a frame
interval with a gap longer than ``imu_max_gap_s`` (or no samples) is predicted by the
constant-velocity model instead, and counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import MapSettings, SlamConfig
from .kernels import compiled_kernel
from .motion import apply_camera_prediction, bias_walk
from .quaternion import (quat_left_kernel, quat_right_kernel, rotation_derivatives_kernel, rotation_kernel,
                         rotvec_to_quat_jacobian_kernel)
from .state import State

GRAVITY = np.array([0.0, 0.0, -9.81])


@compiled_kernel(rotation_kernel, rotation_derivatives_kernel, quat_left_kernel, quat_right_kernel,
                 rotvec_to_quat_jacobian_kernel)
def imu_step_kernel(x_v, omega_m, f_m, d, g):
    """One IMU interval (the equations of the module docstring) with gravity ``g`` (3,) m/s^2
    in the world frame (a 24-number block's own ``g`` instead): x_v_new, F = dx_new/dx_v
    (cd, cd) and G = dx_new/d(f_m, omega_m) (cd, 6), for a camera block of 13, 19, 20 or 24."""
    cd = x_v.shape[0]
    biased = cd >= 19
    scaled = cd >= 24
    k = x_v[20] if scaled else 1.0
    if scaled:
        g = x_v[21:24]
    q = x_v[3:7]
    omega = omega_m.copy()
    f = f_m.copy()
    if biased:
        omega -= x_v[13:16]
        f -= x_v[16:19]
    R = rotation_kernel(q[0], q[1], q[2], q[3])
    a_m = R @ f + g                      # metric
    a = k * a_m
    p, dp_dtheta = rotvec_to_quat_jacobian_kernel(omega[0] * d, omega[1] * d, omega[2] * d)
    L = quat_left_kernel(q[0], q[1], q[2], q[3])
    x_new = x_v.copy()
    x_new[0:3] = x_v[0:3] + x_v[7:10] * d + 0.5 * a * d * d
    x_new[3:7] = L @ p
    x_new[7:10] = x_v[7:10] + a * d
    x_new[10:13] = omega
    D = rotation_derivatives_kernel(q[0], q[1], q[2], q[3])
    da_dq = np.empty((3, 4))
    for j in range(4):
        da_dq[:, j] = k * (D[j] @ f)
    kR = k * R
    dq_domega = (L @ dp_dtheta) * d
    F = np.eye(cd)
    for i in range(3):
        F[i, 7 + i] = d
        F[10 + i, 10 + i] = 0.0
    F[0:3, 3:7] = 0.5 * d * d * da_dq
    F[7:10, 3:7] = d * da_dq
    F[3:7, 3:7] = quat_right_kernel(p[0], p[1], p[2], p[3])
    if biased:
        F[0:3, 16:19] = -0.5 * d * d * kR
        F[7:10, 16:19] = -d * kR
        F[3:7, 13:16] = -dq_domega
        for i in range(3):
            F[10 + i, 13 + i] = -1.0
    if scaled:
        F[0:3, 20] = 0.5 * d * d * a_m
        F[7:10, 20] = d * a_m
        for i in range(3):
            F[i, 21 + i] = 0.5 * d * d * k
            F[7 + i, 21 + i] = d * k
    G = np.zeros((cd, 6))
    G[0:3, 0:3] = 0.5 * d * d * kR
    G[7:10, 0:3] = d * kR
    G[3:7, 3:6] = dq_domega
    for i in range(3):
        G[10 + i, 3 + i] = 1.0
    return x_new, F, G


def imu_step_and_jacobians(x_v, omega, f, d: float, g=GRAVITY) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One IMU interval: ``x_v_new``, ``F`` and ``G`` (see :func:`imu_step_kernel`)."""
    return imu_step_kernel(np.ascontiguousarray(np.asarray(x_v, float).reshape(-1)), np.asarray(omega, float).reshape(3),
                           np.asarray(f, float).reshape(3), float(d), np.asarray(g, float).reshape(3))


@compiled_kernel(imu_step_kernel)
def _propagate_kernel(x_v, P_vv, ds, omegas, fs, sa, sg, g):
    """The camera block and its covariance through every interval, and the product of the
    intervals' Jacobians (for the camera-map cross-covariance). ``sa``, ``sg`` (k,): each
    interval's noise densities; ``g`` (3,) gravity, world."""
    cd = x_v.shape[0]
    F_total = np.eye(cd)
    for j in range(len(ds)):
        d = ds[j]
        x_v, F, G = imu_step_kernel(x_v, omegas[j], fs[j], d, g)
        Pn = np.zeros((6, 6))               # white noise of density s over d: variance s^2 / d
        for i in range(3):
            Pn[i, i] = sa[j] * sa[j] / d
            Pn[3 + i, 3 + i] = sg[j] * sg[j] / d
        P_vv = F @ P_vv @ F.T + G @ Pn @ G.T
        F_total = F @ F_total
    return x_v, P_vv, F_total


def imu_intervals(imu: np.ndarray, t0: float, t1: float, covered_until: float = np.inf
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split ``(t0, t1]`` at the IMU sample times: durations (k,), rates (k, 3), specific forces
    (k, 3), each interval using the latest sample at or before its start (zero-order hold), and
    which intervals (k,) bool lie beyond ``covered_until`` (s; the split is also made there):
    held, no sample having described them. ``imu`` : (m, 7) rows ``[t, wx, wy, wz, ax, ay,
    az]`` sorted by time, with a sample at or before t0."""
    imu = np.asarray(imu, float).reshape(-1, 7)
    times = imu[:, 0]
    i0 = int(np.searchsorted(times, t0, side="right")) - 1
    if i0 < 0:
        raise ValueError(f"no IMU sample at or before t = {t0:.6f} s")
    i1 = int(np.searchsorted(times, t1, side="left"))          # samples strictly before t1
    starts = np.concatenate([[t0], times[i0 + 1:i1]])
    rows = imu[i0:max(i1, i0 + 1)]
    if np.isfinite(covered_until):
        j = int(np.searchsorted(starts, covered_until, side="right"))
        if t0 < covered_until < t1 and starts[j - 1] != covered_until:
            starts = np.insert(starts, j, covered_until)
            rows = np.insert(rows, j, rows[j - 1], axis=0)
    d = np.diff(np.concatenate([starts, [t1]]))
    keep = d > 0
    return d[keep], rows[keep, 1:4], rows[keep, 4:7], starts[keep] >= covered_until


def predict_imu(state: State, imu: np.ndarray, t0: float, t1: float, cfg: SlamConfig, noise_gain: float = 1.0,
                covered_until: float = np.inf) -> None:
    """The EKF prediction from ``t0`` to ``t1`` through the IMU samples, in place: ``P_vv``
    interval by interval with each interval's noise, the camera-map cross-covariance by the
    product of the intervals' Jacobians; then ``q`` is renormalised with its Jacobian.

    ``covered_until`` : the time up to which the samples describe the motion (the last one's
    time plus the stream's period). Beyond it the last sample is held without knowing the
    motion (the frame came before the samples covering its end): that stretch takes the
    extra noise of a rate and a specific force that may have changed by ``imu_hold_rate_sigma``
    and ``imu_hold_accel_sigma`` (a white-noise density ``sigma sqrt(d)`` over its length d).
    Gravity is the world's (GRAVITY), or a natural start's map's own state (its 24-number block)."""
    ds, omegas, fs, held = imu_intervals(imu, t0, t1, covered_until)
    cd = state.cam_dim
    sa = noise_gain * np.sqrt(cfg.imu.imu_accel_noise**2 + held * cfg.imu.imu_hold_accel_sigma**2 * ds)
    sg = noise_gain * np.sqrt(cfg.imu.imu_gyro_noise**2 + held * cfg.imu.imu_hold_rate_sigma**2 * ds)
    x_v, P_vv, F_total = _propagate_kernel(state.x[:cd].copy(), state.P[:cd, :cd].copy(),
                                           ds, np.ascontiguousarray(omegas), np.ascontiguousarray(fs), sa, sg, GRAVITY)
    bias_walk(P_vv, t1 - t0, cfg)
    apply_camera_prediction(state, x_v, F_total, P_vv, "inertial predict")


@dataclass
class ImuCounts:
    """What :class:`ImuStream` dropped or could not use (written to stats.json)."""

    rows: int = 0
    non_finite: int = 0
    spikes: int = 0
    out_of_order: int = 0
    gaps: int = 0                 # frame intervals predicted without the IMU because of a gap


class ImuStream:
    """The IMU rows the filter has been given, checked as they arrive, and the rows covering a
    frame interval when they are fit to use."""

    def __init__(self, settings: MapSettings):
        self.settings = settings
        self.rows = np.zeros((0, 7))
        self.counts = ImuCounts()
        self.t_last = -np.inf
        self.period: float | None = None       # the median spacing of the samples, s

    @property
    def covered_until(self) -> float:
        """The time up to which the samples describe the motion: the last one's time plus the
        stream's period (each sample holds until the next)."""
        if not len(self.rows):
            return -np.inf
        return float(self.rows[-1, 0]) + (self.period or 0.0)

    def add(self, rows) -> list[str]:
        """Queue rows (k, 7) ``[t, wx, wy, wz, ax, ay, az]``; returns a line per kind of
        problem found in them (empty when all were good)."""
        rows = np.asarray(rows, float).reshape(-1, 7)
        if not len(rows):
            return []
        c = self.counts
        c.rows += len(rows)
        problems = []
        finite = np.isfinite(rows).all(axis=1)
        spike = finite & ((np.linalg.norm(rows[:, 1:4], axis=1) > self.settings.imu.imu_max_rate_rad_s)
                          | (np.linalg.norm(rows[:, 4:7], axis=1) > self.settings.imu.imu_max_accel_m_s2))
        ok = finite & ~spike
        t = rows[:, 0]
        order = np.zeros(len(rows), bool)
        last = self.t_last
        for i in np.flatnonzero(ok):
            if t[i] <= last:
                order[i] = True
            else:
                last = t[i]
        ok &= ~order
        if (~finite).any():
            c.non_finite += int((~finite).sum())
            problems.append(f"{int((~finite).sum())} IMU samples with NaN/Inf dropped")
        if spike.any():
            c.spikes += int(spike.sum())
            problems.append(f"{int(spike.sum())} IMU samples beyond the sensor's range (spikes) dropped")
        if order.any():
            c.out_of_order += int(order.sum())
            problems.append(f"{int(order.sum())} IMU samples out of time order dropped")
        good = rows[ok]
        if len(good):
            self.t_last = float(good[-1, 0])
            self.rows = np.vstack([self.rows, good]) if len(self.rows) else good
            if self.period is None and len(self.rows) >= 3:
                self.period = float(np.median(np.diff(self.rows[:, 0])))
        return problems

    def covering(self, t0: float, t1: float) -> np.ndarray | None:
        """The rows for the interval (t0, t1], or None if they do not cover it without a gap
        longer than ``imu_max_gap_s`` (then the frame is predicted without the IMU, counted)."""
        r = self.rows
        if not len(r) or r[0, 0] > t0 or r[-1, 0] < t1 - self.settings.imu.imu_max_gap_s:
            if len(r) and r[0, 0] <= t1:
                self.counts.gaps += 1
            return None
        i0 = int(np.searchsorted(r[:, 0], t0, side="right")) - 1
        i1 = int(np.searchsorted(r[:, 0], t1, side="right"))
        seg = r[i0:i1]
        # From the sample holding at t0 (not t0 itself): a sample from before a dropout must not
        # stand for the motion through it.
        edges = np.concatenate([[min(seg[0, 0], t0)], seg[1:, 0], [t1]])
        if np.diff(edges).max() > self.settings.imu.imu_max_gap_s:
            self.counts.gaps += 1
            return None
        return seg

    def drop_before(self, t: float) -> None:
        """Forget rows no longer needed: keep the one holding at ``t`` and those after."""
        if len(self.rows):
            k = max(int(np.searchsorted(self.rows[:, 0], t, side="right")) - 1, 0)
            self.rows = self.rows[k:]


@dataclass(frozen=True)
class StillBiases:
    """Bias estimates from a still stretch of IMU samples (camera frame): the gyro's mean rate
    and the accelerometer's mean less gravity as the camera's attitude ``q`` sees it.
    var_g, var_f : the means' variances (per axis). J_q : (3, 4) d b_a / d q, how the
    accelerometer's bias moves with the attitude it was computed from. seconds : the stretch."""

    b_g: np.ndarray
    b_a: np.ndarray
    var_g: float
    var_f: float
    J_q: np.ndarray
    seconds: float


def still_biases(rows: np.ndarray, t_end: float, q: np.ndarray, settings: MapSettings,
                 cfg: SlamConfig) -> StillBiases | None:
    """The biases from the still stretch that ends at ``t_end`` (the first frame), when the
    samples before it hold one at least ``still_min_s`` long whose rates' RMS spread about their
    mean is within ``still_gyro_rad_s``; else None. Still, the gyro reads its bias and the
    accelerometer ``R(q)^T (0, 0, 9.81) + b_a`` (``q``: the camera's attitude, world frame)."""
    rows = np.asarray(rows, float).reshape(-1, 7)
    rows = rows[rows[:, 0] <= t_end + 1e-9]
    if len(rows) < 3 or t_end - rows[0, 0] < settings.imu.still_min_s:
        return None
    # The longest stretch back from t_end whose rates' RMS spread about their mean stays below
    # the threshold (suffix sums: every candidate start at once).
    w_rev = rows[::-1, 1:4]
    n = np.arange(1, len(rows) + 1)[:, None]
    mean = np.cumsum(w_rev, axis=0) / n
    spread = np.sqrt(np.maximum(np.cumsum((w_rev**2).sum(axis=1)) / n[:, 0] - (mean**2).sum(axis=1), 0.0))
    still = spread <= settings.imu.still_gyro_rad_s
    m = len(rows) if still.all() else int(np.argmin(still))      # the first suffix that is not still
    seg = rows[len(rows) - m:]
    T = float(t_end - seg[0, 0]) if len(seg) else 0.0
    if len(seg) < 3 or T < settings.imu.still_min_s:
        return None
    w, f = seg[:, 1:4], seg[:, 4:7]
    b_g = w.mean(axis=0)
    q = np.asarray(q, float)
    up = -GRAVITY
    b_a = f.mean(axis=0) - rotation_kernel(q[0], q[1], q[2], q[3]).T @ up
    dR = rotation_derivatives_kernel(q[0], q[1], q[2], q[3])
    J_q = -np.column_stack([dR[k].T @ up for k in range(4)])
    # The means' standard errors: from the noise densities, or from the samples' own spread per
    # axis when that is larger (some motion left in the stretch).
    var_g = max(cfg.imu.imu_gyro_noise**2 / T, float(np.mean((w - b_g) ** 2)) / len(w))
    var_f = max(cfg.imu.imu_accel_noise**2 / T, float(np.mean((f - f.mean(axis=0)) ** 2)) / len(f))
    return StillBiases(b_g, b_a, var_g, var_f, J_q, T)
