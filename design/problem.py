"""The pymoo Problem: 12 position variables, the 7 criteria, 3 constraints. It only gathers.

The criteria live in :mod:`design.criteria`; the layout rule in :mod:`design.layout`; the
algorithm, termination and decision are separate objects (:mod:`design.search`,
:mod:`design.decide`), as in pymoo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pymoo.core.problem import Problem

from kinematics import HeadGeometry, reference_head

from . import criteria as C
from .layout import head_from_variables
from .sweep_file import CONSTRAINTS, CRITERIA, VARIABLES, SweepSpec
from .workload import Workload, build_workload


@dataclass(frozen=True)
class EvaluationContext:
    """What every evaluation needs; built once per sweep and shipped to workers."""

    spec: SweepSpec
    workload: Workload

    @classmethod
    def from_spec(cls, spec: SweepSpec) -> "EvaluationContext":
        # The workload depends only on the (fixed) axes, so any layout of the sweep will do.
        head = head_from_variables((spec.xl + spec.xu) / 2, spec)
        return cls(spec=spec, workload=build_workload(head, spec.workload))


def score_head(head: HeadGeometry, ctx: EvaluationContext) -> tuple[dict, dict]:
    """(criteria, constraints) of any head, as name -> value dicts in output order."""
    tau = C.workload_torques(head, ctx.workload)
    s = ctx.spec
    crit = {
        "working_volume_cm3": C.working_volume_cm3(head, s.voxel_m),
        "self_collision": C.self_collision(head, s.collision_steps),
        "integrated_torque": C.integrated_torque(head, ctx.workload, tau),
        "max_torque_nm": C.max_torque_nm(head, ctx.workload, tau),
        "radius_elevation_mm": C.radius_elevation_mm(head),
        "radius_pan_mm": C.radius_pan_mm(head),
        "radius_cyclotorsion_mm": C.radius_cyclotorsion_mm(head),
    }
    cons = {
        "torque_excess_nm": C.torque_excess_nm(head, ctx.workload, tau),
        "rest_penetration_m": C.rest_penetration_m(head, s.clearance_m),
        "part_overlap_m": C.part_overlap_m(head, s.clearance_m),
    }
    assert tuple(crit) == CRITERIA and tuple(cons) == CONSTRAINTS
    return crit, cons


def evaluate_design(x, ctx: EvaluationContext) -> tuple[np.ndarray, np.ndarray]:
    """(F (7,), G (3,)) of one design vector x (12,)."""
    crit, cons = score_head(head_from_variables(x, ctx.spec), ctx)
    return np.array(list(crit.values())), np.array(list(cons.values()))


def evaluate_batch(X, ctx: EvaluationContext) -> tuple[np.ndarray, np.ndarray]:
    """(F (n, 7), G (n, 3)) of design vectors X (n, 12)."""
    X = np.atleast_2d(np.asarray(X, float))
    out = [evaluate_design(x, ctx) for x in X]
    return np.array([o[0] for o in out]).reshape(-1, len(CRITERIA)), np.array([o[1] for o in out]).reshape(-1, len(CONSTRAINTS))


class HeadLayoutProblem(Problem):
    """pymoo Problem over the sweep's bounds; evaluation is :func:`evaluate_batch`."""

    def __init__(self, ctx: EvaluationContext):
        self.ctx = ctx
        super().__init__(n_var=len(VARIABLES), n_obj=len(CRITERIA), n_ieq_constr=len(CONSTRAINTS),
                         xl=ctx.spec.xl, xu=ctx.spec.xu)

    def _evaluate(self, X, out, *args, **kwargs):
        out["F"], out["G"] = evaluate_batch(X, self.ctx)


def reference_scores(ctx: EvaluationContext) -> tuple[dict, dict]:
    """The reference head scored by the same criteria, for comparison in reports."""
    return score_head(reference_head(), ctx)
