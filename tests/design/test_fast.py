"""The batched, compiled evaluation against today's code (kept in reference_criteria.py).

200 random designs of the default sweep: the working volume within 1 % (0.24 % in the median,
0.51 % at most: the last sweep's coarser arcs, kernels.FINAL_STEP), the collision fraction, the
radii and the rest-pose constraints to the bit, the torque criteria to rounding (1e-12 relative;
the kernels sum in another order).
"""

import numpy as np
import pytest

import reference_criteria as RC
from design.batch import arrays_from_head, arrays_from_variables
from design.layout import head_from_variables
from design.problem import EvaluationContext, evaluate_batch, evaluate_design, score_head
from design.sweep_file import CONSTRAINTS, CRITERIA, load_sweep
from kinematics import reference_head


@pytest.fixture(scope="module")
def ctx():
    return EvaluationContext.from_spec(load_sweep())


@pytest.fixture(scope="module")
def designs(ctx):
    X = np.random.default_rng(48).uniform(ctx.spec.xl, ctx.spec.xu, (200, 12))
    F, G = evaluate_batch(X, ctx)
    ref = [RC.reference_score(head_from_variables(x, ctx.spec), ctx) for x in X]
    Fr = np.array([[c[k] for k in CRITERIA] for c, _ in ref])
    Gr = np.array([[g[k] for k in CONSTRAINTS] for _, g in ref])
    return X, F, G, Fr, Gr


def test_volume_within_one_percent(designs):
    _, F, _, Fr, _ = designs
    rel = np.abs(F[:, 0] / Fr[:, 0] - 1)
    assert rel.max() <= 0.01         # the bound (measured: 0.51 %)
    assert np.median(rel) <= 0.005   # measured: 0.24 %; the coarser last sweep only


def test_exact_criteria_to_the_bit(designs):
    _, F, G, Fr, Gr = designs
    np.testing.assert_array_equal(F[:, 1], Fr[:, 1])        # self collision
    assert 0 < np.count_nonzero(Fr[:, 1]) < len(Fr)          # the sample holds both kinds
    np.testing.assert_array_equal(F[:, 4:], Fr[:, 4:])       # radii
    np.testing.assert_array_equal(G[:, 1:], Gr[:, 1:])       # rest penetration, part overlap


def test_torque_criteria_to_rounding(designs):
    _, F, G, Fr, Gr = designs
    np.testing.assert_allclose(F[:, 2:4], Fr[:, 2:4], rtol=1e-12, atol=0)
    np.testing.assert_allclose(G[:, 0], Gr[:, 0], rtol=1e-12, atol=1e-15)


def test_single_design_and_any_head_agree_with_the_batch(ctx, designs):
    X, F, G, _, _ = designs
    f, g = evaluate_design(X[3], ctx)
    np.testing.assert_array_equal(f, F[3])
    crit, cons = score_head(head_from_variables(X[3], ctx.spec), ctx)
    np.testing.assert_allclose(list(crit.values()), F[3], rtol=1e-13)
    np.testing.assert_allclose(list(cons.values()), G[3], rtol=1e-13, atol=1e-16)


def test_reference_head_as_before(ctx):
    head = reference_head()
    crit, cons = score_head(head, ctx)
    rc, rg = RC.reference_score(head, ctx)
    assert crit["working_volume_cm3"] == pytest.approx(rc["working_volume_cm3"], rel=0.01)
    for k in CRITERIA[1:]:
        assert crit[k] == pytest.approx(rc[k], rel=1e-12, abs=1e-15), k
    for k in CONSTRAINTS:
        assert cons[k] == pytest.approx(rg[k], rel=1e-12, abs=1e-15), k


def test_layout_arrays_are_the_heads(ctx, designs):
    X = designs[0][:5]
    A = arrays_from_variables(X, ctx.spec)
    for d, x in enumerate(X):
        B = arrays_from_head(head_from_variables(x, ctx.spec))
        np.testing.assert_array_equal(A.link, B.link)
        np.testing.assert_allclose(A.center[d], B.center[0], rtol=0, atol=1e-15)
        np.testing.assert_allclose(A.mass[d], B.mass[0], rtol=1e-15)
        np.testing.assert_array_equal(A.size[d], B.size[0])
        np.testing.assert_array_equal(A.origin[d], B.origin[0])
        np.testing.assert_array_equal(A.cam[d], B.cam[0])
        np.testing.assert_array_equal(A.lo, B.lo)


def test_surface_picks_the_c_order_sample_from_samples_in_any_order():
    # The pan sweep hands _surface its points in the order kept; the sample it keeps per surface
    # voxel must still be volume._thin's (the last in C order of the half-voxels).
    from design import kernels
    from design.volume import LATTICE_OFFSET, _thin

    rng = np.random.default_rng(5)
    P = rng.normal(size=(3, 30000))
    P *= 0.03 * rng.uniform(size=30000) ** (1 / 3) / np.linalg.norm(P, axis=0)     # a 3 cm ball
    voxel = 0.003
    samples, boundary = _thin(P, voxel)
    shuffled = np.ascontiguousarray(samples[:, rng.permutation(samples.shape[1])])
    h = np.floor(samples * (2 / voxel) - 2 * LATTICE_OFFSET[:, None]).astype(np.int32)    # half-voxels
    got = kernels._surface(shuffled, shuffled.shape[1], h.min(axis=1), h.max(axis=1), 2 / voxel, 2 * LATTICE_OFFSET)
    assert 100 < boundary.shape[1] < samples.shape[1] / 4
    np.testing.assert_array_equal(got, boundary)


def test_unordered_sweep_keeps_the_same_points(ctx):
    from design import kernels
    from design.volume import LATTICE_OFFSET

    X = np.random.default_rng(7).uniform(ctx.spec.xl, ctx.spec.xu, (1, 12))
    A = arrays_from_variables(X, ctx.spec)
    c, s = A.center[0], A.size[0]
    link_c = [np.ascontiguousarray(c[A.link == k]) for k in range(4)]
    link_s = [np.ascontiguousarray(s[A.link == k]) for k in range(4)]
    half, scale2, off2 = ctx.spec.voxel_m / 2, 2 / ctx.spec.voxel_m, 2 * LATTICE_OFFSET
    pts = np.empty((3, kernels._box_count(link_s[3], half)))
    kernels._box_points(link_c[3], link_s[3], half, pts, 0)
    samples, lo_h, hi_h = kernels._thin_points(pts, scale2, off2)
    boundary = kernels._surface(samples, samples.shape[1], lo_h, hi_h, scale2, off2)
    args = (boundary, A.axis[2], A.origin[0, 2], A.lo[2], A.hi[2], half, link_c[2], link_s[2], half, scale2, off2)
    ordered, n, lo, hi = kernels._sweep_thin(samples, samples.shape[1], *args, True)
    kept, m, lo2, hi2 = kernels._sweep_thin(samples, samples.shape[1], *args, False)
    assert n == m > samples.shape[1]
    np.testing.assert_array_equal(lo, lo2)
    np.testing.assert_array_equal(hi, hi2)
    key = lambda Q: Q[:, np.lexsort(Q[::-1])]
    assert not np.array_equal(ordered[:, :n], kept[:, :n])        # the order differs ...
    np.testing.assert_array_equal(key(ordered[:, :n]), key(kept[:, :n]))    # ... the points do not
