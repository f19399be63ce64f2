"""Today's design criteria, kept verbatim as the slow reference the fast kernels are tested against.

Copied from design/volume.py, design/collision.py and design/problem.py (score_head) as they
were before the batched, compiled evaluation (issue 48). Not used by the package.
"""

from __future__ import annotations

# ---- design/volume.py ----


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


# ---- design/collision.py ----


from collections.abc import Sequence

import numpy as np

from kinematics.chain import forward_kinematics
from kinematics.geometry import LINK_NAMES, HeadGeometry, Part

#: Edge-edge SAT axes A_i x B_j shorter than this (i.e. edges within ~1e-6 rad of parallel) are
#: skipped. For parallel edges the cross product is numerical noise whose direction is arbitrary
#: and would report a spurious separation; the face axes already cover that case (the problem
#: reduces to 2D, where the edge normals are face normals).
PARALLEL_TOL = 1e-6


def posed_boxes(head: HeadGeometry, q, parts: Sequence[Part] | None = None):
    """Every part box posed in the mount frame for joint angles ``q``.

    Parameters
    ----------
    head : HeadGeometry
    q : (..., 3) float
        Joint angles (elevation, pan, cyclotorsion), radians.
    parts : sequence of Part, optional
        The P parts to pose; default ``head.parts``.

    Returns
    -------
    centers : (..., P, 3) float
        Box centres in the mount frame, metres.
    R : (..., P, 3, 3) float
        Box orientations: column k is the box's k-th edge direction in the mount frame (the
        link's rotation, since boxes are axis-aligned in their link's frame).
    half : (P, 3) float
        Half edge lengths, metres.
    """
    parts = head.parts if parts is None else tuple(parts)
    q = np.asarray(q, float)
    T_links = forward_kinematics(head, q).T_mount_link          # (..., 3, 4, 4)
    batch = q.shape[:-1]
    # The mount link is the identity; stack it in front so link index = LINK_NAMES index.
    R_links = np.concatenate([np.broadcast_to(np.eye(3), batch + (1, 3, 3)), T_links[..., :3, :3]], axis=-3)
    p_links = np.concatenate([np.zeros(batch + (1, 3)), T_links[..., :3, 3]], axis=-2)
    link = np.array([LINK_NAMES.index(p.link) for p in parts], int)
    center_link = np.array([p.center_m for p in parts], float).reshape(-1, 3)
    R = R_links[..., link, :, :]                                  # (..., P, 3, 3)
    centers = np.einsum("...ij,...j->...i", R, center_link) + p_links[..., link, :]
    half = np.array([p.size_m for p in parts], float).reshape(-1, 3) / 2.0
    return centers, R, half


def obb_penetration(cA, RA, hA, cB, RB, hB) -> np.ndarray:
    """Signed overlap of two oriented boxes by the separating-axis theorem.

    Parameters
    ----------
    cA, cB : (..., 3) float
        Box centres, metres.
    RA, RB : (..., 3, 3) float
        Box orientations (columns are the box edge directions, orthonormal).
    hA, hB : (..., 3) float
        Half edge lengths along those columns, metres.
    All leading dimensions broadcast against each other.

    Returns
    -------
    penetration : (...,) float
        The minimum, over the 15 SAT axes (3 + 3 face normals and the 9 edge-edge cross
        products; near-parallel edge pairs skipped, see :data:`PARALLEL_TOL`), of the overlap
        of the two boxes' projections on that axis, metres. ``> 0``: the boxes intersect and
        this is the penetration depth along the axis of least overlap (the minimum translation
        that separates them). ``<= 0``: they are separated (or touch) and ``-penetration`` is a
        lower bound on their distance.
    """
    cA, cB, hA, hB = (np.asarray(a, float) for a in (cA, cB, hA, hB))
    RA, RB = np.asarray(RA, float), np.asarray(RB, float)
    # Work in A's frame: C[i, j] = A_i . B_j, t = centre offset in A's coordinates.
    C = np.swapaxes(RA, -1, -2) @ RB                               # (..., 3, 3)
    t = np.einsum("...ji,...j->...i", RA, cB - cA)                 # (..., 3)
    absC = np.abs(C)
    hA_, hB_ = hA[..., :, None], hB[..., None, :]

    # Face axes of A (rows i) and of B (columns j): radius of A + radius of B - centre distance.
    over_A = hA + np.sum(absC * hB_, axis=-1) - np.abs(t)
    t_B = np.einsum("...ij,...i->...j", C, t)
    over_B = np.sum(absC * hA_, axis=-2) + hB - np.abs(t_B)

    # Edge axes L_ij = A_i x B_j, in A's frame e_i x C[:, j]. With (i1, i2) = (i+1, i+2) mod 3
    # and likewise (j1, j2): |L| = sqrt(C[i1,j]^2 + C[i2,j]^2), and the projections are the
    # textbook ones (Gottschalk; Ericson, Real-Time Collision Detection, 4.4.1), divided by |L|.
    i1, i2 = np.array([1, 2, 0]), np.array([2, 0, 1])
    Ci1, Ci2 = C[..., i1, :], C[..., i2, :]                        # [i, j] -> C[i1, j], C[i2, j]
    aCi1, aCi2 = absC[..., i1, :], absC[..., i2, :]
    rA = hA[..., i1, None] * aCi2 + hA[..., i2, None] * aCi1
    aCj1, aCj2 = absC[..., :, i1], absC[..., :, i2]                # [i, j] -> |C[i, j1]|, |C[i, j2]|
    rB = hB[..., None, i1] * aCj2 + hB[..., None, i2] * aCj1
    dist = np.abs(t[..., i2, None] * Ci1 - t[..., i1, None] * Ci2)
    norm = np.sqrt(Ci1 ** 2 + Ci2 ** 2)
    degenerate = norm < PARALLEL_TOL
    over_E = np.where(degenerate, np.inf, (rA + rB - dist) / np.where(degenerate, 1.0, norm))

    return np.minimum(np.minimum(over_A.min(axis=-1), over_B.min(axis=-1)), over_E.min(axis=(-2, -1)))


def collision_pairs(head: HeadGeometry) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j`` into ``head.parts``, of parts that may collide.

    Both parts are not brackets (brackets are masses only: they join a motor to the next link
    and touch it by design) and they are on different links (parts on one link never move
    relative to each other; see :func:`same_link_overlap`).
    """
    return [(i, j) for i, j in _solid_pairs(head) if head.parts[i].link != head.parts[j].link]


def _solid_pairs(head: HeadGeometry) -> list[tuple[int, int]]:
    solid = [k for k, p in enumerate(head.parts) if p.kind != "bracket"]
    return [(i, j) for a, i in enumerate(solid) for j in solid[a + 1:]]


def pair_penetrations(head: HeadGeometry, q, pairs: list[tuple[int, int]] | None = None) -> np.ndarray:
    """:func:`obb_penetration` of part pairs at joint angles ``q``.

    Parameters
    ----------
    q : (..., 3) float
        Joint angles, radians.
    pairs : list of K (i, j) index pairs into ``head.parts``; default :func:`collision_pairs`.

    Returns
    -------
    (..., K) float, metres (> 0: that pair intersects).
    """
    pairs = collision_pairs(head) if pairs is None else list(pairs)
    q = np.asarray(q, float)
    if not pairs:
        return np.zeros(q.shape[:-1] + (0,))
    used = sorted({k for pair in pairs for k in pair})
    c, R, h = posed_boxes(head, q, [head.parts[k] for k in used])
    i, j = (np.array([used.index(k) for k in ks]) for ks in zip(*pairs))
    return obb_penetration(c[..., i, :], R[..., i, :, :], h[i], c[..., j, :], R[..., j, :, :], h[j])


def rest_penetration(head: HeadGeometry) -> float:
    """Largest penetration over :func:`collision_pairs` at q = 0, metres (constraint: <= 0).

    ``-inf`` if the head has no collision pair.
    """
    pen = pair_penetrations(head, np.zeros(3))
    return float(pen.max()) if pen.size else -np.inf


def same_link_overlap(head: HeadGeometry) -> float:
    """Largest penetration between non-bracket parts on the same link, metres (constraint: <= 0).

    Independent of the posture (the parts are rigidly fixed to each other), so it is evaluated
    at q = 0. ``-inf`` if no link carries two non-bracket parts.
    """
    pairs = [(i, j) for i, j in _solid_pairs(head) if head.parts[i].link == head.parts[j].link]
    pen = pair_penetrations(head, np.zeros(3), pairs)
    return float(pen.max()) if pen.size else -np.inf


def posture_grid(head: HeadGeometry, steps: int = 9) -> np.ndarray:
    """(steps, steps, steps, 3) joint angles, radians: ``np.linspace(lower, upper, steps)`` per joint.

    Endpoints included; index ``[a, b, c]`` is (elevation[a], pan[b], cyclotorsion[c]).
    """
    samples = [np.linspace(lo, hi, steps) for lo, hi in zip(head.lower, head.upper)]
    return np.stack(np.meshgrid(*samples, indexing="ij"), axis=-1)


def collision_grid(head: HeadGeometry, steps: int = 9) -> np.ndarray:
    """(steps, steps, steps) bool: some collision pair intersects at that posture of :func:`posture_grid`."""
    centers, R, half = posed_boxes(head, posture_grid(head, steps))
    link_of = [LINK_NAMES.index(p.link) for p in head.parts]
    hit = np.zeros((steps,) * 3, bool)
    for i, j in collision_pairs(head):
        # The pose of link b relative to link a (a < b) depends only on joints a .. b-1 (joint k
        # turns link k+1), and the overlap of two boxes only on their relative pose: test the
        # sub-grid of those joints (the others at their first sample) and broadcast over the
        # rest. A mount-elevation pair costs `steps` box tests instead of steps**3.
        a, b = sorted((link_of[i], link_of[j]))
        sub = tuple(slice(None) if a <= k < b else slice(0, 1) for k in range(3))
        pen = obb_penetration(centers[sub + (i,)], R[sub + (i,)], half[i], centers[sub + (j,)], R[sub + (j,)], half[j])
        hit |= pen > 0.0
    return hit


def self_collision_fraction(head: HeadGeometry, steps: int = 9) -> float:
    """Fraction of postures, in [0, 1], at which some pair of :func:`collision_pairs` intersects.

    The postures are the ``steps**3`` grid of :func:`posture_grid`: ``np.linspace(lower, upper,
    steps)`` over each joint's range, endpoints included, all combinations (729 at the default
    ``steps=9``, about 20 degrees apart for the HS-50's 160 degrees). A pair intersects when its
    :func:`obb_penetration` is > 0 (touching does not count). The criterion is the share of the
    joint space lost to self collision, not the collision depth.
    """
    return float(collision_grid(head, steps).mean())


# ---- design/criteria.py and design/problem.py (score_head) ----
from kinematics import inverse_dynamics  # noqa: E402
from kinematics.chain import radii_of_rotation  # noqa: E402


def reference_score(head, ctx) -> tuple[dict, dict]:
    """(criteria, constraints) of a head, as today's design.problem.score_head computed them."""
    w = ctx.workload
    s = ctx.spec
    tau = inverse_dynamics(head, w.q, w.qd, w.qdd, gravity_mount=w.gravity_mount, omega_mount=w.omega_mount,
                           alpha_mount=w.alpha_mount, accel_mount=w.accel_mount)
    radii = radii_of_rotation(head)
    crit = {
        "working_volume_cm3": swept_volume_m3(head, voxel_m=s.voxel_m) * 1e6,
        "self_collision": self_collision_fraction(head, steps=s.collision_steps),
        "integrated_torque": float(np.sum((tau**2).sum(axis=1) * w.dt)),
        "max_torque_nm": float(np.abs(tau).max()),
        "radius_elevation_mm": float(radii[0] * 1000),
        "radius_pan_mm": float(radii[1] * 1000),
        "radius_cyclotorsion_mm": float(radii[2] * 1000),
    }
    cons = {
        "torque_excess_nm": float((np.abs(tau).max(axis=0) - head.max_torque).max()),
        "rest_penetration_m": float(rest_penetration(head) + s.clearance_m),
        "part_overlap_m": float(max(same_link_overlap(head), -1.0) + s.clearance_m),
    }
    return crit, cons
