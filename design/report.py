"""A sweep's outputs: front.csv, chosen_head.toml, head.xml, pictures and report.md."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from kinematics import save_head
from kinematics.mjcf import build_mjcf

from .decide import choose_design
from .layout import head_from_variables
from .pareto import hypervolume_mc, non_dominated, normalise
from .problem import reference_scores
from .sweep import SweepResult
from .sweep_file import CONSTRAINTS, CRITERIA, VARIABLES, SweepSpec

HV_SAMPLES = 100_000


def front_hypervolume(F_front: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """Monte Carlo hypervolume of a front normalised by its own ideal and nadir, ref point 1.1."""
    Fn = normalise(F_front, F_front.min(axis=0), F_front.max(axis=0))
    return hypervolume_mc(Fn, 1.1, HV_SAMPLES, seed)


def write_outputs(result: SweepResult, spec: SweepSpec, out: Path, pictures: bool = True) -> dict:
    """Write the sweep's files into ``out``; returns a summary dict (front size, chosen, HV...)."""
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
    summary = {"evaluations": len(result.F), "feasible": int(feasible.sum()), "front_size": int(len(idx)),
               "algorithm": result.algorithm}
    ref_crit, ref_cons = reference_scores(result.ctx)
    if len(idx) == 0:
        summary["chosen"] = None
        (out / "report.md").write_text(_report(spec, summary, None, ref_crit, None, None))
        return summary
    k, how = choose_design(result.F[idx], spec.decision_method, spec.decision_weights)
    chosen = idx[k]
    head = head_from_variables(result.X[chosen], spec, name=f"{spec.name}-chosen")
    save_head(head, out / "chosen_head.toml")
    (out / "head.xml").write_text(build_mjcf(head))
    hv, hv_se = front_hypervolume(result.F[idx])
    summary.update(chosen_index=int(chosen), decision=how, hypervolume=hv, hypervolume_se=hv_se,
                   chosen_criteria=dict(zip(CRITERIA, map(float, result.F[chosen]))),
                   reference_criteria={k: float(v) for k, v in ref_crit.items()})
    pics = {}
    if pictures:
        pics["parallel"] = _parallel_coordinates(result.F[idx], k, out / "front_parallel.png")
        pics["scatter"] = _scatter_matrix(result.F, feasible, front, chosen, out / "front_scatter.png")
        from kinematics.picture import render_head
        pics["head"] = render_head(head, out / "chosen_head.png", np.radians([[0, 0, 0], [35, 50, 20], [-30, -60, -25]])).name
    (out / "report.md").write_text(_report(spec, summary, result.F[chosen], ref_crit, how, pics))
    return summary


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
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path.name


def _report(spec, summary, chosen_F, ref_crit, how, pics) -> str:
    lines = [f"# Design sweep `{spec.name}`", "",
             f"- Algorithm: {summary['algorithm']}; evaluations: {summary['evaluations']}; "
             f"feasible: {summary['feasible']}; non-dominated (front): {summary['front_size']}",
             "- Files: [evaluations.csv](evaluations.csv), [front.csv](front.csv), [sweep.toml](sweep.toml)"
             + (", [chosen_head.toml](chosen_head.toml), [head.xml](head.xml)" if chosen_F is not None else ""), ""]
    if chosen_F is None:
        lines += ["No feasible design was found: widen the bounds or raise the budget.", ""]
        return "\n".join(lines)
    lines += [f"- Hypervolume of the front: {summary['hypervolume']:.4f} ± {summary['hypervolume_se']:.4f} "
              f"(objectives normalised to [0, 1] between the front's ideal and nadir, reference point 1.1 in each, "
              f"so at most 1.1^7 = {1.1 ** 7:.4f}; Monte Carlo with {HV_SAMPLES:,} samples, ± one standard error)",
              f"- Decision: {how}", "",
              "| criterion | chosen | reference head |", "|---|---|---|"]
    for name, v in zip(CRITERIA, chosen_F):
        lines.append(f"| `{name}` | {v:.6g} | {ref_crit[name]:.6g} |")
    lines.append("")
    if pics:
        lines += [f"![parallel coordinates]({pics['parallel']})", "", f"![scatter matrix]({pics['scatter']})", "",
                  f"![chosen head]({pics['head']})", ""]
    return "\n".join(lines)
