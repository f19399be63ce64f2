"""Quaternion maths of the filter, compiled so the measurement and motion kernels can call it.

``q = (w, x, y, z)``; the product is Hamilton's, ``(q * p)`` applies ``p`` first:
``R(q * p) = R(q) R(p)``. :func:`rotation_kernel` uses the homogeneous quadratic formula
(``R(s q) = s^2 R(q)``, no normalisation inside), so it and its derivative
:func:`rotation_derivatives_kernel` are defined on all of R^4; every Jacobian of this package
with respect to ``q`` treats its four components as independent variables of that formula. The
norm is kept at 1 by an explicit renormalisation with its own Jacobian
(:func:`normalise_quaternion_kernel`).

Only the compiled kernels and the thin wrappers the filter calls live here; every other rotation
conversion (rotation vectors, matrices, the TUM x y z w order) is kinematics.transforms'.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from .kernels import compiled_kernel


@compiled_kernel()
def quat_left_kernel(w, x, y, z):
    """(4, 4) ``L(q)`` with ``q * p = L(q) p``, from the four components of q."""
    return np.array([[w, -x, -y, -z],
                     [x, w, -z, y],
                     [y, z, w, -x],
                     [z, -y, x, w]])


@compiled_kernel()
def quat_right_kernel(w, x, y, z):
    """(4, 4) ``M(p)`` with ``q * p = M(p) q``, from the four components of p."""
    return np.array([[w, -x, -y, -z],
                     [x, w, z, -y],
                     [y, -z, w, x],
                     [z, y, -x, w]])


@compiled_kernel()
def rotation_kernel(w, x, y, z):
    """(3, 3) R(q) by the homogeneous quadratic formula (camera -> world for the state's q)."""
    R = np.empty((3, 3))
    R[0, 0] = w * w + x * x - y * y - z * z
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = w * w - x * x + y * y - z * z
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = w * w - x * x - y * y + z * z
    return R


@compiled_kernel()
def rotation_derivatives_kernel(w, x, y, z):
    """(4, 3, 3) dR/dq_i for i = w, x, y, z of :func:`rotation_kernel`."""
    D = np.empty((4, 3, 3))
    D[0, 0, 0], D[0, 0, 1], D[0, 0, 2] = w, -z, y
    D[0, 1, 0], D[0, 1, 1], D[0, 1, 2] = z, w, -x
    D[0, 2, 0], D[0, 2, 1], D[0, 2, 2] = -y, x, w
    D[1, 0, 0], D[1, 0, 1], D[1, 0, 2] = x, y, z
    D[1, 1, 0], D[1, 1, 1], D[1, 1, 2] = y, -x, -w
    D[1, 2, 0], D[1, 2, 1], D[1, 2, 2] = z, w, -x
    D[2, 0, 0], D[2, 0, 1], D[2, 0, 2] = -y, x, w
    D[2, 1, 0], D[2, 1, 1], D[2, 1, 2] = x, y, z
    D[2, 2, 0], D[2, 2, 1], D[2, 2, 2] = -w, z, -y
    D[3, 0, 0], D[3, 0, 1], D[3, 0, 2] = -z, -w, x
    D[3, 1, 0], D[3, 1, 1], D[3, 1, 2] = w, -z, y
    D[3, 2, 0], D[3, 2, 1], D[3, 2, 2] = x, y, z
    return 2.0 * D


# Below this rotation angle (rad) the rotation-vector map uses its Taylor series; at 1e-3 the
# first neglected terms are ~1e-17, below double-precision rounding of the O(1) terms.
_SMALL_ANGLE = 1e-3


@compiled_kernel()
def rotvec_to_quat_jacobian_kernel(t0, t1, t2):
    """``q(theta) = (cos(a/2), sin(a/2) theta / a)``, ``a = |theta|``, (4,) and dq/dtheta (4, 3),
    exact (series) at and near zero, where dq/dtheta = [0; I/2]."""
    theta = np.array([t0, t1, t2])
    a2 = t0 * t0 + t1 * t1 + t2 * t2
    a = math.sqrt(a2)
    if a < _SMALL_ANGLE:
        s = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0      # sin(a/2) / a
        ds_over_a = -1.0 / 24.0 + a2 / 960.0         # s'(a) / a
        c = 1.0 - a2 / 8.0 + a2 * a2 / 384.0         # cos(a/2)
    else:
        s = math.sin(0.5 * a) / a
        c = math.cos(0.5 * a)
        ds_over_a = (0.5 * a * c - math.sin(0.5 * a)) / (a2 * a)
    q = np.empty(4)
    q[0] = c
    q[1:] = s * theta
    J = np.empty((4, 3))
    J[0] = -0.5 * s * theta
    J[1:] = s * np.eye(3) + ds_over_a * np.outer(theta, theta)
    return q, J


@compiled_kernel()
def normalise_quaternion_kernel(q0, q1, q2, q3):
    """``q / |q|`` (4,), its Jacobian ``(|q|^2 I - q q^T) / |q|^3`` (4, 4), and whether ``|q|^2``
    was finite and > 0 (if not, the arrays are NaN)."""
    q = np.array([q0, q1, q2, q3])
    nrm2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    J = np.empty((4, 4))
    if not (np.isfinite(nrm2) and nrm2 > 0):
        J[:] = np.nan
        return np.full(4, np.nan), J, False
    nrm = math.sqrt(nrm2)
    for i in range(4):
        for j in range(4):
            J[i, j] = ((nrm2 if i == j else 0.0) - q[i] * q[j]) / (nrm2 * nrm)
    return q / nrm, J, True


# -- Python wrappers ---------------------------------------------------------------------------

def quat_left_matrix(q) -> np.ndarray:
    w, x, y, z = q
    return quat_left_kernel(float(w), float(x), float(y), float(z))


def quat_multiply(q, p) -> np.ndarray:
    """Hamilton product ``q * p`` of two (4,) quaternions, w x y z."""
    return quat_left_matrix(q) @ np.asarray(p, dtype=float)


def quat_to_rotation(q) -> np.ndarray:
    """(3, 3) R(q) (homogeneous formula: a rotation when |q| = 1)."""
    w, x, y, z = q
    return rotation_kernel(float(w), float(x), float(y), float(z))


def rotation_derivatives(q) -> np.ndarray:
    """(4, 3, 3) dR(q)/dq_i."""
    w, x, y, z = q
    return rotation_derivatives_kernel(float(w), float(x), float(y), float(z))


def rotvec_to_quat_jacobian(theta) -> tuple[np.ndarray, np.ndarray]:
    t0, t1, t2 = np.asarray(theta, dtype=float).reshape(3)
    return rotvec_to_quat_jacobian_kernel(float(t0), float(t1), float(t2))


def rotvec_to_quat(theta) -> np.ndarray:
    """Rotation vector (rad) to unit quaternion, w x y z."""
    return rotvec_to_quat_jacobian(theta)[0]


def quat_from_rotation(R) -> np.ndarray:
    """(4,) w x y z of a rotation matrix (3, 3)."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def normalise_quaternion_jacobian(q) -> tuple[np.ndarray, np.ndarray]:
    q = np.asarray(q, dtype=float).reshape(4)
    q_unit, J, ok = normalise_quaternion_kernel(q[0], q[1], q[2], q[3])
    if not ok:
        raise ValueError(f"cannot normalise the quaternion {q.tolist()}")
    return q_unit, J


def dq_dtheta_right(q) -> np.ndarray:
    """(4, 3): d(q * q(theta))/dtheta at theta = 0: how a small rotation theta (rad) in the
    rotated (camera) frame moves q."""
    return quat_left_matrix(q)[:, 1:] * 0.5
