"""A natural feature's plane normal fitted to its looks (after Molton, Davison and Reid, BMVC
2004): the candidate normal whose warp of the first-view patch best matches the image at the
feature's match (fit_normal_kernel), used by map management (mapping.MapManager) as the view
turns."""

from __future__ import annotations

import math

import numpy as np

from ..kernels import compiled_kernel
from .plane import plane_corners_kernel
from .warp import _template_from_corners
from .zncc import zncc_at


@compiled_kernel(plane_corners_kernel, _template_from_corners, zncc_at)
def normal_scores_kernel(grey, patch, t, rays0, r0, y, r, R, model, lens, z, normals):
    """The score ``2 (1 - ZNCC)`` (k,) of the feature's first-view patch warped into the current
    view by the plane through ``y`` with each of ``normals`` (k, 3), centred on the feature's
    match ``z`` (2,) px, against the image there; 2 where a normal gives no valid warp."""
    k = normals.shape[0]
    h = t // 2
    out = np.full(k, 2.0)
    zu, zv = int(round(z[0])), int(round(z[1]))
    for c in range(k):
        corners = plane_corners_kernel(rays0, normals[c], r0, y, r, R, model, lens)
        if not np.isfinite(corners).all():
            continue
        cu, cv = corners[4, 0], corners[4, 1]
        if abs(cu - z[0]) > 2.0 or abs(cv - z[1]) > 2.0:
            continue                      # the first view's centre lands off the match on this plane
        # The warped patch moved so that its centre lands on the match, sampled on the grid of
        # the image window about the match's pixel: only the plane's shape is compared.
        tpl, inside = _template_from_corners(patch, corners, t, cu - h - (z[0] - zu), cv - h - (z[1] - zv))
        if inside:
            out[c] = zncc_at(grey, tpl, zu, zv)
    return out


@compiled_kernel()
def candidate_normals(d0, tilts_deg, n_azimuth):
    """(k, 3) unit normals tilted from the direction ``d0`` (3,) by each of ``tilts_deg`` (a 0
    gives ``d0`` itself, once) towards ``n_azimuth`` directions evenly spread about it."""
    d = d0 / math.sqrt(d0[0] ** 2 + d0[1] ** 2 + d0[2] ** 2)
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, a)
    e1 /= math.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    e2 = np.cross(d, e1)
    k = 0
    for tilt in tilts_deg:
        k += 1 if tilt == 0.0 else n_azimuth
    out = np.empty((k, 3))
    k = 0
    for tilt in tilts_deg:
        if tilt == 0.0:
            out[k] = d
            k += 1
            continue
        th = math.radians(tilt)
        for j in range(n_azimuth):
            ph = 2 * math.pi * j / n_azimuth
            out[k] = math.cos(th) * d + math.sin(th) * (math.cos(ph) * e1 + math.sin(ph) * e2)
            k += 1
    return out


@compiled_kernel(normal_scores_kernel, candidate_normals)
def fit_normal_kernel(grey, patch, t, rays0, r0, y, r, R, model, lens, z, normal, tilts_deg, n_azimuth, fine_deg):
    """The plane normal (3,) that best explains the feature's looks at its match ``z`` (2,) px
    (normal_scores_kernel), coarse to fine: ``normal`` and the normals ``tilts_deg`` from the
    direction to the first view, then ``fine_deg`` about the best of those (facing the first
    view); and its score and that of ``normal``."""
    d0 = r0 - y
    d0 = d0 / math.sqrt(d0[0] ** 2 + d0[1] ** 2 + d0[2] ** 2)
    coarse = candidate_normals(d0, tilts_deg, n_azimuth)
    s0 = normal_scores_kernel(grey, patch, t, rays0, r0, y, r, R, model, lens, z, normal.reshape(1, 3))[0]
    sc = normal_scores_kernel(grey, patch, t, rays0, r0, y, r, R, model, lens, z, coarse)
    b = np.argmin(sc)
    best, score = normal.copy(), s0
    if sc[b] < score:
        best, score = coarse[b].copy(), sc[b]
    fine = candidate_normals(best, np.array([fine_deg]), n_azimuth)
    sf = normal_scores_kernel(grey, patch, t, rays0, r0, y, r, R, model, lens, z, fine)
    for c in range(fine.shape[0]):
        if sf[c] < score and fine[c, 0] * d0[0] + fine[c, 1] * d0[1] + fine[c, 2] * d0[2] > 0.2:
            best, score = fine[c].copy(), sf[c]
    return best, score, s0
