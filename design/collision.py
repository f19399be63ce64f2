"""Self-collision of the head's parts: oriented-box overlap over the joint ranges.

A design criterion of the Pareto optimisation (paper, section 2): "self collisions between
motors and sensors, which would otherwise reduce the angular sensing range". Every part of a
:class:`~kinematics.geometry.HeadGeometry` is a box fixed in its link's frame, so at a posture
``q`` each part is an oriented box in the mount frame, and two parts collide when the boxes
intersect, decided exactly by the separating-axis theorem (SAT).

Which pairs are checked (:func:`collision_pairs`): parts of kind ``servo`` or ``camera`` on
different links. Brackets are modelled as masses only: a bracket joins a motor to the next link
and touches both by design, so its box says nothing about collisions. Parts on the same link
never move relative to each other; whether they overlap is a separate, posture-independent
constraint (:func:`same_link_overlap`).

Everything is vectorised over postures: the loops are over parts, pairs or joints only. Units:
metres and radians.
"""

from __future__ import annotations

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
