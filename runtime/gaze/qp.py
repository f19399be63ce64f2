"""The joint-rate QP of the gaze controller: one small convex problem, built once, re-solved
every control period with new parameter values (cvxpy's disciplined parametrised programming).

Variables: the joint rates ``qd`` (3,), rad/s. The desired motion is given as joint rates
``qd_des`` (from the fixation IK: where the joints should be one period from now), but it is
followed in the camera's own angular velocity, ``omega_cam = J_cam qd`` (optical frame), so
that when a limit bites the QP gives up the least important part of the motion (the roll about
the optic axis, weighted ``roll_weight``) and keeps the gaze moving in a straight line, rather
than clipping each joint on its own and bending the path::

    minimise   | W (J_cam qd - J_cam qd_des) |^2 + smooth | qd - qd_prev |^2 + reg | qd |^2
    subject to lo <= qd <= hi

with ``W = diag(1, 1, roll_weight)`` and the bounds ``lo, hi`` the tightest of the speed limit
(the controlled-motion limit, never above the servo's) and the joint range reached within one
period: ``(q_min - q) / dt <= qd <= (q_max - q) / dt``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RateQPSettings:
    """Weights of the rate QP. ``smooth`` penalises the change of rate between periods
    ((rad/s)^-2, relative to the gaze term), ``reg`` keeps the problem strictly convex when the
    camera Jacobian is near singular, ``roll_weight`` weights the roll about the optic axis."""

    smooth: float = 0.05
    reg: float = 1e-4
    roll_weight: float = 0.5


class RateQP:
    """Joint-rate QP built once; :meth:`solve` sets the parameters and re-solves (Clarabel)."""

    def __init__(self, settings: RateQPSettings = RateQPSettings()):
        # Imported here, not with the module: cvxpy takes ~1 s to import, and every `wvr` command
        # imports the gaze package (its parser lists the closed loop's tasks) without a QP to solve.
        import cvxpy as cp

        self.settings = settings
        self.qd = cp.Variable(3, name="qd")
        # The objective is written as one stacked least-squares | A qd - b |^2: the gaze term,
        # the smoothness term and the regulariser, with A and b parameters (DPP-compliant).
        self.A = cp.Parameter((9, 3), name="A")
        self.b = cp.Parameter(9, name="b")
        self.lo = cp.Parameter(3, name="lo")
        self.hi = cp.Parameter(3, name="hi")
        self.problem = cp.Problem(cp.Minimize(cp.sum_squares(self.A @ self.qd - self.b)),
                                  [self.qd >= self.lo, self.qd <= self.hi])
        assert self.problem.is_dpp()
        self._W = np.diag([1.0, 1.0, settings.roll_weight])
        self.failures = 0

    @staticmethod
    def bounds(q, q_min, q_max, speed, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Rate bounds (3,), (3,) rad/s from the speed limit and the range reached in ``dt`` s."""
        q, q_min, q_max = (np.asarray(a, float) for a in (q, q_min, q_max))
        speed = np.broadcast_to(np.asarray(speed, float), (3,))
        lo = np.maximum(-speed, (q_min - q) / dt)
        hi = np.minimum(speed, (q_max - q) / dt)
        # Rounding can leave q a hair outside its range: never ask for an empty box.
        lo = np.minimum(lo, 0.0)
        hi = np.maximum(hi, 0.0)
        return lo, hi

    def solve(self, J_cam, qd_des, qd_prev, lo, hi) -> np.ndarray:
        """Joint rates (3,), rad/s, inside ``[lo, hi]``.

        J_cam : (3, 3) camera angular velocity (optical frame) per joint rate.
        qd_des : (3,) the rates that would reach the desired angles in one period.
        qd_prev : (3,) the previous period's rates (smoothness).
        """
        s = self.settings
        J_cam, qd_des, qd_prev = (np.asarray(a, float) for a in (J_cam, qd_des, qd_prev))
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        if not (np.isfinite(J_cam).all() and np.isfinite(qd_des).all() and np.isfinite(qd_prev).all()):
            raise ValueError("rate QP given non-finite Jacobian or rates; the controller must hold instead")
        WJ = self._W @ J_cam
        a_s, a_r = np.sqrt(s.smooth), np.sqrt(s.reg)
        self.A.value = np.vstack([WJ, a_s * np.eye(3), a_r * np.eye(3)])
        self.b.value = np.concatenate([WJ @ qd_des, a_s * qd_prev, np.zeros(3)])
        self.lo.value, self.hi.value = lo, hi
        import cvxpy as cp      # loaded by __init__; a module in an attribute would not deep-copy or pickle

        try:
            self.problem.solve(solver=cp.CLARABEL)
            ok = self.problem.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) and self.qd.value is not None
        except cp.SolverError:
            ok = False
        if not ok:
            # Never leave the controller without a safe answer: the desired rates clipped to the box.
            self.failures += 1
            return np.clip(qd_des, lo, hi)
        # Interior-point solutions sit a hair inside or outside the box: the box is a hard limit.
        return np.clip(np.asarray(self.qd.value, float), lo, hi)
