"""Inverse kinematics for gaze: joint angles that put a direction or a 3D point on the optic axis.

The head has three joints and fixation fixes two degrees of freedom; the third (redundancy) is
removed as in the paper (section 5): the cyclotorsion keeps the world vertical upright in the
image, i.e. the optical x axis is horizontal and optical y (down) points downwards.

* Direction targets are solved in closed form: the elevation and pan angles by Paden-Kahan
  subproblem 2 (two rotations taking the optic axis onto the target direction, 0 to 2
  solutions), the cyclotorsion angle by one atan2.
* Point targets start from that closed form and are polished by Newton's method on the exact
  residual (the target's normalised image coordinates and the horizontality of optical x),
  because the optical centre is offset from the axes and moves as the head turns.

All inputs are in the ``mount`` frame. ``up_mount`` is the world's up direction expressed in
the mount frame (it changes as the wearer moves; the controller supplies it from SLAM or the
IMU). Within ``zenith_cone_rad`` of straight up or down the vertical rule is undefined: the
result says so (``vertical_defined=False``) and the cyclotorsion is held at its current angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .chain import forward_kinematics
from .geometry import JOINT_NAMES, HeadGeometry
from .transforms import cross3

#: Default cone around the zenith/nadir in which "image vertical" has no meaning.
ZENITH_CONE_RAD = math.radians(5.0)
#: Smallest singular value of d(gaze)/d(elevation, pan) below which a posture is reported
#: near-singular (gaze along the elevation axis: pan and cyclotorsion align).
SINGULAR_TOL = 0.1
_RANGE_TOL = 1e-12


@dataclass(frozen=True)
class GazeSolution:
    """One set of joint angles that fixates the target.

    q : (3,) joint angles, radians, inside the joint ranges.
    sigma_min : smallest singular value of the pointing Jacobian d(gaze)/d(elevation, pan);
        rates needed to follow a moving target scale like 1 / sigma_min.
    """

    q: np.ndarray
    sigma_min: float


@dataclass(frozen=True)
class GazeResult:
    """Outcome of a gaze IK query.

    reachable : True when at least one solution lies inside every joint range.
    solutions : the valid solutions, nearest to ``q_current`` first.
    reason : empty when reachable; otherwise says which joint blocks and by how much.
    blocking_joint : name of the joint whose range blocks the nearest candidate, if any.
    vertical_defined : False when the target is within the zenith cone, where the cyclotorsion
        was held instead of set by the image-vertical rule.
    near_singular : True when the best solution's sigma_min is below ``SINGULAR_TOL``.
    """

    reachable: bool
    solutions: tuple[GazeSolution, ...]
    reason: str = ""
    blocking_joint: str | None = None
    vertical_defined: bool = True
    near_singular: bool = False
    required: tuple[np.ndarray, ...] = field(default=(), repr=False)

    @property
    def best(self) -> GazeSolution | None:
        return self.solutions[0] if self.solutions else None

    @property
    def q(self) -> np.ndarray:
        if not self.reachable:
            raise ValueError(f"gaze target unreachable: {self.reason}")
        return self.solutions[0].q


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"direction {v.tolist()} has zero or non-finite length; give a non-zero 3-vector")
    return v / n


def paden_kahan_2(w1: np.ndarray, w2: np.ndarray, p: np.ndarray, q: np.ndarray) -> list[tuple[float, float]]:
    """All (t1, t2) with R(w1, t1) R(w2, t2) p = q, for unit axes w1, w2 through a common point.

    p and q are unit vectors. Returns 0, 1 or 2 solutions (Murray, Li, Sastry, 1994, 3.2.2).
    """
    c12 = float(w1 @ w2)
    denom = c12 * c12 - 1.0
    if abs(denom) < 1e-12:
        raise ValueError("the elevation and pan axes are parallel; the head cannot point in 3D")
    alpha = (c12 * (w2 @ p) - (w1 @ q)) / denom
    beta = (c12 * (w1 @ q) - (w2 @ p)) / denom
    w12 = cross3(w1, w2)
    g2 = (p @ p - alpha * alpha - beta * beta - 2.0 * alpha * beta * c12) / (w12 @ w12)
    if g2 < -1e-12:
        return []
    gammas = [0.0] if g2 <= 1e-24 else [math.sqrt(g2), -math.sqrt(g2)]
    out = []
    for g in gammas:
        z = alpha * w1 + beta * w2 + g * w12
        t2 = _subproblem_1(w2, p, z)
        t1 = -_subproblem_1(w1, q, z)
        out.append((t1, t2))
    return out


def _subproblem_1(w: np.ndarray, p: np.ndarray, q: np.ndarray) -> float:
    """The angle t with R(w, t) p = q (components along w assumed equal)."""
    pp = p - w * (w @ p)
    qp = q - w * (w @ q)
    return math.atan2(float(w @ cross3(pp, qp)), float(pp @ qp))


def _wrap_into_range(t: float, lo: float, hi: float) -> float:
    """Represent angle t in [lo, hi] if some t + 2 pi k lies there, else the nearest (-pi, pi] one."""
    t = math.remainder(t, 2.0 * math.pi)
    for k in (0, -1, 1):
        tk = t + 2.0 * math.pi * k
        if lo - _RANGE_TOL <= tk <= hi + _RANGE_TOL:
            return min(max(tk, lo), hi)
    return t


def _pointing_sigma_min(axes_mount: np.ndarray, d: np.ndarray) -> float:
    J = np.column_stack([cross3(axes_mount[0], d), cross3(axes_mount[1], d)])
    return float(np.linalg.svd(J, compute_uv=False)[-1])


def _cyclotorsion_for_vertical(head: HeadGeometry, q12: tuple[float, float], up: np.ndarray,
                               cone: float, q3_hold: float) -> tuple[float, bool]:
    """The cyclotorsion angle that makes optical x horizontal with optical y pointing down."""
    pose0 = forward_kinematics(head, np.array([q12[0], q12[1], 0.0]))
    d = pose0.optic_axis
    x_des = cross3(d, up)
    if np.linalg.norm(x_des) < math.sin(cone):
        return q3_hold, False
    x_des /= np.linalg.norm(x_des)
    x0 = pose0.R_mount_cam[:, 0]
    a3 = pose0.axes_mount[2]
    return math.atan2(float(a3 @ cross3(x0, x_des)), float(x0 @ x_des)), True


def _finish(head: HeadGeometry, candidates: list[np.ndarray], q_current: np.ndarray, d_of, vertical: bool,
            no_solution_reason: str) -> GazeResult:
    """Wrap candidates into the ranges, keep the valid ones, name the blocking limit otherwise."""
    lo, hi = head.lower, head.upper
    valid, required = [], []
    for q in candidates:
        q = np.array([_wrap_into_range(t, l, h) for t, l, h in zip(q, lo, hi)])
        required.append(q)
        if np.all(q >= lo - _RANGE_TOL) and np.all(q <= hi + _RANGE_TOL):
            pose = forward_kinematics(head, q)
            valid.append(GazeSolution(q=q, sigma_min=_pointing_sigma_min(pose.axes_mount, d_of(pose))))
    valid.sort(key=lambda s: float(np.linalg.norm(s.q - q_current)))
    if valid:
        return GazeResult(True, tuple(valid), vertical_defined=vertical,
                          near_singular=valid[0].sigma_min < SINGULAR_TOL, required=tuple(required))
    if not required:
        return GazeResult(False, (), reason=no_solution_reason, vertical_defined=vertical)
    # The candidate that misses its ranges by the least names the blocking joint.
    def excess(q):
        return np.maximum(lo - q, 0) + np.maximum(q - hi, 0)
    worst = min(required, key=lambda q: float(excess(q).sum()))
    j = int(np.argmax(excess(worst)))
    reason = (f"{JOINT_NAMES[j]} would need {math.degrees(worst[j]):.1f} deg, outside its range "
              f"[{math.degrees(lo[j]):.1f}, {math.degrees(hi[j]):.1f}] deg")
    return GazeResult(False, (), reason=reason, blocking_joint=JOINT_NAMES[j], vertical_defined=vertical,
                      required=tuple(required))


def gaze_at_direction(head: HeadGeometry, d_mount, up_mount=(0.0, 0.0, 1.0), q_current=None,
                      zenith_cone_rad: float = ZENITH_CONE_RAD) -> GazeResult:
    """Joint angles that align the optic axis with direction ``d_mount`` (3,), closed form.

    Parameters
    ----------
    d_mount : (3,) gaze direction in the mount frame (any length > 0).
    up_mount : (3,) world up in the mount frame.
    q_current : (3,) current joint angles, radians; solutions are sorted by distance to it and
        its cyclotorsion is held inside the zenith cone. Defaults to zeros.
    """
    d = _unit(d_mount)
    up = _unit(up_mount)
    q_cur = np.zeros(3) if q_current is None else np.asarray(q_current, float)
    axes = head.axes
    f0 = np.asarray(head.camera.forward, float)  # optic axis in the pan link frame at any cyclotorsion
    candidates, vertical = [], True
    for t1, t2 in paden_kahan_2(axes[0], axes[1], f0, d):
        t3, vertical = _cyclotorsion_for_vertical(head, (t1, t2), up, zenith_cone_rad, q_cur[2])
        candidates.append(np.array([t1, t2, t3]))
    return _finish(head, candidates, q_cur, lambda pose: pose.optic_axis, vertical,
                   "no elevation and pan angles point the optic axis that way (outside the cone the two axes can reach)")


def gaze_at_point(head: HeadGeometry, p_mount, up_mount=(0.0, 0.0, 1.0), q_current=None,
                  zenith_cone_rad: float = ZENITH_CONE_RAD, tol: float = 1e-14, max_iter: int = 30) -> GazeResult:
    """Joint angles that put the 3D point ``p_mount`` (3,), metres, on the optic axis, in front.

    The closed-form direction solution from the current optical centre seeds Newton's method on
    three residuals: the point's normalised image coordinates (x/z, y/z) and optical x . up
    (or the held cyclotorsion inside the zenith cone). Converges quadratically; points too close
    to the head to be fixated are reported unreachable.
    """
    p = np.asarray(p_mount, float)
    up = _unit(up_mount)
    q_cur = np.zeros(3) if q_current is None else np.asarray(q_current, float)
    c0 = forward_kinematics(head, q_cur).p_mount_cam
    if np.linalg.norm(p - c0) < 1e-9:
        return GazeResult(False, (), reason="target coincides with the optical centre")
    seed = gaze_at_direction(head, p - c0, up, q_cur, zenith_cone_rad)
    seeds = list(seed.solutions) + [GazeSolution(q=q, sigma_min=0.0) for q in seed.required]
    candidates, vertical = [], seed.vertical_defined
    seen = []
    for s in seeds:
        if any(np.allclose(s.q, t) for t in seen):
            continue
        seen.append(s.q)
        q, vert = _polish_point(head, p, up, s.q.copy(), q_cur[2], zenith_cone_rad, tol, max_iter)
        if q is not None:
            candidates.append(q)
            vertical = vert
    far = np.linalg.norm(p - c0) > 100.0 * max(float(np.linalg.norm(c0)), 0.01)
    if not candidates and far and not seed.reachable and seed.required:
        # Newton found nothing near out-of-range seeds of a far point (one along the elevation
        # axis is a gimbal lock); from far away the direction's blocking joint is the reason.
        return seed
    too_close = "the point is too close to the head for the optic axis to pass through it in front of the camera"
    return _finish(head, candidates, q_cur, lambda pose: _unit(p - pose.p_mount_cam), vertical, too_close)


def point_residual(head: HeadGeometry, q: np.ndarray, p: np.ndarray, up: np.ndarray, q3_hold: float | None):
    """Residual r (3,) of fixating point p with the vertical rule, and its Jacobian dr/dq (3, 3).

    r = (X/Z, Y/Z, x_cam . up) with (X, Y, Z) the point in the optical frame; if ``q3_hold`` is
    given (zenith cone) the third residual is q3 - q3_hold. Also returns Z and y_cam . up.
    """
    pose = forward_kinematics(head, q)
    R = pose.R_mount_cam
    c = pose.p_mount_cam
    P = R.T @ (p - c)
    X, Y, Z = P
    # A point fixed in the mount frame, seen from a camera turned by joint i about axis w_i
    # through o_i, moves in the camera frame by -R^T (w_i x (p - o_i)).
    dP = -(R.T @ np.cross(pose.axes_mount, p - pose.origins_mount).T)  # (3 coords, 3 joints)
    J = np.empty((3, 3))
    J[0] = (dP[0] * Z - X * dP[2]) / (Z * Z)
    J[1] = (dP[1] * Z - Y * dP[2]) / (Z * Z)
    x_cam = R[:, 0]
    if q3_hold is None:
        r3 = x_cam @ up
        J[2] = np.cross(pose.axes_mount, x_cam) @ up
    else:
        r3 = q[2] - q3_hold
        J[2] = [0.0, 0.0, 1.0]
    return np.array([X / Z, Y / Z, r3]), J, Z, float(R[:, 1] @ up)


def _polish_point(head, p, up, q, q3_hold, cone, tol, max_iter):
    pose = forward_kinematics(head, q)
    vertical = np.linalg.norm(np.cross(_unit(p - pose.p_mount_cam), up)) >= math.sin(cone)
    hold = None if vertical else q3_hold
    if not vertical:
        q[2] = q3_hold
    for _ in range(max_iter):
        r, J, Z, _ = point_residual(head, q, p, up, hold)
        if Z <= 0:
            return None, vertical
        if np.max(np.abs(r)) < tol:
            break
        # Least squares, not solve: a far point along the elevation axis makes J singular (that
        # joint no longer moves the point), and the minimum-norm step still converges.
        step = np.linalg.lstsq(J, r, rcond=None)[0]
        # Damp steps larger than ~0.3 rad so Newton stays in the seed's basin.
        n = np.linalg.norm(step)
        q = q - step * (min(1.0, 0.3 / n) if n > 0 else 1.0)
    r, J, Z, y_up = point_residual(head, q, p, up, hold)
    if Z <= 0 or np.max(np.abs(r)) > 1e-9 or (vertical and y_up > 0):
        return None, vertical
    return q, vertical
