"""Search algorithms behind one ask/tell interface, so the runner can checkpoint any of them.

* :func:`agemoea2` : pymoo's AGE-MOEA2: survival by an estimate of the front's
  geometry (its Lp norm) and of each design's proximity and diversity on it; no reference
  directions, so a small population (28) works for seven objectives.
* :func:`surrogate_agemoea2` (the default) : AGE-MOEA2 whose offspring are pre-screened by a model of the
  criteria and constraints fitted on every design evaluated so far (:class:`ScreenedAGEMOEA2`).
* :func:`nsga3` : pymoo's NSGA-III with Das-Dennis reference directions. NSGA-II's crowding
  distance loses selection pressure beyond three objectives; reference directions keep the
  front spread over all seven.
* :class:`RandomVariation` : the paper's own method as the baseline: random variations of the
  3D coordinates of camera and motors, and a Pareto test of non-dominance to keep the best.

All are deterministic for a seed and picklable mid-run (their random generators included).
"""

from __future__ import annotations

import numpy as np
from pymoo.algorithms.moo.age2 import AGEMOEA2
from pymoo.algorithms.moo.nsga3 import NSGA3
from pymoo.core.evaluator import Evaluator
from pymoo.core.population import Population
from pymoo.core.problem import Problem
from pymoo.operators.sampling.lhs import LHS
from pymoo.problems.static import StaticProblem
from pymoo.util.ref_dirs import get_reference_directions
from scipy.interpolate import RBFInterpolator

from .pareto import non_dominated


def _cache_age_kernels() -> None:
    """pymoo jit-compiles AGE-MOEA2's numba kernels without an on-disk cache, so every process
    that runs the search spent ~7 s compiling them again: the same functions with the same flags
    (nopython, fastmath), now compiled once into numba's cache. Same machine code, same results;
    a pymoo without these kernels is left as it is."""
    import numba
    from pymoo.algorithms.moo import age, age2

    def cached(kernel):
        return numba.njit(cache=True, fastmath=True)(kernel.py_func)

    kernels = [getattr(age, "point_2_line_distance", None), getattr(age, "find_corner_solutions", None),
               getattr(age2, "project_on_manifold", None),
               getattr(age.AGEMOEASurvival, "minkowski_distances", None),
               getattr(age2.AGEMOEA2Survival, "pairwise_distances", None)]
    if not all(isinstance(k, numba.core.registry.CPUDispatcher) for k in kernels):
        return
    # Callees first: a kernel's callees are looked up in its module when it is compiled.
    age.point_2_line_distance = cached(age.point_2_line_distance)
    age.find_corner_solutions = cached(age.find_corner_solutions)
    age2.project_on_manifold = cached(age2.project_on_manifold)
    age.AGEMOEASurvival.minkowski_distances = staticmethod(cached(age.AGEMOEASurvival.minkowski_distances))
    age2.AGEMOEA2Survival.pairwise_distances = staticmethod(cached(age2.AGEMOEA2Survival.pairwise_distances))


_cache_age_kernels()


class AskTell:
    """Interface: ``ask() -> X (n, n_var)``; ``tell(X, F, G)``. ``batch_size`` designs per ask."""

    batch_size: int

    def ask(self) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def tell(self, X: np.ndarray, F: np.ndarray, G: np.ndarray) -> None:  # pragma: no cover
        raise NotImplementedError


class PymooAskTell(AskTell):
    """Adapts a pymoo algorithm to :class:`AskTell` (evaluation happens outside pymoo)."""

    def __init__(self, algorithm, problem: Problem, seed: int):
        self.algorithm = algorithm
        self.problem = problem
        # Termination is the runner's business (an evaluation budget); give pymoo a distant one.
        algorithm.setup(problem, termination=("n_gen", 10**9), seed=seed, verbose=False)
        self.batch_size = algorithm.pop_size
        self._pop = None

    def ask(self) -> np.ndarray:
        self._pop = self.algorithm.ask()
        return self._pop.get("X")

    def tell(self, X, F, G) -> None:
        pop = self._pop[: len(X)]
        Evaluator().eval(StaticProblem(self.problem, F=F, G=G), pop)
        self.algorithm.tell(infills=pop)
        self._pop = None


#: AGE-MOEA2's population: with 28 it reaches random variation's 2520-evaluation hypervolume in
#: 0.14-0.38 of the evaluations over seeds 0-4, median 0.18; 14, 21 and 40 did worse on seeds 0-2
#: (docs/design-sweeps.md).
AGEMOEA2_POPULATION = 28


def agemoea2(problem: Problem, seed: int, pop_size: int = AGEMOEA2_POPULATION) -> PymooAskTell:
    """AGE-MOEA2 over the problem (pymoo's default constraint handling: feasible designs first,
    then the least violation), started from a Latin hypercube over the bounds."""
    return PymooAskTell(AGEMOEA2(pop_size=pop_size, sampling=LHS()), problem, seed)


class ScreenedAGEMOEA2(AGEMOEA2):
    """AGE-MOEA2 with a surrogate pre-screen of its offspring (Emmerich-style pre-screening).

    The objective is unchanged: the problem's criteria (minimised) under its constraints, and
    survival is AGE-MOEA2's on the true values. Only which offspring get evaluated changes:

    * proposals: each generation the mating (tournament, SBX, polynomial mutation) makes
      ``screen`` x ``n_offsprings`` candidates from the population;
    * model: scipy's ``RBFInterpolator``, thin-plate spline with a linear tail, local over the
      ``neighbors`` nearest evaluated designs, on the variables scaled to [0, 1] by the bounds,
      fitted to every design evaluated so far (criteria and constraints, one model);
    * selection: the first ``explore`` share of the batch is the mating's first candidates,
      unscreened (so the search is never confined to where the model is right); the rest are
      picked one by one, predicted-feasible candidates first (else the least predicted
      violation), by the largest predicted additive-epsilon gain over the feasible front of
      every evaluation so far (criteria scaled to that front's range); each pick's prediction
      joins that front, so the next pick must improve on it too, which keeps the batch spread.

    Until ``min_train`` designs are evaluated (the Latin hypercube start and the first
    generation), offspring are AGE-MOEA2's own. Every step is a function of the seed and of what
    was told, so a resume replays it exactly.

    The model is fitted on the last ``max_train`` designs told and the front is kept as an
    archive (the non-dominated set of the union is that of the old front and the new designs),
    so a generation's cost stays bounded on a sweep of 100,000 evaluations; a 2520-evaluation
    sweep reaches its target long before ``max_train`` matters.
    """

    def __init__(self, *, screen: int = 10, explore: float = 0.25, neighbors: int = 64, min_train: int = 37,
                 max_train: int = 2048, **kwargs):
        super().__init__(**kwargs)
        self.screen, self.explore = int(screen), float(explore)
        self.neighbors, self.min_train = int(neighbors), int(min_train)
        self.max_train = int(max_train)
        self._X = self._F = self._G = None     # the last max_train designs told: (n, n_var), (n, n_obj), (n, n_constr)
        self._front = None                     # the feasible non-dominated criteria so far (k, n_obj)

    def _remember(self, infills) -> None:
        if infills is None or len(infills) == 0:
            return
        X, F, G = infills.get("X"), infills.get("F"), infills.get("G")
        if self._X is None:
            self._X, self._F, self._G = X, F, G
        else:
            keep = max(0, len(self._X) + len(X) - self.max_train)
            self._X, self._F, self._G = (np.vstack([A[keep:], B])
                                         for A, B in ((self._X, X), (self._F, F), (self._G, G)))
        feasible = np.all(G <= 0, axis=1)
        if feasible.any():
            cand = F[feasible] if self._front is None else np.vstack([self._front, F[feasible]])
            self._front = cand[non_dominated(cand)]

    def front(self) -> np.ndarray:
        """The criteria (k, n_obj) the candidates must improve on: the feasible non-dominated
        designs told so far, or, while none is feasible, the designs the model is fitted on."""
        return self._F if self._front is None else self._front

    def _initialize_advance(self, infills=None, **kwargs):
        self._remember(infills)
        super()._initialize_advance(infills=infills, **kwargs)

    def _advance(self, infills=None, **kwargs):
        self._remember(infills)
        return super()._advance(infills=infills, **kwargs)

    def _infill(self):
        n = self.n_offsprings
        if self._X is None or len(self._X) < self.min_train or self.screen <= 1:
            return super()._infill()
        off = self.mating.do(self.problem, self.pop, self.screen * n, algorithm=self, random_state=self.random_state)
        X = off.get("X")
        n_keep = min(int(round(self.explore * n)), len(X))
        picked = np.concatenate([np.arange(n_keep), n_keep + self.select(X[n_keep:], n - n_keep)]).astype(int)
        return Population.new(X=X[picked])

    def predict(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted (F (m, n_obj), G (m, n_constr)) of designs X (m, n_var) from the last
        ``max_train`` designs told."""
        xl, xu = self.problem.xl, self.problem.xu
        model = RBFInterpolator((self._X - xl) / (xu - xl), np.hstack([self._F, self._G]),
                                neighbors=min(self.neighbors, len(self._X)), kernel="thin_plate_spline",
                                smoothing=1e-8)
        P = model((X - xl) / (xu - xl))
        return P[:, : self.problem.n_obj], P[:, self.problem.n_obj:]

    def select(self, X: np.ndarray, k: int) -> np.ndarray:
        """Indices of the ``k`` candidates of X (m, n_var) to evaluate, in the order picked."""
        k = min(k, len(X))
        try:
            F, G = self.predict(X)
        except np.linalg.LinAlgError:    # a degenerate neighbourhood: take the proposals as they come
            return np.arange(k)
        cv = np.maximum(G, 0).sum(axis=1)
        front = self.front()
        lo, hi = front.min(axis=0), front.max(axis=0)
        span = np.where(hi > lo, hi - lo, 1.0)
        Fn, An = (F - lo) / span, (front - lo) / span
        # gain[c] = min over front points p of max_i (p_i - c_i): > 0 iff no p weakly dominates c
        gain = np.full(len(X), np.inf)
        for s in range(0, len(An), 64):     # in blocks: (64, m, n_obj) at a time
            gain = np.minimum(gain, (An[s:s + 64, None, :] - Fn[None, :, :]).max(axis=2).min(axis=0))
        free = np.ones(len(X), bool)
        picked = []
        for _ in range(k):
            ok = free & (cv <= 0)
            if ok.any():
                i = int(np.flatnonzero(ok)[np.argmax(gain[ok])])
            else:                           # none predicted feasible: the least predicted violation
                i = int(np.flatnonzero(free)[np.argmin(cv[free])])
            picked.append(i)
            free[i] = False
            gain = np.minimum(gain, (Fn[i] - Fn).max(axis=1))
        return np.array(picked, dtype=int)


def surrogate_agemoea2(problem: Problem, seed: int, pop_size: int = AGEMOEA2_POPULATION,
                       **screen) -> PymooAskTell:
    """:class:`ScreenedAGEMOEA2` over the problem (population 28, Latin hypercube start; ``screen``:
    its keyword arguments). docs/design-sweeps.md, Convergence, fifth round."""
    return PymooAskTell(ScreenedAGEMOEA2(pop_size=pop_size, sampling=LHS(), **screen), problem, seed)


def nsga3(problem: Problem, seed: int, partitions: int) -> PymooAskTell:
    """NSGA-III over the problem with Das-Dennis directions (population = number of directions),
    started from a Latin hypercube over the bounds (docs/design-sweeps.md: with 28 directions it
    reaches random variation's 2520-evaluation hypervolume in 0.32-0.50 of the evaluations over
    seeds 0-4, against 0.58-0.94 for 84 directions and a uniform start)."""
    ref_dirs = get_reference_directions("das-dennis", problem.n_obj, n_partitions=partitions)
    return PymooAskTell(NSGA3(ref_dirs=ref_dirs, pop_size=len(ref_dirs), sampling=LHS()), problem, seed)


class RandomVariation(AskTell):
    """The paper's optimiser: vary the coordinates at random, keep the non-dominated.

    The first batch is uniform over the bounds. Afterwards each candidate is, with probability
    ``explore``, uniform again, else a Gaussian variation (sigma = ``sigma_frac`` of each
    bound's span) of a random member of the archive: the feasible non-dominated designs, or,
    while none is feasible, the ``batch_size`` least-violating ones.
    """

    def __init__(self, xl, xu, batch_size: int, seed: int, sigma_frac: float = 0.1, explore: float = 0.2):
        self.xl, self.xu = np.asarray(xl, float), np.asarray(xu, float)
        self.batch_size = batch_size
        self.sigma = sigma_frac * (self.xu - self.xl)
        self.explore = explore
        self.rng = np.random.default_rng(seed)
        self.X = np.empty((0, len(self.xl)))
        self.F = None
        self.G = None
        self.archive = np.empty(0, int)

    def ask(self) -> np.ndarray:
        n, d = self.batch_size, len(self.xl)
        uniform = self.rng.uniform(self.xl, self.xu, (n, d))
        if len(self.archive) == 0:
            return uniform
        parents = self.X[self.rng.choice(self.archive, n)]
        varied = np.clip(parents + self.rng.normal(0.0, 1.0, (n, d)) * self.sigma, self.xl, self.xu)
        pick = self.rng.uniform(size=n) < self.explore
        return np.where(pick[:, None], uniform, varied)

    def tell(self, X, F, G) -> None:
        self.X = np.vstack([self.X, X])
        self.F = F if self.F is None else np.vstack([self.F, F])
        self.G = G if self.G is None else np.vstack([self.G, G])
        feasible = np.all(self.G <= 0, axis=1)
        if feasible.any():
            self.archive = np.flatnonzero(non_dominated(self.F, feasible))
        else:
            cv = np.maximum(self.G, 0).sum(axis=1)
            self.archive = np.argsort(cv, kind="stable")[: self.batch_size]
