"""The surrogate pre-screen (design.search.ScreenedAGEMOEA2) picks better designs than it is offered."""

import numpy as np
from pymoo.indicators.hv import HV
from pymoo.operators.sampling.lhs import LHS
from pymoo.problems import get_problem

from design.pareto import non_dominated
from design.search import PymooAskTell, ScreenedAGEMOEA2


def front_hypervolume(screen: int, seed: int, budget: int = 280) -> float:
    """Hypervolume (reference 1.1) of the front of every evaluation of a run on DTLZ2 (3 objectives,
    12 variables, like the head's 12 coordinates) after ``budget`` evaluations."""
    problem = get_problem("dtlz2", n_var=12, n_obj=3)
    search = PymooAskTell(ScreenedAGEMOEA2(pop_size=28, sampling=LHS(), screen=screen), problem, seed)
    Fs = []
    while sum(map(len, Fs)) < budget:
        X = search.ask()
        F = problem.evaluate(X)
        search.tell(X, F, np.zeros((len(X), 0)))
        Fs.append(F)
    F = np.vstack(Fs)[:budget]
    return float(HV(ref_point=np.full(3, 1.1))(F[non_dominated(F)]))


def test_screened_offspring_beat_the_unscreened_at_a_fixed_budget():
    # screen=1 evaluates the mating's offspring as proposed (plain AGE-MOEA2); screen=10 picks its
    # batch from ten times as many by the model. Taking the proposals in order (a no-op
    # selection) or the worst predicted gives about the unscreened hypervolume or less.
    screened = np.array([front_hypervolume(10, seed) for seed in (0, 1, 2)])
    unscreened = np.array([front_hypervolume(1, seed) for seed in (0, 1, 2)])
    assert np.all(screened > unscreened), (screened, unscreened)
    assert screened.mean() > unscreened.mean() + 0.15, (screened, unscreened)


def test_screening_is_deterministic_for_the_seed():
    assert front_hypervolume(10, 3, budget=140) == front_hypervolume(10, 3, budget=140)
