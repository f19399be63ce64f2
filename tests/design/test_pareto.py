"""Non-dominance against brute force (ties and duplicates included), hypervolume, decision."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from design.decide import choose_design
from design.pareto import EXACT_HV_POINTS, hypervolume, non_dominated


def brute_force_front(F, feasible):
    n = len(F)
    keep = np.zeros(n, bool)
    for i in range(n):
        if not feasible[i]:
            continue
        dominated = False
        for j in range(n):
            if j != i and feasible[j] and all(F[j] <= F[i]) and any(F[j] < F[i]):
                dominated = True
                break
        keep[i] = not dominated
    return keep


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 60), st.integers(1, 7), st.integers(0, 2**31 - 1))
def test_non_dominated_matches_brute_force(n, m, seed):
    rng = np.random.default_rng(seed)
    # Small integer values force ties; repeated rows force duplicates.
    F = rng.integers(0, 4, (n, m)).astype(float)
    if n > 3:
        F[-1] = F[0]
        F[-2] = F[1]
    feasible = rng.uniform(size=n) < 0.8
    np.testing.assert_array_equal(non_dominated(F, feasible), brute_force_front(F, feasible))


def test_duplicates_are_both_kept_and_dominated_removed():
    F = np.array([[1.0, 2.0], [1.0, 2.0], [2.0, 3.0], [0.5, 5.0]])
    np.testing.assert_array_equal(non_dominated(F), [True, True, False, True])


def test_hypervolume_of_a_single_point_is_its_box():
    assert hypervolume(np.array([[0.5, 0.5]]), ref=1.0) == (pytest.approx(0.25), True)
    assert hypervolume(np.zeros((1, 3)), ref=1.1)[0] == pytest.approx(1.1**3)
    assert hypervolume(np.array([[1.2, 0.0]]), ref=1.1) == (0.0, True)     # beyond the reference: nothing


def test_hypervolume_of_two_boxes_and_the_approximation():
    # Two 2D boxes [0.2, 1] x [0.6, 1] and [0.6, 1] x [0.2, 1]: 0.32 + 0.32 - 0.16.
    assert hypervolume(np.array([[0.2, 0.6], [0.6, 0.2]]), ref=1.0)[0] == pytest.approx(0.48)
    rng = np.random.default_rng(3)
    P = rng.dirichlet(np.ones(4), 400)
    P = P[non_dominated(P)][: EXACT_HV_POINTS + 10]
    approx, exact = hypervolume(P, 1.1)
    assert not exact
    assert approx == pytest.approx(hypervolume(P[:EXACT_HV_POINTS], 1.1)[0], rel=0.02)


def test_decision_prefers_the_weighted_criterion():
    F = np.array([[0.0, 1.0], [0.5, 0.5], [1.0, 0.0]])
    assert choose_design(F, "pseudo-weights", [1, 1])[0] == 1
    assert choose_design(F, "pseudo-weights", [1, 0])[0] == 0
    assert choose_design(F, "pseudo-weights", [0, 1])[0] == 2
    # A constant criterion is ignored rather than dividing by zero.
    F3 = np.column_stack([F, np.ones(3)])
    assert choose_design(F3, "pseudo-weights", [1, 1, 1])[0] == 1
    with pytest.raises(ValueError, match="no feasible design"):
        choose_design(np.empty((0, 2)))


def test_knee_point_on_a_convex_front():
    t = np.linspace(0, 1, 41)
    F = np.column_stack([t, (1 - t) ** 8])  # sharp knee near the origin corner
    k, how = choose_design(F, "knee")
    assert "knee" in how
    assert F[k].sum() < 0.5
