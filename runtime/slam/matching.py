"""The frame's active search over all the features it measures at once (paper, section 4.1), in
one compiled pass: each feature's template predicted for the current view by the homography its
plane induces (templates.py explains the geometry) and matched by zero-mean normalised
cross-correlation at every pixel inside its 3-sigma ellipse, with a parabolic sub-pixel fit.

The score is ``2 (1 - ZNCC)`` as in search.py (0 for identical patches up to gain and offset,
2 for unrelated ones); a warped template that matches nothing is retried as first seen (the
plane guess may be wrong). The templates are warped in one compiled pass and every feature is
searched, matched and refined in another (a call per frame, not per feature: the per-feature
calls into OpenCV and back cost more than the correlation). The correlation is computed only
inside each ellipse, a row's chord at a time; windows too flat to hold a match are excluded by
their variance. Templates 11 px or wider (640 x 480 images) are searched coarse to fine: one
pyramid level picks the peaks, a descent at every pixel finds each one's best (half the time;
an edge's level valley is still searched exhaustively).

The best position is refined to sub-pixel precision by Gauss-Newton on the template under an
affine warp about its centre (Lucas-Kanade, inverse compositional; the shape is damped towards
the prediction): a parabola through the correlation peak errs by a tenth of a pixel or more with
the sub-pixel phase, and a template predicted with a slightly wrong plane or pose, if only
translated, is pulled off its feature by a few tenths, a bias that grows as the view leaves the
first one (the twin's tracks measured against their true projections; benchmarks/NOTES.md).

The templates' warp is in template_warp.py; the plane a natural feature's warp uses starts as a
guess (facing its first view) and, as the view turns, is fitted to the feature's looks
(normal_fit.py).
"""

from __future__ import annotations

import math

import numpy as np

from kinematics.camera import CameraIntrinsics, lens_kernel_args

from .kernels import compiled_kernel
from .quaternion import quat_to_rotation
from .search import parabola_offset
from .template_warp import warp_kernel
from .templates import MapFeature

#: A window flatter than this grey-level variance cannot hold a match (ZNCC is noise there).
FLAT_VARIANCE = 4.0
#: The weight of the sub-pixel refinement's prior on the template's shape, the predicted one
#: (affine Gauss-Newton; larger: closer to translation only).
AFFINE_DAMPING = 1.0
#: Templates this wide or wider are searched coarse to fine (their half-size template, at least
#: 5 x 5, still picks the peaks; a 4 x 4 one misses about 1 in 600 matches).
COARSE_MIN_TEMPLATE = 11
#: The coarse grid's minima the fine search descends from.
COARSE_PEAKS = 3
#: More coarse scores than COARSE_LEVEL_MOST within COARSE_LEVEL of the least: a level valley
#: (an edge, a repeated pattern), where a descent stops at a local best and the exhaustive
#: search's global one is nearer the truth; searched exhaustively.
COARSE_LEVEL = 0.2
COARSE_LEVEL_MOST = 8
#: A level valley in a region larger than this (its bounding box, px) is not searched
#: exhaustively: the descents start from its COARSE_LEVEL_MOST least coarse minima instead, so
#: a young feature's long epipolar ellipse (tens of thousands of pixels) costs a coarse scan
#: and a few descents, not a full correlation at every pixel.
VALLEY_EXHAUSTIVE_MAX_PX = 6000



@compiled_kernel()
def _zero_mean_into(tpl, T):
    """``T`` (t, t) <- the template ``tpl`` less its mean (in ``T``'s precision); returns the
    sum of ``T``'s squares."""
    t = tpl.shape[0]
    mean = 0.0
    for b in range(t):
        for a in range(t):
            mean += tpl[b, a]
    mean /= t * t
    ss = 0.0
    for b in range(t):
        for a in range(t):
            T[b, a] = tpl[b, a] - mean
            ss += T[b, a] * T[b, a]
    return ss


@compiled_kernel()
def _region_integrals(grey, y0, x0, rh, rw):
    """The integral images (rh + 1, rw + 1) of the values and squares of ``grey``'s region at
    (x0, y0) of size (rh, rw), in float64."""
    ii = np.zeros((rh + 1, rw + 1))
    ii2 = np.zeros((rh + 1, rw + 1))
    for y in range(rh):
        row = 0.0
        row2 = 0.0
        for x in range(rw):
            g = np.float64(grey[y0 + y, x0 + x])
            row += g
            row2 += g * g
            ii[y + 1, x + 1] = ii[y, x + 1] + row
            ii2[y + 1, x + 1] = ii2[y, x + 1] + row2
    return ii, ii2


@compiled_kernel(fastmath={"contract", "reassoc"})
def _score(corr, tn2, sw, sw2, n):
    """``2 (1 - ZNCC)`` from the correlation ``corr`` of the zero-mean template (squares' sum
    ``tn2``) with a window of ``n`` pixels whose sum and sum of squares are ``sw``, ``sw2``; inf
    for a flat window."""
    var = sw2 - sw * sw / n
    if var < FLAT_VARIANCE * n:
        return np.inf
    return 2.0 * (1.0 - min(max(corr / math.sqrt(tn2 * var), -1.0), 1.0))


@compiled_kernel(_score, fastmath={"contract", "reassoc"})
def _score_from_sums(corr, tn2, ii, ii2, i, j, t):
    """``_score`` of the window whose top-left is (i, j) in the region's integral images."""
    sw = ii[j + t, i + t] - ii[j, i + t] - ii[j + t, i] + ii[j, i]
    sw2 = ii2[j + t, i + t] - ii2[j, i + t] - ii2[j + t, i] + ii2[j, i]
    return _score(corr, tn2, sw, sw2, t * t)


@compiled_kernel(_zero_mean_into, _region_integrals, _score_from_sums, fastmath={"contract", "reassoc"})
def _zncc_in_ellipse(grey, tpl, u0, v0, nu, nv, uv0, uv1, iaa, iab, ibb, n2):
    """The scores ``2 (1 - ZNCC)`` (nv, nu) of the (t, t) template ``tpl`` against the windows
    of ``grey`` centred on (u0 + i, v0 + j), at the positions inside the ellipse ``(p - uv)^T
    S^-1 (p - uv) <= n2`` (``S^-1 = [[iaa, iab], [iab, ibb]]``) whose windows are not flat; inf
    elsewhere. The windows' sums and sums of squares come from the region's own integral images
    (a few thousand pixels, not the whole image); the correlations are float32 sums, as OpenCV's
    TM_CCOEFF_NORMED (scores within 1e-5 of it); a flat template scores 2 everywhere (OpenCV
    gives it 0)."""
    t = tpl.shape[0]
    h = t // 2
    W = grey.shape[1]
    flat = grey.ravel()
    T = np.empty((t, t), np.float32)
    tn2 = _zero_mean_into(tpl, T)
    rh, rw = nv + 2 * h, nu + 2 * h
    y0, x0 = v0 - h, u0 - h
    ii, ii2 = _region_integrals(grey, y0, x0, rh, rw)
    grid = np.full((nv, nu), np.inf)
    if tn2 <= 0.0:
        T[:, :] = 0.0
        tn2 = 1.0
    corr = np.empty(nu, np.float32)
    for j in range(nv):
        dv = v0 + j - uv1
        # The ellipse's chord on this row, a pixel wider each side (the test below is exact).
        disc = (iab * dv) ** 2 - iaa * (ibb * dv * dv - n2)
        if disc < 0.0:
            continue
        r = math.sqrt(disc)
        lo = max(int(math.floor((-iab * dv - r) / iaa + uv0 - u0)) - 1, 0)
        hi = min(int(math.ceil((-iab * dv + r) / iaa + uv0 - u0)) + 1, nu - 1)
        if hi < lo:
            continue
        # The correlation along the chord, a template pixel at a time: a contiguous run the
        # compiler vectorises (unsigned indices: no negative-index wraparound to check).
        corr[lo:hi + 1] = 0.0
        run = np.uint64(hi + 1 - lo)
        for b in range(t):
            base = np.uint64((y0 + j + b) * W + x0 + lo)
            for a in range(t):
                w = T[b, a]
                at = base + np.uint64(a)
                for i in range(run):
                    corr[lo + i] += w * flat[at + i]
        for i in range(lo, hi + 1):
            du = u0 + i - uv0
            if iaa * du * du + 2.0 * iab * du * dv + ibb * dv * dv > n2:
                continue
            grid[j, i] = _score_from_sums(corr[i], tn2, ii, ii2, i, j, t)
    return grid


@compiled_kernel(fastmath={"contract"})
def _window_sums(grey, T, y, x):
    """The correlation of the zero-mean (t, t) template ``T`` with ``grey``'s window whose
    top-left is (x, y), and the window's sum and sum of squares. The correlation is a float32 sum
    in ``_zncc_in_ellipse``'s order (no reassociation), so that the two give the same score to
    the bit on integer grey levels (whose float64 sums are exact)."""
    t = T.shape[0]
    c = np.float32(0.0)
    sw = 0.0
    sw2 = 0.0
    for b in range(t):
        for a in range(t):
            g = grey[y + b, x + a]
            c += T[b, a] * g
            sw += g
            sw2 += np.float64(g) * g
    return c, sw, sw2


@compiled_kernel(_zero_mean_into, _region_integrals, _score, _score_from_sums, _window_sums, _zncc_in_ellipse,
                 fastmath={"contract", "reassoc"})
def _zncc_coarse_to_fine(grey, tpl, u0, v0, nu, nv, uv0, uv1, iaa, iab, ibb, n2, peaks, level, most,
                         exhaustive_max):
    """The scores of ``_zncc_in_ellipse`` at the positions a coarse-to-fine search visits, inf
    elsewhere. Coarse: the region and the template averaged over 2 x 2 blocks (one pyramid
    level), scored at every second pixel of every second row of the ellipse grown by a pixel's
    diagonal. A coarse grid with more than ``most`` scores within ``level`` of its least is a
    level valley (an edge, a repeated pattern): the exhaustive scores are returned. Otherwise,
    fine: from each of the ``peaks`` least local minima of the coarse grid, a descent at every
    pixel (the 3 x 3 around the current position scored, the least taken, until the current one
    is the least around it), which leaves the best's neighbours scored for the parabolic fit.
    Each fine score equals the exhaustive one to the bit on integer grey levels
    (``_window_sums``); the best is the exhaustive search's unless its basin holds none of those
    minima (on the twin's walk and kitchen walk, 0.1% and 0.5% of the natural features' matches
    differ and 0.01% and 0.06% are lost)."""
    t = tpl.shape[0]
    h = t // 2
    n = t * t
    T = np.empty((t, t), np.float32)
    tn2 = _zero_mean_into(tpl, T)
    if tn2 <= 0.0:
        T[:, :] = 0.0
        tn2 = 1.0
    rh, rw = nv + 2 * h, nu + 2 * h
    y0, x0 = v0 - h, u0 - h
    # One pyramid level of the region and of the template (its first 2 (t // 2) rows and columns).
    tc = t // 2
    ch, cw = rh // 2, rw // 2
    R = np.empty((ch, cw), np.float32)
    for y in range(ch):
        for x in range(cw):
            R[y, x] = 0.25 * (grey[y0 + 2 * y, x0 + 2 * x] + grey[y0 + 2 * y, x0 + 2 * x + 1]
                              + grey[y0 + 2 * y + 1, x0 + 2 * x] + grey[y0 + 2 * y + 1, x0 + 2 * x + 1])
    Tc = np.empty((tc, tc), np.float32)
    for b in range(tc):
        for a in range(tc):
            Tc[b, a] = 0.25 * (tpl[2 * b, 2 * a] + tpl[2 * b, 2 * a + 1] + tpl[2 * b + 1, 2 * a]
                               + tpl[2 * b + 1, 2 * a + 1])
    Tz = np.empty((tc, tc), np.float32)
    tcn2 = _zero_mean_into(Tc, Tz)
    if tcn2 <= 0.0:
        Tz[:, :] = 0.0
        tcn2 = 1.0
    ii, ii2 = _region_integrals(R, 0, 0, ch, cw)
    flat = R.ravel()
    # Within a pixel (each axis) of the ellipse: Mahalanobis radius + sqrt(2 lambda_max(S^-1)).
    lam = 0.5 * (iaa + ibb) + math.sqrt(0.25 * (iaa - ibb) ** 2 + iab * iab)
    nd = math.sqrt(n2) + math.sqrt(2.0 * lam)
    nd2 = nd * nd
    nuc, nvc = (nu + 1) // 2, (nv + 1) // 2
    coarse = np.full((nvc, nuc), np.inf)
    corr = np.empty(nuc, np.float32)
    for k in range(nvc):
        dv = v0 + 2 * k - uv1
        disc = (iab * dv) ** 2 - iaa * (ibb * dv * dv - nd2)
        if disc < 0.0:
            continue
        r = math.sqrt(disc)
        lo = max(int(math.floor((-iab * dv - r) / iaa + uv0 - u0)) - 1, 0)
        hi = min(int(math.ceil((-iab * dv + r) / iaa + uv0 - u0)) + 1, nu - 1)
        mlo, mhi = (lo + 1) // 2, hi // 2
        if mhi < mlo:
            continue
        # The chord and its correlation as in _zncc_in_ellipse, written out again: as called
        # functions (tried) the compiler no longer vectorised the run, half the speed.
        corr[mlo:mhi + 1] = 0.0
        run = np.uint64(mhi + 1 - mlo)
        for b in range(tc):
            base = np.uint64((k + b) * cw + mlo)
            for a in range(tc):
                w = Tz[b, a]
                at = base + np.uint64(a)
                for q in range(run):
                    corr[mlo + q] += w * flat[at + q]
        for m in range(mlo, mhi + 1):
            du = u0 + 2 * m - uv0
            if iaa * du * du + 2.0 * iab * du * dv + ibb * dv * dv > nd2:
                continue
            coarse[k, m] = _score_from_sums(corr[m], tcn2, ii, ii2, m, k, tc)
    # A level valley (an edge, a repeated pattern): the exhaustive search, or in a large region
    # descents from more of its minima.
    if (coarse <= coarse.min() + level).sum() > most:
        if nu * nv <= exhaustive_max:
            return _zncc_in_ellipse(grey, tpl, u0, v0, nu, nv, uv0, uv1, iaa, iab, ibb, n2)
        peaks = most
    # The coarse grid's least local minima (over its 8 neighbours).
    best_s = np.full(peaks, np.inf)
    best_i = np.zeros(peaks, np.int64)
    best_j = np.zeros(peaks, np.int64)
    for k in range(nvc):
        for m in range(nuc):
            s = coarse[k, m]
            if not s < best_s[peaks - 1]:
                continue
            is_min = True
            for dk in range(max(k - 1, 0), min(k + 2, nvc)):
                for dm in range(max(m - 1, 0), min(m + 2, nuc)):
                    if coarse[dk, dm] < s:
                        is_min = False
            if not is_min:
                continue
            q = peaks - 1
            while q > 0 and best_s[q - 1] > s:
                best_s[q], best_i[q], best_j[q] = best_s[q - 1], best_i[q - 1], best_j[q - 1]
                q -= 1
            best_s[q], best_i[q], best_j[q] = s, 2 * m, 2 * k
    grid = np.full((nv, nu), np.inf)
    done = np.zeros((nv, nu), np.bool_)
    for p in range(peaks):
        if not np.isfinite(best_s[p]):
            break
        ci, cj = best_i[p], best_j[p]
        for _ in range(nu + nv):
            ni, nj, s_min = ci, cj, np.inf
            for j in range(max(cj - 1, 0), min(cj + 2, nv)):
                for i in range(max(ci - 1, 0), min(ci + 2, nu)):
                    if not done[j, i]:
                        done[j, i] = True
                        du, dv = u0 + i - uv0, v0 + j - uv1
                        if iaa * du * du + 2.0 * iab * du * dv + ibb * dv * dv <= n2:
                            c, sw, sw2 = _window_sums(grey, T, y0 + j, x0 + i)
                            grid[j, i] = _score(c, tn2, sw, sw2, n)
                    if grid[j, i] < s_min:
                        ni, nj, s_min = i, j, grid[j, i]
            if ni == ci and nj == cj:
                break
            ci, cj = ni, nj
    return grid


@compiled_kernel(parabola_offset)
def _best_in_grid(grid):
    """The least score in ``grid`` (nv, nu) (inf: not a candidate) with a parabolic sub-pixel
    fit through the neighbours in each direction when both are candidates: (i + su, j + sv,
    score); score 2 and NaN offsets if there is none."""
    nv, nu = grid.shape
    best, bi, bj = np.inf, -1, -1
    for j in range(nv):
        for i in range(nu):
            if grid[j, i] < best:
                best, bi, bj = grid[j, i], i, j
    if bi < 0:
        return np.nan, np.nan, 2.0
    su = sv = 0.0
    if 0 < bi < nu - 1 and np.isfinite(grid[bj, bi - 1]) and np.isfinite(grid[bj, bi + 1]):
        su = parabola_offset(grid[bj, bi - 1], best, grid[bj, bi + 1])
    if 0 < bj < nv - 1 and np.isfinite(grid[bj - 1, bi]) and np.isfinite(grid[bj + 1, bi]):
        sv = parabola_offset(grid[bj - 1, bi], best, grid[bj + 1, bi])
    return bi + su, bj + sv, best


@compiled_kernel()
def refine_affine_kernel(img, tpl, u, v, iterations, tol, reg):
    """Sub-pixel refinement of a match at (u, v) px by Gauss-Newton on the zero-mean, unit-norm
    template under an affine warp about its centre (inverse compositional): the template's shape
    is fitted to the image too, so a template predicted with a slightly wrong warp does not pull
    its centre off the feature. The shape has a prior, ``reg |A - I|^2`` (A: the warp's linear
    part, the identity being the predicted shape), in both the step's matrix and its gradient:
    with the step's damping alone, the shape of an edge or a noisy patch wandered on from
    iteration to iteration and the centre with it (no fixed point). Returns (u, v, ok): ok False
    if it leaves the image, diverges or moves over a pixel."""
    H, W = img.shape
    t = tpl.shape[0]
    h = t // 2
    n = t * t
    T = np.empty((t, t))
    nt = math.sqrt(_zero_mean_into(tpl, T))
    if nt < 1e-9:
        return u, v, False
    for b in range(t):
        for a in range(t):
            T[b, a] /= nt
    # Steepest-descent images (n, 6) and the damped Gauss-Newton matrix, Cholesky-factored.
    SD = np.empty((n, 6))
    Hs = np.zeros((6, 6))
    k = 0
    for b in range(t):
        for a in range(t):
            a0, a1 = max(a - 1, 0), min(a + 1, t - 1)
            b0, b1 = max(b - 1, 0), min(b + 1, t - 1)
            gx = (T[b, a1] - T[b, a0]) / (a1 - a0)
            gy = (T[b1, a] - T[b0, a]) / (b1 - b0)
            x, y = a - h, b - h
            SD[k, 0], SD[k, 1], SD[k, 2], SD[k, 3], SD[k, 4], SD[k, 5] = gx * x, gy * x, gx * y, gy * y, gx, gy
            for i in range(6):
                for j in range(i + 1):
                    Hs[i, j] += SD[k, i] * SD[k, j]
            k += 1
    for i in range(4):
        Hs[i, i] += reg
    L = np.zeros((6, 6))
    for i in range(6):
        for j in range(i + 1):
            acc = Hs[i, j]
            for q in range(j):
                acc -= L[i, q] * L[j, q]
            if i == j:
                if not acc > 1e-12:
                    return u, v, False
                L[i, i] = math.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    a00, a01, a10, a11 = 1.0, 0.0, 0.0, 1.0          # the current warp: x_img = A x + (u, v)
    cu, cv = u, v
    Wv = np.empty(n)
    g = np.empty(6)
    dp = np.empty(6)
    for _ in range(iterations):
        k = 0
        wsum = 0.0
        for b in range(t):
            for a in range(t):
                x, y = a - h, b - h
                px = a00 * x + a01 * y + cu
                py = a10 * x + a11 * y + cv
                if not (0.0 <= px < W - 1 and 0.0 <= py < H - 1):
                    return u, v, False
                ix, iy = int(px), int(py)
                fx, fy = px - ix, py - iy
                Wv[k] = ((1 - fx) * (1 - fy) * img[iy, ix] + fx * (1 - fy) * img[iy, ix + 1]
                         + (1 - fx) * fy * img[iy + 1, ix] + fx * fy * img[iy + 1, ix + 1])
                wsum += Wv[k]
                k += 1
        wmean = wsum / n
        nw = 0.0
        for k in range(n):
            Wv[k] -= wmean
            nw += Wv[k] * Wv[k]
        nw = math.sqrt(nw)
        if nw < 1e-9:
            return u, v, False
        g[:] = 0.0
        k = 0
        for b in range(t):
            for a in range(t):
                e = Wv[k] / nw - T[b, a]
                for i in range(6):
                    g[i] += SD[k, i] * e
                k += 1
        # The prior's pull of the shape back to the predicted one, reg (A - I), in dp's order
        # (p0 = a00 - 1, p1 = a10, p2 = a01, p3 = a11 - 1).
        g[0] += reg * (a00 - 1.0)
        g[1] += reg * a10
        g[2] += reg * a01
        g[3] += reg * (a11 - 1.0)
        for i in range(6):                             # dp = Hs^-1 g by the Cholesky factor
            acc = g[i]
            for q in range(i):
                acc -= L[i, q] * dp[q]
            dp[i] = acc / L[i, i]
        for i in range(5, -1, -1):
            acc = dp[i]
            for q in range(i + 1, 6):
                acc -= L[q, i] * dp[q]
            dp[i] = acc / L[i, i]
        # Inverse compositional: W <- W o W(dp)^-1, W(dp) = [[1 + p0, p2], [p1, 1 + p3]] x + (p4, p5)
        d00, d01, d10, d11 = 1.0 + dp[0], dp[2], dp[1], 1.0 + dp[3]
        dd = 1.0 / (d00 * d11 - d01 * d10)
        i00, i01, i10, i11 = d11 * dd, -d01 * dd, -d10 * dd, d00 * dd
        t0 = -(i00 * dp[4] + i01 * dp[5])
        t1 = -(i10 * dp[4] + i11 * dp[5])
        cu, cv = a00 * t0 + a01 * t1 + cu, a10 * t0 + a11 * t1 + cv
        a00, a01, a10, a11 = (a00 * i00 + a01 * i10, a00 * i01 + a01 * i11,
                              a10 * i00 + a11 * i10, a10 * i01 + a11 * i11)
        if abs(cu - u) > 1.0 or abs(cv - v) > 1.0 or not (0.5 < abs(a00 * a11 - a01 * a10) < 2.0):
            return u, v, False
        if dp[4] * dp[4] + dp[5] * dp[5] < tol * tol and abs(dp[0]) + abs(dp[1]) + abs(dp[2]) + abs(dp[3]) < tol:
            break
    return cu, cv, True



@compiled_kernel(_zncc_in_ellipse, _zncc_coarse_to_fine, _best_in_grid, refine_affine_kernel)
def _search_one(grey, tpl, uv, S, n2, max_area, max_score):
    """(u, v, score) of the best match of ``tpl`` in the ellipse (NaN, NaN, 2 when none); only a
    match scoring at most ``max_score`` is refined to sub-pixel (the others are not used)."""
    H, W = grey.shape
    h = tpl.shape[0] // 2
    a, b, c = S[0, 0], S[0, 1], S[1, 1]
    if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c) and np.isfinite(uv[0])
            and np.isfinite(uv[1]) and a * c - b * b > 0):
        return np.nan, np.nan, 2.0
    hu, hv = math.sqrt(n2 * a), math.sqrt(n2 * c)
    if (2 * hu + 1) * (2 * hv + 1) > max_area:
        return np.nan, np.nan, 2.0
    u0, u1 = max(math.floor(uv[0] - hu), h), min(math.ceil(uv[0] + hu), W - 1 - h)
    v0, v1 = max(math.floor(uv[1] - hv), h), min(math.ceil(uv[1] + hv), H - 1 - h)
    if u1 < u0 or v1 < v0:
        return np.nan, np.nan, 2.0
    det = a * c - b * b
    if tpl.shape[0] >= COARSE_MIN_TEMPLATE:
        grid = _zncc_coarse_to_fine(grey, tpl, u0, v0, u1 - u0 + 1, v1 - v0 + 1, uv[0], uv[1], c / det, -b / det,
                                    a / det, n2, COARSE_PEAKS, COARSE_LEVEL, COARSE_LEVEL_MOST, VALLEY_EXHAUSTIVE_MAX_PX)
    else:
        grid = _zncc_in_ellipse(grey, tpl, u0, v0, u1 - u0 + 1, v1 - v0 + 1, uv[0], uv[1], c / det, -b / det,
                                a / det, n2)
    du, dv, s = _best_in_grid(grid)
    if not np.isfinite(du):
        return np.nan, np.nan, 2.0
    u, v = u0 + du, v0 + dv
    if s <= max_score:
        ur, vr, ok = refine_affine_kernel(grey, tpl, u, v, 10, 0.005, AFFINE_DAMPING)
        if ok:
            u, v = ur, vr
    return u, v, s


@compiled_kernel(_search_one)
def search_kernel(grey, tpls, templates, warped, uv, S, n2, max_area, max_score):
    """Every feature's match: z (m, 2) px (NaN: none in its ellipse) and score (m,); a warped
    template (``tpls[i]`` with ``warped[i]``) that matches nothing is retried as first seen
    (``templates[i]``)."""
    m = tpls.shape[0]
    z = np.full((m, 2), np.nan)
    score = np.full(m, 2.0)
    for i in range(m):
        u, v, s = _search_one(grey, tpls[i], uv[i], S[i], n2, max_area, max_score)
        if s > max_score and warped[i]:
            u, v, s = _search_one(grey, templates[i], uv[i], S[i], n2, max_area, max_score)
        z[i, 0], z[i, 1], score[i] = u, v, s
    return z, score


def match_features(grey: np.ndarray, features: list[MapFeature], warp: np.ndarray,
                   Y: np.ndarray, x_v: np.ndarray, cam: CameraIntrinsics, uv: np.ndarray, S: np.ndarray,
                   max_score: float, max_area: float, n_sigma: float = 3.0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match the map features ``features`` (m) whose predictions are ``uv`` (m, 2) px with
    innovation covariances ``S`` (m, 2, 2): each warped by its plane (through its point ``Y``
    (m, 3), normal ``MapFeature.normal``) where ``warp`` (m,) says so, retried unwarped when the
    warped template finds nothing. ``grey`` : (H, W) float32. Returns z (m, 2) (NaN: not found),
    score (m,), found (m,)."""
    m = len(features)
    if m == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool)
    t = features[0].template.shape[0]
    ph = max((f.patch.shape[0] for f in features if f.patch is not None), default=t)
    templates = np.empty((m, t, t), np.float32)
    patches = np.zeros((m, ph, ph), np.float32)
    rays0 = np.zeros((m, 5, 3))
    normals = np.zeros((m, 3))
    r0s = np.zeros((m, 3))
    use = np.asarray(warp, bool).copy()
    for i, f in enumerate(features):
        templates[i] = f.template
        r0s[i] = f.r0
        if use[i] and f.patch is not None and f.normal is not None and f.patch.shape[0] == ph:
            patches[i] = f.patch
            normals[i] = f.normal
            rays0[i] = f.first_view_rays(cam)
        else:
            use[i] = False
    model, lens = lens_kernel_args(cam)
    tpls, warped = warp_kernel(templates, patches, use, rays0, normals, r0s, np.ascontiguousarray(Y, float),
                               np.ascontiguousarray(x_v[:3], float), quat_to_rotation(x_v[3:7]), model, lens)
    z, score = search_kernel(np.ascontiguousarray(grey, np.float32), tpls, templates, warped,
                             np.ascontiguousarray(uv, float), np.ascontiguousarray(S, float),
                             n_sigma * n_sigma, float(max_area), float(max_score))
    found = score <= max_score
    return z, score, found
