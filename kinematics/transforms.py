"""Rotations and quaternions, once for the whole suite, on scipy's ``Rotation`` where it fits.

Conventions
-----------
Rotation matrices ``R_a_b`` (3, 3) take vectors in frame b to frame a. Rotation vectors are
axis times angle (radians). Quaternions come in two orders, named in the function names:
``xyzw`` (scipy's, and the TUM trajectory files') and ``wxyz`` (MuJoCo's, and MonoSLAM's state);
every quaternion a function returns has a non-negative scalar part. Functions take one rotation
or a batch (leading axis N) and return the same.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "skew", "so3_exp", "so3_log", "quat_wxyz_from_matrix", "matrix_from_quat_wxyz", "quat_multiply_wxyz",
    "quat_conjugate_wxyz", "rotation_angle", "nearest_rotation", "rotation_between", "cross3",
]


def cross3(a, b) -> np.ndarray:
    """``np.cross(a, b)`` of two 3-vectors (3,): the same products and differences in the same
    order, so the same numbers, without np.cross's axis handling (~20x the arithmetic's cost
    for one pair; the pure-Python IK calls it tens of thousands of times per workload)."""
    a0, a1, a2 = a.tolist() if isinstance(a, np.ndarray) else a
    b0, b1, b2 = b.tolist() if isinstance(b, np.ndarray) else b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def skew(v) -> np.ndarray:
    """(3, 3) (or (N, 3, 3)) matrix [v]x with [v]x u = v x u."""
    v = np.asarray(v, float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def so3_exp(w) -> np.ndarray:
    """Rotation matrix (3, 3) or (N, 3, 3) of rotation vectors w (3,) or (N, 3), radians."""
    w = np.asarray(w, float)
    return Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(w.shape[:-1] + (3, 3))


def so3_log(R) -> np.ndarray:
    """Rotation vector (3,) or (N, 3), radians, of rotation matrices (3, 3) or (N, 3, 3)."""
    R = np.asarray(R, float)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def quat_wxyz_from_matrix(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of rotation matrices (3, 3) or (N, 3, 3)."""
    R = np.asarray(R, float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()[:, [3, 0, 1, 2]]
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(R.shape[:-2] + (4,))


def matrix_from_quat_wxyz(q) -> np.ndarray:
    """Rotation matrix (3, 3) or (N, 3, 3) of quaternions (w, x, y, z) (normalised first)."""
    q = np.asarray(q, float)
    flat = q.reshape(-1, 4)
    return Rotation.from_quat(flat[:, [1, 2, 3, 0]]).as_matrix().reshape(q.shape[:-1] + (3, 3))


def quat_multiply_wxyz(q, p) -> np.ndarray:
    """Hamilton product q p of quaternions (w, x, y, z): the rotation p, then q."""
    q, p = np.asarray(q, float), np.asarray(p, float)
    w1, v1 = q[..., :1], q[..., 1:]
    w2, v2 = p[..., :1], p[..., 1:]
    return np.concatenate([w1 * w2 - np.sum(v1 * v2, axis=-1, keepdims=True),
                           w1 * v2 + w2 * v1 + np.cross(v1, v2)], axis=-1)


def quat_conjugate_wxyz(q) -> np.ndarray:
    """(w, -x, -y, -z): the inverse rotation of a unit quaternion."""
    q = np.asarray(q, float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def rotation_angle(R_a, R_b) -> np.ndarray:
    """Geodesic angle (radians) between rotations (3, 3) or (N, 3, 3): ``|log(R_a^T R_b)|``.

    Computed from the trace, clipped into [-1, 1]: exact to ~1e-8 rad near 0 and pi.
    """
    Ra = np.asarray(R_a, float).reshape(-1, 3, 3)
    Rb = np.asarray(R_b, float).reshape(-1, 3, 3)
    c = (np.einsum("nji,nji->n", Ra, Rb) - 1.0) / 2.0   # trace(Ra^T Rb)
    out = np.arccos(np.clip(c, -1.0, 1.0))
    return out[0] if np.ndim(R_a) == 2 and np.ndim(R_b) == 2 else out


def nearest_rotation(M) -> np.ndarray:
    """The rotation nearest (Frobenius) to each matrix (3, 3) or (N, 3, 3): its polar factor,
    with the sign fixed so det = +1. For products of rotations that drifted by rounding, and for
    the chordal mean of rotations (the nearest rotation to their mean matrix)."""
    M = np.asarray(M, float)
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ (D[..., :, None] * Vt)


def rotation_between(a, b) -> np.ndarray:
    """The minimal rotation (3, 3) taking direction a (3,) onto direction b (3,) (any lengths > 0):
    about a x b; for opposite directions, half a turn about an axis perpendicular to a."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return so3_exp(np.pi * perp / np.linalg.norm(perp))
    return so3_exp(axis / s * np.arctan2(s, c))
