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

from .layout import head_from_variables
from .sweep_file import CONSTRAINTS, CRITERIA, VARIABLES, SweepSpec
from .workload import Workload, build_workload


@dataclass(frozen=True)
class EvaluationContext:
    """What every evaluation needs; built once per sweep and shipped to workers."""

    spec: SweepSpec
    workload: Workload

    @property
    def evaluator(self):
        """The batch evaluator (design.batch), made on first use in each process."""
        ev = self.__dict__.get("_evaluator")
        if ev is None:
            from .batch import Evaluator
            ev = Evaluator(self.spec, self.workload)
            object.__setattr__(self, "_evaluator", ev)
        return ev

    def __getstate__(self):
        # Shipped to Dask workers without the evaluator's caches (rebuilt there).
        return {"spec": self.spec, "workload": self.workload}

    def __setstate__(self, state):
        object.__setattr__(self, "spec", state["spec"])
        object.__setattr__(self, "workload", state["workload"])

    @classmethod
    def from_spec(cls, spec: SweepSpec) -> "EvaluationContext":
        # The workload depends only on the (fixed) axes, so any layout of the sweep will do.
        head = head_from_variables((spec.xl + spec.xu) / 2, spec)
        return cls(spec=spec, workload=build_workload(head, spec.workload))


def score_head(head: HeadGeometry, ctx: EvaluationContext) -> tuple[dict, dict]:
    """(criteria, constraints) of any head, as name -> value dicts in output order (the
    definitions are design.criteria's; computed by the batch kernels)."""
    from .batch import arrays_from_head

    F, G = ctx.evaluator(arrays_from_head(head), head)
    return dict(zip(CRITERIA, map(float, F[0]))), dict(zip(CONSTRAINTS, map(float, G[0])))


def evaluate_design(x, ctx: EvaluationContext) -> tuple[np.ndarray, np.ndarray]:
    """(F (7,), G (3,)) of one design vector x (12,)."""
    x = np.asarray(x, float)
    if x.shape != (len(VARIABLES),):
        head_from_variables(x, ctx.spec)   # raises the layout's message for a wrong shape
    F, G = evaluate_batch(x[None], ctx)
    return F[0], G[0]


def evaluate_batch(X, ctx: EvaluationContext) -> tuple[np.ndarray, np.ndarray]:
    """(F (n, 7), G (n, 3)) of design vectors X (n, 12): the layout as arrays for all designs at
    once, the criteria by the compiled kernels (design.batch)."""
    from .batch import arrays_from_variables

    X = np.atleast_2d(np.asarray(X, float))
    if X.ndim != 2 or X.shape[1] != len(VARIABLES):
        raise ValueError(f"designs must be an (n, {len(VARIABLES)}) array ({', '.join(VARIABLES)}), got {X.shape}")
    if len(X) == 0:
        return np.empty((0, len(CRITERIA))), np.empty((0, len(CONSTRAINTS)))
    return ctx.evaluator(arrays_from_variables(X, ctx.spec))


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
