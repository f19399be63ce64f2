"""A match's sub-pixel refinement: Gauss-Newton on the template under an affine warp about its
centre (Lucas-Kanade, inverse compositional), the shape held by a prior towards the predicted one.
A parabola through the correlation peak errs by a tenth of a pixel or more with the sub-pixel
phase, and a template predicted with a slightly wrong plane or pose, if only translated, is
pulled off its feature by a few tenths (benchmarks/NOTES.md)."""

from __future__ import annotations

import math

import numpy as np

from ..kernels import compiled_kernel
from .zncc import zero_mean_into

#: The weight of the sub-pixel refinement's prior on the template's shape, the predicted one
#: (affine Gauss-Newton; larger: closer to translation only).
AFFINE_DAMPING = 1.0


@compiled_kernel(zero_mean_into)
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
    nt = math.sqrt(zero_mean_into(tpl, T))
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
