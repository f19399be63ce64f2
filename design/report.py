"""A sweep's outputs: front.csv, chosen_head.toml, head.xml, pictures and report.md."""

from __future__ import annotations

import csv
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from kinematics import save_head
from kinematics.mjcf import build_mjcf

from .decide import choose_design
from .layout import head_from_variables
from .pareto import hypervolume, non_dominated, normalise
from .problem import reference_scores
from .sweep import SweepResult
from .sweep_file import CONSTRAINTS, CRITERIA, VARIABLES, SweepSpec

def front_hypervolume(F_front: np.ndarray) -> tuple[float, bool]:
    """Hypervolume of a front normalised by its own ideal and nadir, ref point 1.1, and whether
    it is exact (pareto.hypervolume)."""
    Fn = normalise(F_front, F_front.min(axis=0), F_front.max(axis=0))
    return hypervolume(Fn, 1.1)


@dataclass(frozen=True)
class ChosenDesign:
    """The design the decision picked from the front.

    index : its row in the sweep's evaluations (SweepResult order). decision : how it was chosen
    (the method and weights, in words). criteria, reference_criteria : the seven criteria of the
    chosen and of the reference head, by name (sweep_file.CRITERIA). hypervolume,
    hypervolume_exact : the front's normalised hypervolume and whether it is exact (else
    moocore's approximation). head_path : its chosen_head.toml.
    """

    index: int
    decision: str
    criteria: dict[str, float]
    reference_criteria: dict[str, float]
    hypervolume: float
    hypervolume_exact: bool
    head_path: Path


@dataclass(frozen=True)
class DesignOutputs:
    """What a sweep's outputs hold: counts, the chosen design (None when nothing is feasible)
    and the files written into ``folder``.

    evaluations : designs in the sweep. evaluated, reused : computed in this run, and taken from
    the log of a resumed one. feasible : designs meeting every constraint. front_size : the
    non-dominated feasible ones. pictures : kind -> file name of the plots written.
    """

    folder: Path
    algorithm: str
    evaluations: int
    evaluated: int
    reused: int
    feasible: int
    front_size: int
    chosen: ChosenDesign | None
    pictures: dict[str, str]

    @property
    def report_path(self) -> Path:
        return self.folder / "report.md"


def write_outputs(result: SweepResult, spec: SweepSpec, out: Path, pictures: bool = True) -> DesignOutputs:
    """Write the sweep's files into ``out`` (front.csv, report.md and, when a design is feasible,
    chosen_head.toml, head.xml and the plots); returns what they hold."""
    out = Path(out)
    feasible = result.feasible
    front = non_dominated(result.F, feasible)
    idx = np.flatnonzero(front)
    with open(out / "front.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["batch", *VARIABLES, *CRITERIA, *CONSTRAINTS])
        for i in idx:
            w.writerow([int(result.batch[i]), *map(repr, map(float, result.X[i])), *map(repr, map(float, result.F[i])),
                        *map(repr, map(float, result.G[i]))])
    ref_crit, _ = reference_scores(result.ctx)
    outputs = DesignOutputs(folder=out, algorithm=result.algorithm, evaluations=len(result.F),
                            evaluated=result.evaluated, reused=result.reused, feasible=int(feasible.sum()),
                            front_size=int(len(idx)), chosen=None, pictures={})
    if len(idx) == 0:
        (out / "report.md").write_text(_report(spec, outputs))
        return outputs
    k, how = choose_design(result.F[idx], spec.decision_method, spec.decision_weights)
    i_chosen = int(idx[k])
    head = head_from_variables(result.X[i_chosen], spec, name=f"{spec.name}-chosen")
    save_head(head, out / "chosen_head.toml")
    (out / "head.xml").write_text(build_mjcf(head))
    hv, hv_exact = front_hypervolume(result.F[idx])
    chosen = ChosenDesign(index=i_chosen, decision=how, criteria=dict(zip(CRITERIA, map(float, result.F[i_chosen]))),
                          reference_criteria={c: float(v) for c, v in ref_crit.items()}, hypervolume=hv,
                          hypervolume_exact=hv_exact, head_path=out / "chosen_head.toml")
    pics = {}
    if pictures:
        pics["parallel"] = _parallel_coordinates(result.F[idx], k, out / "front_parallel.png")
        pics["scatter"] = _scatter_matrix(result.F, feasible, front, i_chosen, out / "front_scatter.png")
        from kinematics.picture import render_head
        pics["head"] = render_head(head, out / "chosen_head.png", np.radians([[0, 0, 0], [35, 50, 20], [-30, -60, -25]])).name
    outputs = replace(outputs, chosen=chosen, pictures=pics)
    (out / "report.md").write_text(_report(spec, outputs))
    return outputs


def _parallel_coordinates(F: np.ndarray, chosen: int, path: Path) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    Fn = normalise(F, F.min(axis=0), F.max(axis=0))
    fig, ax = plt.subplots(figsize=(10, 4.5))
    x = np.arange(F.shape[1])
    for row in Fn:
        ax.plot(x, row, color="#4477aa", alpha=0.35, lw=1)
    ax.plot(x, Fn[chosen], color="#cc3311", lw=3, label="chosen")
    ax.set_xticks(x, [c.replace("_", "\n") for c in CRITERIA], fontsize=8)
    ax.set_ylabel("normalised over the front (0 best)")
    ax.set_title(f"Pareto front: {len(F)} non-dominated designs")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def _scatter_matrix(F, feasible, front, chosen, path: Path) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    M = F.shape[1]
    fig, axes = plt.subplots(M, M, figsize=(14, 14))
    for i in range(M):
        for j in range(M):
            ax = axes[i, j]
            if i == j:
                ax.hist(F[feasible, i], bins=20, color="#bbbbbb")
                ax.hist(F[front, i], bins=20, color="#4477aa")
            else:
                ax.scatter(F[feasible, j], F[feasible, i], s=3, c="#bbbbbb")
                ax.scatter(F[front, j], F[front, i], s=6, c="#4477aa")
                ax.scatter(F[chosen, j], F[chosen, i], s=40, c="#cc3311", marker="*")
            ax.tick_params(labelsize=5)
            if i == M - 1:
                ax.set_xlabel(CRITERIA[j], fontsize=7)
            if j == 0:
                ax.set_ylabel(CRITERIA[i], fontsize=7)
    fig.suptitle("Criteria pairwise: feasible designs (grey), front (blue), chosen (red star)")
    # Fixed margins: tight_layout measured the 49 axes' labels in a draw of its own, ~40 % of the time.
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.04, top=0.96, wspace=0.3, hspace=0.25)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path.name


def _report(spec: SweepSpec, o: DesignOutputs) -> str:
    c = o.chosen
    lines = [f"# Design sweep `{spec.name}`", "",
             f"- Algorithm: {o.algorithm}; evaluations: {o.evaluations}; "
             f"feasible: {o.feasible}; non-dominated (front): {o.front_size}",
             "- Files: [evaluations.csv](evaluations.csv), [front.csv](front.csv), [sweep.toml](sweep.toml)"
             + (", [chosen_head.toml](chosen_head.toml), [head.xml](head.xml)" if c is not None else ""), ""]
    if c is None:
        lines += ["No feasible design was found: widen the bounds or raise the budget.", ""]
        return "\n".join(lines)
    how = ("exact (moocore)" if c.hypervolume_exact else
           "moocore's deterministic approximation, relative error about 1e-4, as the front is too large for the exact one")
    lines += [f"- Hypervolume of the front: {c.hypervolume:.4f} "
              f"(objectives normalised to [0, 1] between the front's ideal and nadir, reference point 1.1 in each, "
              f"so at most 1.1^7 = {1.1 ** 7:.4f}; {how})",
              f"- Decision: {c.decision}", "",
              "| criterion | chosen | reference head |", "|---|---|---|"]
    for name in CRITERIA:
        lines.append(f"| `{name}` | {c.criteria[name]:.6g} | {c.reference_criteria[name]:.6g} |")
    lines.append("")
    if o.pictures:
        lines += [f"![parallel coordinates]({o.pictures['parallel']})", "",
                  f"![scatter matrix]({o.pictures['scatter']})", "", f"![chosen head]({o.pictures['head']})", ""]
    return "\n".join(lines)
