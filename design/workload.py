"""The standard gaze workload over which the torque criteria are integrated.

Two parts, both in joint space plus the mount's own motion:

* **Saccades** of the sizes the runtime makes: gaze redirections of each amplitude in
  ``saccade_amplitudes_deg`` (up, down, left, right, from straight ahead and from a posture
  looking down-left at a bench), each a minimum-jerk profile whose peak rate is the paper's
  controlled-motion limit (~30 deg/s), with the cyclotorsion keeping the image upright; the
  mount is still and upright.
* **Stabilisation against walking**: the mount rides a walking wearer's shoulder (vertical
  bounce at the step frequency, lateral sway and roll and yaw at the stride frequency, pitch at
  the step frequency) while the head holds the gaze on a fixed world direction, image upright
  (Path A).

Holding still costs nothing: the HS-50 holds position unpowered (paper, section 2), so only
motion segments are integrated. Because the chain order and axis directions are fixed in a
sweep, the joint trajectories are the same for every candidate; only the torques differ, so the
workload is built once per sweep and every evaluation is one batched inverse-dynamics call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import HeadGeometry, gaze_at_direction
from kinematics.dynamics import GRAVITY

from .sweep_file import WorkloadSpec


@dataclass(frozen=True)
class Workload:
    """Samples of the workload, N of them.

    q, qd, qdd : (N, 3) joint angles (rad), rates (rad/s), accelerations (rad/s^2).
    gravity_mount, omega_mount, alpha_mount, accel_mount : (N, 3) the mount's gravity (m/s^2),
        angular velocity (rad/s), angular acceleration (rad/s^2) and linear acceleration
        (m/s^2), all in the mount frame.
    dt : (N,) integration weight of each sample, s.
    segment : (N,) index of the motion segment each sample belongs to; ``labels[segment]``.
    """

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    gravity_mount: np.ndarray
    omega_mount: np.ndarray
    alpha_mount: np.ndarray
    accel_mount: np.ndarray
    dt: np.ndarray
    segment: np.ndarray
    labels: tuple[str, ...]

    @property
    def duration_s(self) -> float:
        return float(self.dt.sum())


def _gaze(e: float, p: float) -> np.ndarray:
    """Unit gaze direction at gaze elevation e and pan p (mount frame: x forward, y left, z up)."""
    return np.array([math.cos(e) * math.cos(p), math.sin(p), math.sin(e) * math.cos(p)])


def _joint_path(head: HeadGeometry, dirs: np.ndarray, ups: np.ndarray) -> np.ndarray:
    q = np.zeros(3)
    out = []
    for d, up in zip(dirs, ups):
        res = gaze_at_direction(head, d, up, q_current=q)
        if not res.reachable:
            raise ValueError(f"workload direction unreachable by the sweep's axes: {res.reason}; "
                             "reduce the saccade amplitudes or the walking motion")
        q = res.q
        out.append(q)
    return np.array(out)


def _derivatives(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    qd = np.gradient(q, dt, axis=0, edge_order=2)
    return qd, np.gradient(qd, dt, axis=0, edge_order=2)


def saccade_segments(spec: WorkloadSpec):
    """(label, start (e, p), end (e, p)) of every saccade in the workload, radians."""
    starts = {"ahead": (0.0, 0.0), "bench": (math.radians(-25.0), math.radians(30.0))}
    for a in spec.saccade_amplitudes_deg:
        A = math.radians(a)
        for sname, (e0, p0) in starts.items():
            for dname, (de, dp) in {"up": (A, 0), "down": (-A, 0), "left": (0, A), "right": (0, -A)}.items():
                yield f"saccade {a:g} deg {dname} from {sname}", (e0, p0), (e0 + de, p0 + dp)


def build_workload(head: HeadGeometry, spec: WorkloadSpec) -> Workload:
    """Sample the workload for a head with the sweep's axes (its offsets do not matter)."""
    h = 1.0 / spec.rate_hz
    up = np.array([0.0, 0.0, 1.0])
    g_up = np.array([0.0, 0.0, -GRAVITY])
    cols = {k: [] for k in ("q", "qd", "qdd", "gravity_mount", "omega_mount", "alpha_mount", "accel_mount", "dt", "segment")}
    labels = []

    def add(label, q, qd, qdd, grav, omega, alpha, accel):
        n = len(q)
        for k, v in (("q", q), ("qd", qd), ("qdd", qdd), ("gravity_mount", grav), ("omega_mount", omega),
                     ("alpha_mount", alpha), ("accel_mount", accel)):
            cols[k].append(np.broadcast_to(v, (n, 3)))
        cols["dt"].append(np.full(n, h))
        cols["segment"].append(np.full(n, len(labels)))
        labels.append(label)

    peak = math.radians(spec.saccade_peak_rate_deg_s)
    for label, (e0, p0), (e1, p1) in saccade_segments(spec):
        amp = math.hypot(e1 - e0, p1 - p0)
        T = 1.875 * amp / peak          # minimum jerk: peak rate = 1.875 amplitude / duration
        tau = np.linspace(0.0, 1.0, max(int(round(T / h)) + 1, 5))
        s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        dirs = np.array([_gaze(e0 + (e1 - e0) * si, p0 + (p1 - p0) * si) for si in s])
        q = _joint_path(head, dirs, np.broadcast_to(up, dirs.shape))
        qd, qdd = _derivatives(q, T / (len(tau) - 1))
        z = np.zeros(3)
        add(label, q, qd, qdd, g_up, z, z, z)

    # Walking: the mount's orientation and position over time, sampled finely enough to
    # differentiate twice.
    t = np.arange(0.0, spec.walk_seconds + 1e-12, h)
    f_step = spec.walk_step_hz
    f_stride = f_step / 2
    w_step, w_stride = 2 * math.pi * f_step, 2 * math.pi * f_stride
    roll = math.radians(spec.walk_roll_deg) * np.sin(w_stride * t)
    pitch = math.radians(spec.walk_pitch_deg) * np.sin(w_step * t + math.pi / 4)
    yaw = math.radians(spec.walk_yaw_deg) * np.sin(w_stride * t)
    R_world_mount = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]))
    R = R_world_mount.as_matrix()
    # Linear acceleration of the mount (the forward speed is constant and drops out).
    acc_world = np.column_stack([np.zeros_like(t),
                                 -spec.walk_sway_m * w_stride**2 * np.sin(w_stride * t),
                                 -spec.walk_bounce_m * w_step**2 * np.sin(w_step * t)])
    RT = np.swapaxes(R, 1, 2)
    d_mount = RT @ np.array([1.0, 0.0, 0.0])
    up_mount = RT @ up
    q = _joint_path(head, d_mount, up_mount)
    qd, qdd = _derivatives(q, h)
    # Body-frame angular velocity from consecutive orientations, then its derivative, which
    # equals the angular acceleration expressed in the mount frame.
    omega = _body_rates(R_world_mount, h)
    alpha = np.gradient(omega, h, axis=0, edge_order=2)
    add("walk, gaze held on a world direction (Path A)", q, qd, qdd, RT @ g_up, omega, alpha,
        np.einsum("nij,nj->ni", RT, acc_world))
    return Workload(**{k: np.concatenate(v) for k, v in cols.items()}, labels=tuple(labels))


def _body_rates(R: Rotation, h: float) -> np.ndarray:
    """(N, 3) angular velocity in the body (mount) frame by central differences of orientation."""
    n = len(R)
    idx_p = np.minimum(np.arange(n) + 1, n - 1)
    idx_m = np.maximum(np.arange(n) - 1, 0)
    span = (idx_p - idx_m) * h
    return (R[idx_m].inv() * R[idx_p]).as_rotvec() / span[:, None]
