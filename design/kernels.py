"""Compiled (numba) kernels behind the criteria: the voxel sweep, the collision grid, the dynamics.

Each kernel computes what the numpy code it replaced computed, in the same order of operations
where the order decides a result (which sample of a half-voxel is kept, which boundary voxels a
sweep reaches), so the criteria keep their meaning and, but for the last bit of a few roundings,
their values (tests/design/test_fast.py checks them against the old code, kept in
tests/design/reference_criteria.py). One exception, by design: the last sweep of the working
volume turns the boundary samples in steps of :data:`FINAL_STEP` voxels instead of half a voxel,
which marks a few tenths of a per cent fewer voxels (the test holds it within 1 %). What is gone
is the numpy cost: no (3, N) temporaries per sweep angle, no sort, no Python loop per part or
pair; sweeps are thinned as they are made, and turns about a lattice axis (every layout's) skip
the coordinate they keep. All kernels are ``cache=True``: the first
run in a fresh environment compiles them (a few seconds), later processes load them from disk.

Units: metres and radians; arrays are C-contiguous float64 unless said otherwise.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba.extending import intrinsic

#: Same values as design.volume (duplicated here so the kernels import nothing else).
RADIUS_BANDS = 8
#: Largest step, in voxels, of a boundary sample between two sweep angles in the last (mount
#: frame) sweep, where design.volume takes half a voxel: its voxels are only counted, so a coarser
#: arc misses a voxel now and then and nothing compounds (0.2 % fewer voxels in the median, 0.5 %
#: at most, on tests/design/test_fast.py's 200 designs); the inner sweeps keep half a voxel, as
#: there a changed sample moves every sweep after it.
FINAL_STEP = 0.7


# --------------------------------------------------------------------------------------------
# Small helpers, written as numpy writes them (see kinematics.chain.axis_angle_matrix)
# --------------------------------------------------------------------------------------------

@njit(cache=True)
def _axis_angle(axis, angle, out):
    """out (3, 3) = I + sin(t) K + (1 - cos(t)) K^2, Rodrigues, as kinematics.chain computes it."""
    x, y, z = axis[0], axis[1], axis[2]
    s = math.sin(angle)
    c1 = 1.0 - math.cos(angle)
    K = ((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0))
    K2 = ((x * x - 1.0, x * y, x * z), (x * y, y * y - 1.0, y * z), (x * z, y * z, z * z - 1.0))
    for r in range(3):
        for c in range(3):
            e = 1.0 if r == c else 0.0
            out[r, c] = (e + s * K[r][c]) + c1 * K2[r][c]


@njit(cache=True)
def _linspace(lo, hi, n, out):
    """out[:n] = np.linspace(lo, hi, n) (same rounding: i * step + lo, last = hi)."""
    if n == 1:
        out[0] = lo
        return
    step = (hi - lo) / (n - 1)
    for i in range(n):
        out[i] = i * step + lo
    out[n - 1] = hi


# --------------------------------------------------------------------------------------------
# Working volume: the hierarchical voxel sweep of design.volume
# --------------------------------------------------------------------------------------------

@njit(cache=True)
def _box_count(sizes, spacing):
    total = 0
    for p in range(sizes.shape[0]):
        n = 1
        for d in range(3):
            n *= int(math.ceil(sizes[p, d] / spacing)) + 1
        total += n
    return total


@njit(cache=True)
def _box_points(centers, sizes, spacing, out, start):
    """Fill out[:, start:] (3, M) with the points of every box (volume._box_points, x-major);
    returns the end."""
    k = start
    nmax = 2
    for p in range(centers.shape[0]):
        for d in range(3):
            nmax = max(nmax, int(math.ceil(sizes[p, d] / spacing)) + 1)
    ax = np.empty((3, nmax))
    ns = np.empty(3, np.int64)
    for p in range(centers.shape[0]):
        for d in range(3):
            n = int(math.ceil(sizes[p, d] / spacing)) + 1
            ns[d] = n
            c, s = centers[p, d], sizes[p, d]
            _linspace(c - s / 2.0, c + s / 2.0, n, ax[d])
        for i in range(ns[0]):
            for j in range(ns[1]):
                for m in range(ns[2]):
                    out[0, k] = ax[0, i]
                    out[1, k] = ax[1, j]
                    out[2, k] = ax[2, m]
                    k += 1
    return k


@njit(cache=True, inline="always")
def _set_bit(bits, c):
    bits[c >> 6] |= np.uint64(1) << np.uint64(c & 63)


@intrinsic
def _ctpop(typingctx, x):
    """Number of set bits of an integer (LLVM's ctpop: one instruction)."""
    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])
    return x(x), codegen


@njit(cache=True)
def _popcount(bits):
    n = 0
    for w in bits:
        n += int(_ctpop(w))
    return n


@njit(cache=True)
def _ranks(bits):
    """(n_words + 1,) number of set bits before each word: a set cell's rank (its position in C
    order among the set cells) is ranks[c >> 6] plus the set bits below it in its word."""
    out = np.zeros(bits.size + 1, np.int64)
    for w in range(bits.size):
        out[w + 1] = out[w] + int(_ctpop(bits[w]))
    return out


@njit(cache=True, inline="always")
def _rank(bits, ranks, c):
    below = bits[c >> 6] & ((np.uint64(1) << np.uint64(c & 63)) - np.uint64(1))
    return ranks[c >> 6] + int(_ctpop(below))


@njit(cache=True, inline="always")
def _strides(lo, d1, d2):
    """A lattice box's C-order strides (d1 * d2, d2, 1) and the cell of its corner ``lo``, as
    floats: a cell computed from floored coordinates in float64 is exact (integers below 2**53),
    and float multiplies vectorise where int64 ones (no AVX2 instruction) do not."""
    s0, s1 = float(d1 * d2), float(d2)
    return s0, s1, lo[0] * s0 + lo[1] * s1 + lo[2]


@njit(cache=True)
def _cells(P, i0, i1, scale, off, lo, d1, d2, out):
    """out[:i1 - i0] = C-order lattice cell of points P[:, i0:i1] (3, N), cells of edge 1 / scale
    offset by ``off`` cells, relative to the box corner ``lo``. A loop the compiler vectorises
    (0-based over contiguous slices: indexing from i0 keeps it scalar)."""
    f0, f1, f2 = off[0], off[1], off[2]
    s0, s1, base = _strides(lo, d1, d2)
    X, Y, Z = P[0, i0:i1], P[1, i0:i1], P[2, i0:i1]
    for i in range(i1 - i0):
        a = np.floor(X[i] * scale - f0)
        b = np.floor(Y[i] * scale - f1)
        c = np.floor(Z[i] * scale - f2)
        out[i] = np.int32(((a * s0 + b * s1) + c) - base)


@njit(cache=True)
def _turned_cells(R, origin, P, i0, i1, scale, off, lo, d1, d2, out):
    """out[:i1 - i0] = lattice cells of R @ P[:, i0:i1] + origin (without storing the points)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2],
                                                   R[2, 0], R[2, 1], R[2, 2])
    o0, o1, o2 = origin[0], origin[1], origin[2]
    f0, f1, f2 = off[0], off[1], off[2]
    s0, s1, base = _strides(lo, d1, d2)
    X, Y, Z = P[0, i0:i1], P[1, i0:i1], P[2, i0:i1]
    for i in range(i1 - i0):
        x, y, z = X[i], Y[i], Z[i]
        a = np.floor((((r00 * x + r01 * y) + r02 * z) + o0) * scale - f0)
        b = np.floor((((r10 * x + r11 * y) + r12 * z) + o1) * scale - f1)
        c = np.floor((((r20 * x + r21 * y) + r22 * z) + o2) * scale - f2)
        out[i] = np.int32(((a * s0 + b * s1) + c) - base)


@njit(cache=True)
def _aligned_axis(axis):
    """j if ``axis`` is +-e_j exactly (a layout's joints are), else -1."""
    for j in range(3):
        if abs(axis[j]) == 1.0 and axis[(j + 1) % 3] == 0.0 and axis[(j + 2) % 3] == 0.0:
            return j
    return -1


@njit(cache=True)
def _fixed_cells(P, n, j, origin, scale, off, lo, d1, d2, out):
    """out[i] = the coordinate j's share of the C-order cell of P[:, i] + origin, i < n (a turn
    about e_j keeps that coordinate: row j of _axis_angle's matrix is e_j exactly)."""
    stride = d1 * d2 if j == 0 else (d2 if j == 1 else 1)
    for i in range(n):
        out[i] = (np.int32(np.floor((P[j, i] + origin[j]) * scale - off[j])) - lo[j]) * stride


@njit(cache=True)
def _turned_cells_aligned(R, j, origin, P, fixed, i0, i1, scale, off, lo, d1, d2, out):
    """_turned_cells for a turn about +-e_j, from the cell shares ``fixed`` of coordinate j: the
    same cells (R's row j is e_j, its column j zeros, so each other coordinate is the same two
    products summed in the same order)."""
    u, w = (1, 2) if j == 0 else ((0, 2) if j == 1 else (0, 1))
    su = float(d1 * d2) if u == 0 else float(d2)
    sw = float(d2) if w == 1 else 1.0
    ruu, ruw, rwu, rww = R[u, u], R[u, w], R[w, u], R[w, w]
    ou, ow = origin[u], origin[w]
    fu, fw = off[u], off[w]
    base = lo[u] * su + lo[w] * sw
    U, V, F = P[u, i0:i1], P[w, i0:i1], fixed[i0:i1]
    for i in range(i1 - i0):
        x, y = U[i], V[i]
        a = np.floor(((ruu * x + ruw * y) + ou) * scale - fu)
        c = np.floor(((rwu * x + rww * y) + ow) * scale - fw)
        out[i] = np.int32((a * su + c * sw) - base) + F[i]


@njit(cache=True)
def _turn_cells_into(R, j, origin, P, i0, i1, scale, off, lo, d1, d2, buf, cell):
    """buf[:, :i1 - i0] = R @ P[:, i0:i1] + origin (volume._turn) and cell[:i1 - i0] their C-order
    cells (_cells), in one pass; for a turn about +-e_j (j >= 0) coordinate j is P[j] + origin[j]
    and the others two products each (the same values: R's row j is e_j, its column j zeros)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2],
                                                   R[2, 0], R[2, 1], R[2, 2])
    o0, o1, o2 = origin[0], origin[1], origin[2]
    f0, f1, f2 = off[0], off[1], off[2]
    s0, s1, base = _strides(lo, d1, d2)
    X, Y, Z = P[0, i0:i1], P[1, i0:i1], P[2, i0:i1]
    B0, B1, B2 = buf[0], buf[1], buf[2]
    for i in range(i1 - i0):
        x, y, z = X[i], Y[i], Z[i]
        if j == 0:
            u, v, w = x + o0, (r11 * y + r12 * z) + o1, (r21 * y + r22 * z) + o2
        elif j == 1:
            u, v, w = (r00 * x + r02 * z) + o0, y + o1, (r20 * x + r22 * z) + o2
        elif j == 2:
            u, v, w = (r00 * x + r01 * y) + o0, (r10 * x + r11 * y) + o1, z + o2
        else:
            u, v, w = ((r00 * x + r01 * y) + r02 * z) + o0, ((r10 * x + r11 * y) + r12 * z) + o1, ((r20 * x + r21 * y) + r22 * z) + o2
        B0[i], B1[i], B2[i] = u, v, w
        a = np.floor(u * scale - f0)
        b = np.floor(v * scale - f1)
        c = np.floor(w * scale - f2)
        cell[i] = np.int32(((a * s0 + b * s1) + c) - base)


@njit(cache=True)
def _sweep_plan(boundary, axis, lo, hi, max_step):
    """The boundary samples (3, B) grouped by radius band (3, B), where each band starts in them
    (RADIUS_BANDS + 1,), and each band's angle count (RADIUS_BANDS,), as volume._sweep."""
    B = boundary.shape[1]
    radius = np.empty(B)
    r_max = 0.0
    for i in range(B):
        ap = axis[0] * boundary[0, i] + axis[1] * boundary[1, i] + axis[2] * boundary[2, i]
        s = 0.0
        for d in range(3):
            v = boundary[d, i] - axis[d] * ap
            s += v * v
        radius[i] = math.sqrt(s)
        r_max = max(r_max, radius[i])
    band = np.zeros(B, np.int64)
    counts = np.zeros(RADIUS_BANDS, np.int64)
    if r_max > 0.0:
        f = RADIUS_BANDS / r_max
        for i in range(B):
            band[i] = min(int(radius[i] * f), RADIUS_BANDS - 1)
        for b in range(RADIUS_BANDS):
            counts[b] = int(math.ceil((hi - lo) * r_max * (b + 1) / RADIUS_BANDS / max_step)) + 1
    # The boundary samples grouped by band, each group in the samples' order (boundary[:, band == b]).
    start = np.zeros(RADIUS_BANDS + 1, np.int64)
    for i in range(B):
        start[band[i] + 1] += 1
    for b in range(RADIUS_BANDS):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    members = np.empty((3, B))
    for i in range(B):
        for d in range(3):
            members[d, fill[band[i]]] = boundary[d, i]
        fill[band[i]] += 1
    return members, start, counts


@njit(cache=True)
def _turn_extent(P, n, axis):
    """The cylinder about ``axis`` (through the frame's origin) that holds the points P[:, :n]
    and every turn of them: their least and greatest axial coordinates and largest radius."""
    a_min, a_max, rr = np.inf, -np.inf, 0.0
    for i in range(n):
        ap = axis[0] * P[0, i] + axis[1] * P[1, i] + axis[2] * P[2, i]
        s = 0.0
        for d in range(3):
            v = P[d, i] - axis[d] * ap
            s += v * v
        a_min, a_max, rr = min(a_min, ap), max(a_max, ap), max(rr, s)
    return a_min, a_max, math.sqrt(rr)


@njit(cache=True)
def _turn_bounds(P, n, axis, origin, scale, off, lo_i, hi_i):
    """Widen the lattice box [lo_i, hi_i] (cells of edge 1 / scale) to hold every turn of the
    points P[:, :n] about ``axis`` (through the frame's origin), shifted by ``origin``: the
    cylinder about the axis that holds them (axial extent kept, radius kept)."""
    if n == 0:
        return
    a_min, a_max, rr = _turn_extent(P, n, axis)
    for d in range(3):
        ext = rr * math.sqrt(max(1.0 - axis[d] * axis[d], 0.0))
        x0 = origin[d] + min(axis[d] * a_min, axis[d] * a_max) - ext
        x1 = origin[d] + max(axis[d] * a_min, axis[d] * a_max) + ext
        lo_i[d] = min(lo_i[d], np.int32(math.floor(x0 * scale - off[d])) - 1)
        hi_i[d] = max(hi_i[d], np.int32(math.floor(x1 * scale - off[d])) + 1)


@njit(cache=True)
def _point_bounds(P, n, scale, off, lo_i, hi_i):
    """Widen the lattice box [lo_i, hi_i] to hold the points P[:, :n]."""
    for d in range(3):
        for i in range(n):
            c = np.int32(math.floor(P[d, i] * scale - off[d]))
            lo_i[d] = min(lo_i[d], c - 1)
            hi_i[d] = max(hi_i[d], c + 1)


@njit(cache=True)
def _band_angles(counts, b, lo, hi, ang):
    """Angles strictly between the ends for band b; returns how many (0 if none)."""
    n = counts[b]
    if n <= 2:
        return 0
    _linspace(lo, hi, n, ang)
    return n - 2


@njit(cache=True)
def _keep_new(buf, m, cell, bits, out, kept, K):
    """Append to out[:, K:] (their cells to kept[K:], unless kept is empty) the points buf[:, :m]
    whose half-voxel is not yet marked, marking it, taken last to first: each half-voxel keeps
    the last point made in it, as volume._thin keeps it. Returns the new K."""
    # Branch-free: every point is written at K, which moves on only for a new cell.
    one = np.uint64(1)
    record = kept.size > 0
    for i in range(m - 1, -1, -1):
        c = cell[i]
        word = bits[c >> 6]
        bit = one << np.uint64(c & 63)
        bits[c >> 6] = word | bit
        out[0, K] = buf[0, i]
        out[1, K] = buf[1, i]
        out[2, K] = buf[2, i]
        if record:
            kept[K] = c
        K += int((word & bit) == np.uint64(0))
    return K


@njit(cache=True)
def _in_cell_order(out, kept, K, bits):
    """The kept points out[:, :K] (cells kept[:K], marked in bits) in C order of their cells."""
    ranks = _ranks(bits)
    res = np.empty((3, K))
    for k in range(K):
        r = _rank(bits, ranks, kept[k])
        res[0, r] = out[0, k]
        res[1, r] = out[1, k]
        res[2, r] = out[2, k]
    return res


@njit(cache=True)
def _thin_points(P, scale2, off2):
    """One exact point per occupied half-voxel of the points P (3, M), the last made in it, in C
    order of the half-voxels (volume._thin's samples), and the box of half-voxel cells
    [lo_i, hi_i] (3,) each that holds them."""
    lo_i = np.full(3, 2**30, np.int32)
    hi_i = np.full(3, -2**30, np.int32)
    M = P.shape[1]
    _point_bounds(P, M, scale2, off2, lo_i, hi_i)
    if M == 0:
        return P[:, :0].copy(), lo_i, hi_i
    d1, d2 = hi_i[1] - lo_i[1] + 1, hi_i[2] - lo_i[2] + 1
    bits = np.zeros(((hi_i[0] - lo_i[0] + 1) * d1 * d2) // 64 + 1, np.uint64)
    cell = np.empty(M, np.int32)
    _cells(P, 0, M, scale2, off2, lo_i, d1, d2, cell)
    out = np.empty((3, M))
    kept = np.empty(M, np.int32)
    K = _keep_new(P, M, cell, bits, out, kept, 0)
    return _in_cell_order(out, kept, K, bits), lo_i, hi_i


@njit(cache=True)
def _sweep_thin(samples, S, boundary, axis, origin, lo, hi, max_step, box_c, box_s, spacing, scale2, off2,
                ordered):
    """volume._thin of volume._sweep's points and the parent's boxes, parent frame: the samples
    samples[:, :S] turned to both ends of the joint's range, the boundary samples (3, B) to the
    angles between, the boxes, thinned as they are made (one rotation's points in memory at a
    time, no sort). Returns (P, K, lo_i, hi_i): the kept points are P[:, :K], inside the box
    of half-voxel cells [lo_i, hi_i] (3,) each, one per half-voxel, in C order
    of their half-voxels if ``ordered`` (as volume._thin has them; a sweep that thins them again
    needs that order), else in the order kept (enough for _surface and _count_final, which do
    not depend on it)."""
    members, start, counts = _sweep_plan(boundary, axis, lo, hi, max_step)
    boxes = np.empty((3, _box_count(box_s, spacing)))
    _box_points(box_c, box_s, spacing, boxes, 0)
    lo_i = np.full(3, 2**30, np.int32)
    hi_i = np.full(3, -2**30, np.int32)
    _turn_bounds(samples, S, axis, origin, scale2, off2, lo_i, hi_i)
    _point_bounds(boxes, boxes.shape[1], scale2, off2, lo_i, hi_i)
    if hi_i[0] < lo_i[0]:
        return boxes, 0, lo_i, hi_i
    d0, d1, d2 = hi_i[0] - lo_i[0] + 1, hi_i[1] - lo_i[1] + 1, hi_i[2] - lo_i[2] + 1
    if np.int64(d0) * d1 * d2 >= 2**31:
        raise ValueError("the voxel lattice exceeds 2**31 cells: raise [criteria].voxel_m")
    total = 2 * S + boxes.shape[1]
    for b in range(RADIUS_BANDS):
        if counts[b] > 2:
            total += (counts[b] - 2) * (start[b + 1] - start[b])
    total = min(total, d0 * d1 * d2 + 1)    # + 1: the branch-free keep writes one past the kept points
    bits = np.zeros((d0 * d1 * d2) // 64 + 1, np.uint64)
    out = np.empty((3, total))
    kept = np.empty(total if ordered else 0, np.int32)     # the cells, for putting them in order
    m_max = max(S, boundary.shape[1], boxes.shape[1])
    buf = np.empty((3, m_max))
    cell = np.empty(m_max, np.int32)
    R = np.empty((3, 3))
    j = _aligned_axis(axis)
    K = 0
    # Made in reverse of volume._sweep's order (ends, arcs by band and angle, boxes) and kept at
    # first reach: each half-voxel keeps the point that order makes last.
    _cells(boxes, 0, boxes.shape[1], scale2, off2, lo_i, d1, d2, cell)
    K = _keep_new(boxes, boxes.shape[1], cell, bits, out, kept, K)
    ang = np.empty(int(counts.max()) + 2)
    for b in range(RADIUS_BANDS - 1, -1, -1):
        m = start[b + 1] - start[b]
        n = _band_angles(counts, b, lo, hi, ang)
        for a in range(n, 0, -1):
            _axis_angle(axis, ang[a], R)
            _turn_cells_into(R, j, origin, members, start[b], start[b + 1], scale2, off2, lo_i, d1, d2, buf, cell)
            K = _keep_new(buf, m, cell, bits, out, kept, K)
    for end in (hi, lo):
        _axis_angle(axis, end, R)
        _turn_cells_into(R, j, origin, samples, 0, S, scale2, off2, lo_i, d1, d2, buf, cell)
        K = _keep_new(buf, S, cell, bits, out, kept, K)
    if ordered:
        return _in_cell_order(out, kept, K, bits), K, lo_i, hi_i
    return out, K, lo_i, hi_i


@njit(cache=True)
def _surface(samples, S, lo_h, hi_h, scale2, off2):
    """One sample per surface voxel (3, B) of the thinned samples samples[:, :S] (one per
    half-voxel, in any order, all in the box of half-voxel cells [lo_h, hi_h] (3,) each), in C
    order of the voxels: a voxel's sample in its last half-voxel in C order (volume._thin's
    choice, whose samples are in that order), a surface voxel an occupied one with an empty
    face neighbour (volume._thin's boundary)."""
    if S == 0:
        return samples[:, :0].copy()
    if S >= 2**27:
        raise ValueError("more than 2**27 samples: raise [criteria].voxel_m")
    lo = (lo_h >> 1) - 1          # voxels, with an empty border: every neighbour is in the box
    hi = (hi_h >> 1) + 1
    e0, e1 = hi[0] - lo[0] + 1, hi[1] - lo[1] + 1
    W = (hi[2] - lo[2]) // 64 + 1        # rows padded to whole words
    if np.int64(e0) * e1 * W * 64 >= 2**31:
        raise ValueError("the voxel lattice exceeds 2**31 cells: raise [criteria].voxel_m")
    # Each sample's voxel cell and place in the voxel (bits x, y, z of its half-voxel index), in
    # float so the loop vectorises: floor(h / 2) is the voxel, h - 2 floor(h / 2) the bit, exact.
    cell = np.empty(S, np.int32)
    place = np.empty(S, np.int32)
    s0, s1 = float(e1 * 64 * W), float(64 * W)
    corner = lo[0] * s0 + lo[1] * s1 + lo[2]
    f0, f1, f2 = off2[0], off2[1], off2[2]
    X, Y, Z = samples[0, :S], samples[1, :S], samples[2, :S]
    for i in range(S):
        hx, hy, hz = np.floor(X[i] * scale2 - f0), np.floor(Y[i] * scale2 - f1), np.floor(Z[i] * scale2 - f2)
        vx, vy, vz = np.floor(hx * 0.5), np.floor(hy * 0.5), np.floor(hz * 0.5)
        cell[i] = np.int32(((vx * s0 + vy * s1) + vz) - corner)
        place[i] = np.int32(((hx - 2.0 * vx) * 4.0 + (hy - 2.0 * vy) * 2.0) + (hz - 2.0 * vz))
    bits = np.zeros(e0 * e1 * W, np.uint64)
    for i in range(S):
        _set_bit(bits, cell[i])
    # Surface voxels by word-wide bit operations: interior if it and its six neighbours are set.
    surf = np.zeros_like(bits)
    row = e1 * W
    zero = np.uint64(0)
    one = np.uint64(1)
    s63 = np.uint64(63)
    for a in range(1, e0 - 1):
        for b in range(1, e1 - 1):
            base = (a * e1 + b) * W
            for w in range(W):
                k = base + w
                occ = bits[k]
                if occ == zero:
                    continue
                before = bits[k - 1] >> s63 if w > 0 else zero
                after = bits[k + 1] << s63 if w < W - 1 else zero
                inner = (occ & bits[k - row] & bits[k + row] & bits[k - W] & bits[k + W]
                         & ((occ << one) | before) & ((occ >> one) | after))
                surf[k] = occ & ~inner
    # Each surface voxel's sample, by the voxel's rank among them (so in C order): the one whose
    # place in the voxel (bits x, y, z of its half-voxel) is greatest, the place in the key's
    # high bits, the index in its low 27.
    ranks = _ranks(surf)
    B = ranks[-1]
    best = np.full(B, -1, np.int32)
    for i in range(S):
        c = cell[i]
        if surf[c >> 6] & (one << np.uint64(c & 63)):
            r = _rank(surf, ranks, c)
            key = (place[i] << 27) | i
            best[r] = max(best[r], key)
    out = np.empty((3, B))
    low = (1 << 27) - 1
    for r in range(B):
        i = best[r] & low
        out[0, r] = samples[0, i]
        out[1, r] = samples[1, i]
        out[2, r] = samples[2, i]
    return out


@njit(cache=True)
def _count_final(samples, S, x0, x1, boundary, axis, origin, lo, hi, max_step, box_c, box_s, spacing, scale1,
                 off1):
    """Voxels (mount lattice) holding a point of the last sweep (of the samples samples[:, :S],
    which lie in the box [x0, x1] (3,) each, metres, and of the boundary samples (3, B)) or of
    the mount's boxes.

    The points are marked as they are made, never stored: the lattice box is bounded in
    advance by the cylinder about the joint axis that holds every turn of the box [x0, x1]
    (padded by a voxel against rounding), which changes the array, not the count.
    """
    members, start, counts = _sweep_plan(boundary, axis, lo, hi, max_step)
    boxes = np.empty((3, _box_count(box_s, spacing)))
    _box_points(box_c, box_s, spacing, boxes, 0)
    # Bound of the turned points: axial coordinate kept, radius kept; a box's farthest point
    # from a line and its extremes along it are corners, so its 8 corners bound every sample.
    corners = np.empty((3, 8))
    for k in range(8):
        for d in range(3):
            corners[d, k] = x1[d] if (k >> d) & 1 else x0[d]
    a_min, a_max, rr = _turn_extent(corners, 8, axis)
    lo_i = np.empty(3, np.int32)
    hi_i = np.empty(3, np.int32)
    for d in range(3):
        ext = rr * math.sqrt(max(1.0 - axis[d] * axis[d], 0.0))
        x0 = origin[d] + min(axis[d] * a_min, axis[d] * a_max) - ext if S else np.inf
        x1 = origin[d] + max(axis[d] * a_min, axis[d] * a_max) + ext if S else -np.inf
        for i in range(boxes.shape[1]):
            x0, x1 = min(x0, boxes[d, i]), max(x1, boxes[d, i])
        lo_i[d] = np.int32(math.floor(x0 * scale1 - off1[d])) - 1
        hi_i[d] = np.int32(math.floor(x1 * scale1 - off1[d])) + 1
    d1, d2 = hi_i[1] - lo_i[1] + 1, hi_i[2] - lo_i[2] + 1
    if (hi_i[0] - lo_i[0] + 1) * d1 * d2 >= 2**31:
        raise ValueError("the voxel lattice exceeds 2**31 cells: raise [criteria].voxel_m")
    # A byte per voxel: a plain store per point, where a bit costs a load, a shift and an OR.
    occ = np.zeros((hi_i[0] - lo_i[0] + 1) * d1 * d2, np.uint8)
    R = np.empty((3, 3))
    cell = np.empty(max(S, boundary.shape[1], boxes.shape[1]), np.int32)
    ang = np.empty(int(counts.max()) + 2)
    j = _aligned_axis(axis)
    fixed_s = np.empty(S, np.int32)
    fixed_m = np.empty(members.shape[1], np.int32)
    if j >= 0:
        _fixed_cells(samples, S, j, origin, scale1, off1, lo_i, d1, d2, fixed_s)
        _fixed_cells(members, members.shape[1], j, origin, scale1, off1, lo_i, d1, d2, fixed_m)
    for end in (lo, hi):
        _axis_angle(axis, end, R)
        if j >= 0:
            _turned_cells_aligned(R, j, origin, samples, fixed_s, 0, S, scale1, off1, lo_i, d1, d2, cell)
        else:
            _turned_cells(R, origin, samples, 0, S, scale1, off1, lo_i, d1, d2, cell)
        for i in range(S):
            occ[cell[i]] = 1
    for b in range(RADIUS_BANDS):
        n = counts[b]
        m = start[b + 1] - start[b]
        if n > 2 and m > 0:
            _linspace(lo, hi, n, ang)
            for a in range(1, n - 1):
                _axis_angle(axis, ang[a], R)
                if j >= 0:
                    _turned_cells_aligned(R, j, origin, members, fixed_m, start[b], start[b + 1], scale1, off1, lo_i,
                                          d1, d2, cell)
                else:
                    _turned_cells(R, origin, members, start[b], start[b + 1], scale1, off1, lo_i, d1, d2, cell)
                for i in range(m):
                    occ[cell[i]] = 1
    _cells(boxes, 0, boxes.shape[1], scale1, off1, lo_i, d1, d2, cell)
    for i in range(boxes.shape[1]):
        occ[cell[i]] = 1
    n = 0
    for v in occ:
        n += v
    return n


@njit(cache=True)
def swept_voxels(link_c, link_s, joint_axis, joint_origin, joint_lo, joint_hi, voxel_m, offset):
    """Occupied voxel count of the hierarchical voxel sweep (design.volume's method).

    link_c, link_s : tuples of 4 (n_L, 3) arrays, the part boxes' centres and sizes in the frame
        of each link (mount, elevation, pan, cyclotorsion), metres.
    joint_axis, joint_origin : (3, 3) joint k's unit axis and origin in link k's frame.
    joint_lo, joint_hi : (3,) joint ranges, radians.
    voxel_m : voxel edge, metres. offset : (3,) volume.LATTICE_OFFSET.
    """
    half = voxel_m / 2.0
    scale2 = 2 / voxel_m
    off2 = 2 * offset
    pts = np.empty((3, _box_count(link_s[3], half)))
    _box_points(link_c[3], link_s[3], half, pts, 0)
    samples, lo_i, hi_i = _thin_points(pts, scale2, off2)
    S = samples.shape[1]
    for k in (2, 1):
        # The pan sweep's points (k = 1) are only counted and surfaced, which needs no order.
        boundary = _surface(samples, S, lo_i, hi_i, scale2, off2)
        samples, S, lo_i, hi_i = _sweep_thin(samples, S, boundary, joint_axis[k], joint_origin[k], joint_lo[k],
                                             joint_hi[k], half, link_c[k], link_s[k], half, scale2, off2, k == 2)
    # The pan sweep's lattice box (its cells padded by one each way) in metres: the samples' bound.
    x0 = (lo_i + off2) / scale2
    x1 = (hi_i + 1 + off2) / scale2
    boundary = _surface(samples, S, lo_i, hi_i, scale2, off2)
    return _count_final(samples, S, x0, x1, boundary, joint_axis[0], joint_origin[0], joint_lo[0], joint_hi[0],
                        FINAL_STEP * voxel_m, link_c[0], link_s[0], half, 1 / voxel_m, 1 * offset)


# --------------------------------------------------------------------------------------------
# Self collision: oriented-box overlap (separating-axis theorem) over the posture grid
# --------------------------------------------------------------------------------------------

@njit(cache=True)
def _matmul3(A, B, out):
    for r in range(3):
        for c in range(3):
            out[r, c] = A[r, 0] * B[0, c] + A[r, 1] * B[1, c] + A[r, 2] * B[2, c]


@njit(cache=True)
def obb_penetration(cA, RA, hA, cB, RB, hB):
    """design.collision.obb_penetration for one pair of boxes (same formulas, scalar)."""
    C = np.empty((3, 3))
    absC = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = RA[0, i] * RB[0, j] + RA[1, i] * RB[1, j] + RA[2, i] * RB[2, j]
            absC[i, j] = abs(C[i, j])
    d = np.empty(3)
    for k in range(3):
        d[k] = cB[k] - cA[k]
    t = np.empty(3)
    for i in range(3):
        t[i] = RA[0, i] * d[0] + RA[1, i] * d[1] + RA[2, i] * d[2]
    best = np.inf
    for i in range(3):
        best = min(best, hA[i] + (absC[i, 0] * hB[0] + absC[i, 1] * hB[1] + absC[i, 2] * hB[2]) - abs(t[i]))
    for j in range(3):
        tB = C[0, j] * t[0] + C[1, j] * t[1] + C[2, j] * t[2]
        best = min(best, (absC[0, j] * hA[0] + absC[1, j] * hA[1] + absC[2, j] * hA[2]) + hB[j] - abs(tB))
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            norm = math.sqrt(C[i1, j] ** 2 + C[i2, j] ** 2)
            if norm < 1e-6:   # collision.PARALLEL_TOL
                continue
            rA = hA[i1] * absC[i2, j] + hA[i2] * absC[i1, j]
            rB = hB[j1] * absC[i, j2] + hB[j2] * absC[i, j1]
            dist = abs(t[i2] * C[i1, j] - t[i1] * C[i2, j])
            best = min(best, (rA + rB - dist) / norm)
    return best


@njit(cache=True)
def _link_step(i, origin, Rq, R_out, p_out):
    """Link i + 1's origin and rotation from link i's, its joint's origin and turn Rq (3, 3)."""
    for r in range(3):
        p_out[i + 1, r] = p_out[i, r] + (R_out[i, r, 0] * origin[i, 0] + R_out[i, r, 1] * origin[i, 1]
                                         + R_out[i, r, 2] * origin[i, 2])
    _matmul3(R_out[i], Rq, R_out[i + 1])


@njit(cache=True)
def _mount_link(R_out, p_out):
    """Link 0, the mount: no turn, at the origin."""
    for r in range(3):
        for c in range(3):
            R_out[0, r, c] = 1.0 if r == c else 0.0
        p_out[0, r] = 0.0


@njit(cache=True)
def _pose_links(axis, origin, q, R_out, p_out):
    """Link rotations (4, 3, 3) and origins (4, 3) in the mount frame at angles q (3,), link 0 the
    mount (kinematics.chain.forward_kinematics)."""
    Rq = np.empty((3, 3))
    _mount_link(R_out, p_out)
    for i in range(3):
        _axis_angle(axis[i], q[i], Rq)
        _link_step(i, origin, Rq, R_out, p_out)


@njit(cache=True)
def _pose_links_grid(origin, Rg, u, v, w, R_out, p_out):
    """_pose_links at the grid angles (u, v, w), from the joints' rotations Rg (3, steps, 3, 3)
    at the grid angles, made once (the same matrices _axis_angle makes there)."""
    _mount_link(R_out, p_out)
    for i in range(3):
        _link_step(i, origin, Rg[i, u if i == 0 else (v if i == 1 else w)], R_out, p_out)


@njit(cache=True)
def _posed(R_links, p_links, link, center, out_c, out_R):
    for r in range(3):
        out_c[r] = (R_links[link, r, 0] * center[0] + R_links[link, r, 1] * center[1]
                    + R_links[link, r, 2] * center[2]) + p_links[link, r]
        for c in range(3):
            out_R[r, c] = R_links[link, r, c]


@njit(cache=True)
def collision_count(axis, origin, lo, hi, steps, part_link, part_center, part_half, pairs):
    """Postures of the steps**3 grid (collision.posture_grid) at which a pair (K, 2) of parts
    intersects; design.collision.collision_grid's sub-grid shortcut (a pair of links a < b
    depends on joints a .. b-1 only)."""
    grid = np.empty((3, steps))
    for k in range(3):
        _linspace(lo[k], hi[k], steps, grid[k])
    hit = np.zeros((steps, steps, steps), np.bool_)
    Rg = np.empty((3, steps, 3, 3))
    for k in range(3):
        for u in range(steps):
            _axis_angle(axis[k], grid[k, u], Rg[k, u])
    R_links = np.empty((4, 3, 3))
    p_links = np.empty((4, 3))
    cA, cB = np.empty(3), np.empty(3)
    RA, RB = np.empty((3, 3)), np.empty((3, 3))
    n = np.empty(3, np.int64)
    for k in range(pairs.shape[0]):
        i, j = pairs[k, 0], pairs[k, 1]
        a, b = min(part_link[i], part_link[j]), max(part_link[i], part_link[j])
        for m in range(3):
            n[m] = steps if a <= m < b else 1
        for u in range(n[0]):
            for v in range(n[1]):
                for w in range(n[2]):
                    _pose_links_grid(origin, Rg, u, v, w, R_links, p_links)
                    _posed(R_links, p_links, part_link[i], part_center[i], cA, RA)
                    _posed(R_links, p_links, part_link[j], part_center[j], cB, RB)
                    if obb_penetration(cA, RA, part_half[i], cB, RB, part_half[j]) > 0.0:
                        _fill_hit(hit, u, v, w, n)
    c = 0
    for u in range(steps):
        for v in range(steps):
            for w in range(steps):
                c += hit[u, v, w]
    return c


@njit(cache=True)
def _fill_hit(hit, u, v, w, n):
    """Mark the postures a sub-grid sample stands for (every value of the joints held fixed)."""
    steps = hit.shape[0]
    u0, u1 = (0, steps) if n[0] == 1 else (u, u + 1)
    v0, v1 = (0, steps) if n[1] == 1 else (v, v + 1)
    w0, w1 = (0, steps) if n[2] == 1 else (w, w + 1)
    for uu in range(u0, u1):
        for vv in range(v0, v1):
            for ww in range(w0, w1):
                hit[uu, vv, ww] = True


@njit(cache=True)
def rest_penetration_max(axis, origin, part_link, part_center, part_half, pairs):
    """Largest penetration over pairs (K, 2) at q = 0, metres (-inf without pairs)."""
    R_links = np.empty((4, 3, 3))
    p_links = np.empty((4, 3))
    _pose_links(axis, origin, np.zeros(3), R_links, p_links)
    cA, cB = np.empty(3), np.empty(3)
    RA, RB = np.empty((3, 3)), np.empty((3, 3))
    best = -np.inf
    for k in range(pairs.shape[0]):
        i, j = pairs[k, 0], pairs[k, 1]
        _posed(R_links, p_links, part_link[i], part_center[i], cA, RA)
        _posed(R_links, p_links, part_link[j], part_center[j], cB, RB)
        best = max(best, obb_penetration(cA, RA, part_half[i], cB, RB, part_half[j]))
    return best


# --------------------------------------------------------------------------------------------
# Dynamics: recursive Newton-Euler over a fixed workload (kinematics.dynamics.inverse_dynamics)
# --------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True)
def workload_torques(R, z, W, DW, wl, dwl, a_base, qdd, origin, mass, com, inertia, armature, tau):
    """Joint torques tau (T, 3), N m, of one design over a workload of T samples.

    Everything that does not depend on where the parts are is precomputed once per sweep
    (design.batch.DynamicsPlan): R (T, 3, 3, 3) link rotations, z (T, 3, 3) joint axes, W and
    DW (T, 4, 3) angular velocity and acceleration of the mount (0) and of each link after its
    joint, wl and dwl (T, 3, 3) the links' own in link axes, a_base (T, 3) the mount's
    acceleration minus gravity, all in the mount frame. The design gives origin (3, 3) joint
    origins in the parent frames, and per link mass (3,), com (3, 3) in the link frame,
    inertia (3, 3, 3) about the centre of mass in link axes; armature (3,) kg m^2.
    The link inertia is applied in link axes (R (I (R^T w))), not as R I R^T: equal to
    rounding, cheaper.
    """
    T = R.shape[0]
    F = np.empty((3, 3))
    N = np.empty((3, 3))
    Cc = np.empty((3, 3))
    o = np.empty((4, 3))
    for t in range(T):
        for r in range(3):
            o[0, r] = 0.0
        for i in range(3):
            for r in range(3):
                if i == 0:
                    o[1, r] = origin[0, r]
                else:
                    o[i + 1, r] = o[i, r] + (R[t, i - 1, r, 0] * origin[i, 0] + R[t, i - 1, r, 1] * origin[i, 1]
                                             + R[t, i - 1, r, 2] * origin[i, 2])
        a0, a1, a2 = a_base[t, 0], a_base[t, 1], a_base[t, 2]
        for i in range(3):
            r0, r1, r2 = o[i + 1, 0] - o[i, 0], o[i + 1, 1] - o[i, 1], o[i + 1, 2] - o[i, 2]
            w0, w1, w2 = W[t, i, 0], W[t, i, 1], W[t, i, 2]
            x0, x1, x2 = _cross(DW[t, i, 0], DW[t, i, 1], DW[t, i, 2], r0, r1, r2)
            y0, y1, y2 = _cross(w0, w1, w2, r0, r1, r2)
            y0, y1, y2 = _cross(w0, w1, w2, y0, y1, y2)
            a0, a1, a2 = a0 + x0 + y0, a1 + x1 + y1, a2 + x2 + y2
            w0, w1, w2 = W[t, i + 1, 0], W[t, i + 1, 1], W[t, i + 1, 2]
            d0, d1, d2 = DW[t, i + 1, 0], DW[t, i + 1, 1], DW[t, i + 1, 2]
            c0 = R[t, i, 0, 0] * com[i, 0] + R[t, i, 0, 1] * com[i, 1] + R[t, i, 0, 2] * com[i, 2]
            c1 = R[t, i, 1, 0] * com[i, 0] + R[t, i, 1, 1] * com[i, 1] + R[t, i, 1, 2] * com[i, 2]
            c2 = R[t, i, 2, 0] * com[i, 0] + R[t, i, 2, 1] * com[i, 1] + R[t, i, 2, 2] * com[i, 2]
            x0, x1, x2 = _cross(d0, d1, d2, c0, c1, c2)
            y0, y1, y2 = _cross(w0, w1, w2, c0, c1, c2)
            y0, y1, y2 = _cross(w0, w1, w2, y0, y1, y2)
            m = mass[i]
            F[i, 0], F[i, 1], F[i, 2] = m * (a0 + x0 + y0), m * (a1 + x1 + y1), m * (a2 + x2 + y2)
            # Euler's equation in link axes: I dw' + w' x I w', then back to the mount frame.
            I = inertia[i]
            u0, u1, u2 = wl[t, i, 0], wl[t, i, 1], wl[t, i, 2]
            v0, v1, v2 = dwl[t, i, 0], dwl[t, i, 1], dwl[t, i, 2]
            iw0 = I[0, 0] * u0 + I[0, 1] * u1 + I[0, 2] * u2
            iw1 = I[1, 0] * u0 + I[1, 1] * u1 + I[1, 2] * u2
            iw2 = I[2, 0] * u0 + I[2, 1] * u1 + I[2, 2] * u2
            g0, g1, g2 = _cross(u0, u1, u2, iw0, iw1, iw2)
            n0 = I[0, 0] * v0 + I[0, 1] * v1 + I[0, 2] * v2 + g0
            n1 = I[1, 0] * v0 + I[1, 1] * v1 + I[1, 2] * v2 + g1
            n2 = I[2, 0] * v0 + I[2, 1] * v1 + I[2, 2] * v2 + g2
            for r in range(3):
                N[i, r] = R[t, i, r, 0] * n0 + R[t, i, r, 1] * n1 + R[t, i, r, 2] * n2
            Cc[i, 0], Cc[i, 1], Cc[i, 2] = c0, c1, c2
        f0 = f1 = f2 = 0.0
        n0 = n1 = n2 = 0.0
        for i in (2, 1, 0):
            if i < 2:
                s0, s1, s2 = o[i + 2, 0] - o[i + 1, 0], o[i + 2, 1] - o[i + 1, 1], o[i + 2, 2] - o[i + 1, 2]
            else:
                s0 = s1 = s2 = 0.0
            x0, x1, x2 = _cross(Cc[i, 0], Cc[i, 1], Cc[i, 2], F[i, 0], F[i, 1], F[i, 2])
            y0, y1, y2 = _cross(s0, s1, s2, f0, f1, f2)
            n0, n1, n2 = N[i, 0] + n0 + x0 + y0, N[i, 1] + n1 + x1 + y1, N[i, 2] + n2 + x2 + y2
            f0, f1, f2 = F[i, 0] + f0, F[i, 1] + f1, F[i, 2] + f2
            tau[t, i] = (z[t, i, 0] * n0 + z[t, i, 1] * n1 + z[t, i, 2] * n2) + armature[i] * qdd[t, i]


@njit(cache=True)
def torque_summary(tau, dt, energy, peak):
    """energy (T,) = (tau ** 2).sum(axis=1) * dt (numpy adds a row's three squares in order, as
    here), peak (3,) = np.abs(tau).max(axis=0), for tau (T, 3) N m and dt (T,) s: one pass
    instead of four numpy temporaries (the sum over T stays numpy's, for its rounding)."""
    for i in range(3):
        peak[i] = 0.0
    for t in range(tau.shape[0]):
        a, b, c = tau[t, 0], tau[t, 1], tau[t, 2]
        energy[t] = ((a * a + b * b) + c * c) * dt[t]
        peak[0], peak[1], peak[2] = max(peak[0], abs(a)), max(peak[1], abs(b)), max(peak[2], abs(c))
