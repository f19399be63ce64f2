"""Working volume: the space the head's parts sweep over the joint ranges.

A criterion of the Pareto design optimisation (paper, section 2: the "working volume"): the
volume of the union, over every posture within the joint ranges, of every part box (servos,
camera and brackets: all of them move with the head and take up space near the wearer).

Method: hierarchical voxel sweeping
-----------------------------------
Each link frame has a lattice of cubic voxels of edge ``voxel_m``, offset by
:data:`LATTICE_OFFSET`, and of half-voxels nested in it. Working from the camera end of the
chain down to the mount:

1. Fill each box of the last link (cyclotorsion) with sample points at spacing <= ``voxel_m / 2``
   per axis, faces included, in the link's frame.
2. Thin the samples to one per occupied half-voxel, deduplicating by integer half-voxel index
   (a dense occupancy array: the same set as np.unique on the indices, without the sort). The
   kept sample is an exact point of the set, not a cell centre, so rounding does not accumulate
   from level to level; and two per voxel edge, because a lattice one voxel apart, once turned,
   falls between the next frame's voxels and leaves holes.
3. Express the samples in the parent link's frame and sweep them over the joint's range, at
   angles ``np.linspace(lo, hi, n)`` with ``n`` such that the point farthest from the axis moves
   at most ``voxel_m / 2`` per step. Two exact shortcuts make this cheap (13 times fewer points
   for the reference head than turning every sample to every angle): a set B turned through
   [lo, hi] sweeps R(lo) B | R(hi) B | (the sweep of B's boundary), since a point that B passes
   over at an angle in between is covered at an end or crossed by B's boundary, so every sample
   is turned to the two ends but only one sample per surface voxel (a voxel with an empty face
   neighbour) to the angles in between; and points near the axis move less per step, so the
   samples are split by distance to the axis into :data:`RADIUS_BANDS` bands, each with the
   angles its outer radius needs.
4. Add the parent link's own boxes (step 1) and repeat from 2 with the next joint, down to the
   mount frame, where the mount's boxes are added.
5. The volume is the number of voxels (mount-frame lattice) holding a sample, times
   ``voxel_m**3``.

Bias, jitter and convergence
----------------------------
A voxel counts in full as soon as a sample falls in it, so the voxels the surface cuts through
(the boundary voxels) bias the estimate upwards, by about half a voxel layer over the swept
surface (``0.5 * voxel_m * surface_area``; tests/design/test_volume.py finds 0.3 to 0.6 layers
on shapes of known volume). Which boundary voxels the samples happen to reach changes with
small changes of the design, so the estimate also jitters, by a fraction of that layer. Both are
confined to a band about a voxel thick around the surface, so the estimate converges to the
true volume as ``voxel_m -> 0``, with error ~ ``voxel_m``. A small head's parts are only a few
voxels thick at the default 3 mm, so there the bias is large. The reference head, whose swept
volume is about 450 cm^3 (by extrapolation), gives 509 cm^3 at 3 mm, 482 at 1.5 mm, 467 at
1 mm and 458 at 0.5 mm; random sub-millimetre shifts of its parts move the 3 mm value by 2 %
(one standard deviation, 1.6 % at 1.5 mm). Widening a joint's range never shrinks the true
volume, but where it barely grows it (the reference head's nearly square camera turned past
+-45 degrees of cyclotorsion) the jitter can lower the estimate, by up to 4 % at 3 mm. Designs
compared at one voxel size share the bias; for an absolute figure use a finer voxel.

Cost, reference head: 15 ms at 3 mm with an allocator that keeps freed memory (30 ms where each
large temporary array is a fresh mapping, as on small VMs), 0.7 s at 1 mm; it grows about as
``voxel_m**-4``. Peak memory is about 10 MB at 3 mm and 230 MB at 1 mm, mostly the swept
points, 24 bytes each.
"""

from __future__ import annotations

import math

import numpy as np

from kinematics.chain import axis_angle_matrix
from kinematics.geometry import LINK_NAMES, HeadGeometry, Joint, Part

#: Number of radius bands, each with its own angular step (module docstring, step 3).
RADIUS_BANDS = 8
#: Where the voxel lattice sits, in voxels: voxel ijk spans [ijk + offset, ijk + offset + 1) * voxel_m
#: in each link frame. Irrational fractions, so that the faces of boxes at round-number
#: coordinates (the reference head's, or an optimiser's grid) do not fall exactly on voxel
#: planes, where floating-point rounding alone would decide whether a closed face spills a whole
#: voxel layer into the next voxel.
LATTICE_OFFSET = np.array([math.sqrt(2.0) - 1.0, (math.sqrt(5.0) - 1.0) / 2.0, math.sqrt(3.0) - 1.5])


def swept_volume_m3(head: HeadGeometry, voxel_m: float = 0.003) -> float:
    """Volume swept by all parts over the joint ranges, m^3, by hierarchical voxel sweeping.

    Parameters
    ----------
    head : HeadGeometry
    voxel_m : float
        Voxel edge, metres. Samples are ``voxel_m / 2`` apart, and move at most ``voxel_m / 2``
        between consecutive sweep angles.

    Returns
    -------
    float
        (number of occupied voxels) * voxel_m**3. Biased upwards by about half a voxel layer
        over the swept surface (+13 % for the reference head at 3 mm), with a jitter of a few
        per cent between similar designs; converges as ``voxel_m -> 0`` (module docstring).
    """
    if not voxel_m > 0:
        raise ValueError(f"voxel_m = {voxel_m} must be a positive length in metres")
    blocks = [_box_points(head.parts_on(LINK_NAMES[-1]), voxel_m / 2.0)]
    for k in (2, 1, 0):  # joint k turns link k + 1 (LINK_NAMES[k + 1]) in link k's frame
        samples, boundary = _thin(_as_points(blocks), voxel_m)
        blocks = _sweep(samples, boundary, head.joints[k], voxel_m / 2.0)
        blocks.append(_box_points(head.parts_on(LINK_NAMES[k]), voxel_m / 2.0))
    return _count_voxels(blocks, voxel_m) * voxel_m ** 3


def swept_volume_cm3(head: HeadGeometry, voxel_m: float = 0.003) -> float:
    """:func:`swept_volume_m3` in cm^3 (for reports)."""
    return swept_volume_m3(head, voxel_m) * 1e6


def _box_points(parts: tuple[Part, ...], spacing: float) -> np.ndarray:
    """(3, N) points filling the boxes at most ``spacing`` apart per axis, faces included, link frame."""
    out = [np.zeros((3, 0))]
    for p in parts:
        axes = [np.linspace(c - s / 2.0, c + s / 2.0, int(math.ceil(s / spacing)) + 1)
                for c, s in zip(p.center_m, p.size_m)]
        out.append(np.stack(np.meshgrid(*axes, indexing="ij")).reshape(3, -1))
    return np.concatenate(out, axis=1)


def _as_points(blocks: list[np.ndarray]) -> np.ndarray:
    """Blocks of (..., 3, N) points as one (3, M) array."""
    return np.concatenate([np.moveaxis(b, -2, 0).reshape(3, -1) for b in blocks], axis=1)


def _index(x: np.ndarray, voxel_m: float, per_voxel: int = 1) -> np.ndarray:
    """Integer lattice indices of (..., 3, N) points, on cells of edge ``voxel_m / per_voxel``.

    Cell edges are at (i / per_voxel + LATTICE_OFFSET) * voxel_m, so the cells nest in the voxels:
    voxel index = cell index // per_voxel.
    """
    y = x * (per_voxel / voxel_m)
    y -= per_voxel * LATTICE_OFFSET[:, None]
    return np.floor(y, out=y).astype(np.intp)


def _last_point_grid(ijk: np.ndarray) -> np.ndarray:
    """For (3, N) integer cell indices: a dense grid over their bounding box holding, per cell,
    the index of the last point in it, or -1."""
    local = ijk - ijk.min(axis=1, keepdims=True)
    dims = tuple(local.max(axis=1) + 1)
    grid = np.full(int(np.prod(dims)), -1, np.intp)
    grid[np.ravel_multi_index(tuple(local), dims)] = np.arange(ijk.shape[1])
    return grid.reshape(dims)


def _thin(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """One exact point per occupied half-voxel, (3, M), and one per voxel on the surface, (3, K).

    A surface voxel is an occupied voxel with an empty face neighbour.
    """
    if points.shape[1] == 0:
        return points, points
    half = _index(points, voxel_m, 2)
    cells = _last_point_grid(half)
    kept = cells[cells >= 0]
    samples = points[:, kept]
    voxels = _last_point_grid(half[:, kept] // 2)
    p = np.pad(voxels >= 0, 1)
    interior = (p[:-2, 1:-1, 1:-1] & p[2:, 1:-1, 1:-1] & p[1:-1, :-2, 1:-1]
                & p[1:-1, 2:, 1:-1] & p[1:-1, 1:-1, :-2] & p[1:-1, 1:-1, 2:])
    return samples, samples[:, voxels[(voxels >= 0) & ~interior]]


def _sweep(samples: np.ndarray, boundary: np.ndarray, joint: Joint, max_step: float) -> list[np.ndarray]:
    """Blocks of (..., 3, N) parent-frame points: the samples turned to the two ends of ``joint``'s
    range, the boundary samples also to the angles between, no point moving more than
    ``max_step`` per step."""
    axis, origin = np.asarray(joint.axis, float), np.asarray(joint.origin_m, float)
    lo, hi = joint.range_rad
    blocks = [_turn(axis_angle_matrix(axis, np.array([lo, hi])), samples, origin)]
    # Distance from the axis, which passes through the link origin.
    radius = np.linalg.norm(boundary - np.outer(axis, axis @ boundary), axis=0)
    r_max = radius.max(initial=0.0)
    if r_max > 0.0:
        band = np.minimum((radius * (RADIUS_BANDS / r_max)).astype(int), RADIUS_BANDS - 1)
        for b in range(RADIUS_BANDS):
            n = int(math.ceil((hi - lo) * r_max * (b + 1) / RADIUS_BANDS / max_step)) + 1
            members = boundary[:, band == b]
            if n > 2 and members.shape[1]:
                blocks.append(_turn(axis_angle_matrix(axis, np.linspace(lo, hi, n)[1:-1]), members, origin))
    return blocks


def _turn(R: np.ndarray, points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(n, 3, N): the (3, N) points under each of the (n, 3, 3) rotations, then shifted by ``origin``."""
    out = (R.reshape(-1, 3) @ points).reshape(R.shape[0], 3, -1)
    out += origin[:, None]
    return out


def _count_voxels(blocks: list[np.ndarray], voxel_m: float) -> int:
    """Number of voxels holding at least one point of the (..., 3, N) blocks."""
    blocks = [b for b in blocks if b.size]
    if not blocks:
        return 0
    # The lattice box from the coordinate extremes (floor is monotone), then one block at a time,
    # so only one block's indices are in memory at once.
    xyz = [tuple(a for a in range(b.ndim) if a != b.ndim - 2) for b in blocks]  # all axes but xyz
    lo = _index(np.min([b.min(axis=a) for b, a in zip(blocks, xyz)], axis=0)[:, None], voxel_m)[:, 0]
    hi = _index(np.max([b.max(axis=a) for b, a in zip(blocks, xyz)], axis=0)[:, None], voxel_m)[:, 0]
    dims = hi - lo + 1
    occupied = np.zeros(int(np.prod(dims)), bool)
    for b in blocks:
        i, j, k = (c - lo[axis] for axis, c in enumerate(np.moveaxis(_index(b, voxel_m), -2, 0)))
        occupied[((i * dims[1] + j) * dims[2] + k).ravel()] = True
    return int(np.count_nonzero(occupied))
