"""Zero-mean normalised cross-correlation (ZNCC), the one score of every appearance match:
``2 (1 - ZNCC)``, 0 for identical patches up to a gain and offset (lighting changes), 2 for
unrelated ones, 4 for inverted ones. The scores of a template at every pixel of an ellipse (a
row's chord at a time, from the region's own integral images; coarse to fine for wide
templates), at one pixel (the plane fit's), and the best of a grid with the one parabolic
sub-pixel step."""

from __future__ import annotations

import math

import numpy as np

from ..kernels import compiled_kernel

#: A window flatter than this grey-level variance cannot hold a match (ZNCC is noise there).
FLAT_VARIANCE = 4.0

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
def parabola_offset(a: float, b: float, c: float) -> float:
    """Offset of the extremum of a parabola through (-1, a), (0, b), (1, c), clamped to +-0.5:
    the sub-pixel step of a best score ``b`` between its neighbours' ``a`` and ``c``."""
    d = a - 2 * b + c
    return 0.0 if abs(d) < 1e-12 else min(max(0.5 * (a - c) / d, -0.5), 0.5)


@compiled_kernel()
def zero_mean_into(tpl, T):
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


@compiled_kernel(zero_mean_into, _region_integrals, _score_from_sums, fastmath={"contract", "reassoc"})
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
    tn2 = zero_mean_into(tpl, T)
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


@compiled_kernel(zero_mean_into, _region_integrals, _score, _score_from_sums, _window_sums, _zncc_in_ellipse,
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
    tn2 = zero_mean_into(tpl, T)
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
    tcn2 = zero_mean_into(Tc, Tz)
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
def zncc_at(grey, tpl, u, v):
    """``2 (1 - ZNCC)`` of the (t, t) template ``tpl`` against the window of ``grey`` centred on
    the integer pixel (u, v); 2 when either is flat or the window leaves the image."""
    H, W = grey.shape
    t = tpl.shape[0]
    h = t // 2
    if u - h < 0 or v - h < 0 or u + h >= W or v + h >= H:
        return 2.0
    n = t * t
    mt = 0.0
    mw = 0.0
    for b in range(t):
        for a in range(t):
            mt += tpl[b, a]
            mw += grey[v - h + b, u - h + a]
    mt /= n
    mw /= n
    stw = 0.0
    stt = 0.0
    sww = 0.0
    for b in range(t):
        for a in range(t):
            dt = tpl[b, a] - mt
            dw = grey[v - h + b, u - h + a] - mw
            stw += dt * dw
            stt += dt * dt
            sww += dw * dw
    if stt < 1e-9 or sww < FLAT_VARIANCE * n:
        return 2.0
    return 2.0 * (1.0 - stw / math.sqrt(stt * sww))
