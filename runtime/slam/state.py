"""The MonoSLAM state: its layout (written once, here), the quaternion convention, the filter's
parameters and the covariance guard.

State vector (SI units)
-----------------------
``x = [x_v, y_0, y_1, ..., y_{N-1}]``, ``n = 13 + 3 N`` numbers, with one full covariance
``P`` (n, n) (a single EKF over camera and map, as in MonoSLAM).

camera block ``x_v`` (13), indices 0..12:

====== ======= ==========================================================================
slice  symbol  meaning
====== ======= ==========================================================================
0:3    r       position of the camera's optical centre in the world frame, m
3:7    q       unit quaternion, **w x y z order**, rotating camera (optical frame: x right,
               y down, z forward) coordinates into the world frame: ``p_world = R(q) p_cam
               + r``. (TUM files store the same rotation in x y z w order; scipy's Rotation
               also uses x y z w.)
7:10   v       linear velocity of the optical centre, world frame, m/s
10:13  w       angular velocity, **camera (optical) frame**, rad/s, as in MonoSLAM: the
               motion model composes on the right, ``q_new = q * q(w dt)``
====== ======= ==========================================================================

feature ``k`` (0-based), indices ``13 + 3k .. 13 + 3k + 2``: a 3D point in the world frame, m.
Removing feature ``k`` shifts every later feature down by one index.

Quaternions
-----------
``q = (w, x, y, z)``; the product is Hamilton's, ``(q * p)`` applies ``p`` first:
``R(q * p) = R(q) R(p)``. :func:`quat_to_rotation` uses the homogeneous quadratic formula
(``R(s q) = s^2 R(q)``, no normalisation inside), so it and its derivative
:func:`rotation_derivatives` are defined on all of R^4; every Jacobian in this package with
respect to ``q`` treats its four components as independent variables of that formula
(finite differences perturb them one at a time, without renormalising). The norm is kept at 1
by an explicit renormalisation step with its own Jacobian (motion.py).

Covariance and the quaternion's norm direction
----------------------------------------------
Renormalising ``q`` multiplies the covariance by ``J = (I - q q^T)`` (at ``|q| = 1``), which
removes the variance along ``q`` itself. ``P`` is therefore positive *semi*-definite with one
exact null direction (the norm of ``q``, which no measurement sees because a projection is
invariant to scaling the point); restricted to the other ``n - 1`` directions it is positive
definite. :func:`check_covariance` accepts eigenvalues down to ``-psd_rel_tol * max(diag P)``
(rounding) and rejects anything more negative, and any NaN or Inf, with a message naming the
problem.
"""

from __future__ import annotations

import hashlib
import inspect
import math
from dataclasses import dataclass, fields
from pathlib import Path

import numba
import numpy as np
import scipy.linalg

# ---------------------------------------------------------------------------------------------
# Compiled kernels
# ---------------------------------------------------------------------------------------------

# Source files each kernel made by compiled_kernel is built from (its own and its callees').
_KERNEL_SOURCES: dict = {}


def compiled_kernel(*callees):
    """Decorator: ``numba.njit(cache=True, error_model="numpy")`` for a kernel of this package,
    which may call the compiled functions ``callees`` of other modules.

    numba's on-disk cache is invalidated only when the kernel's own file changes, yet a kernel's
    machine code contains its callees: after an edit to, say, a lens model in
    kinematics/camera.py, the cached measurement kernel would go on projecting with the old one.
    So the cache's freshness stamp is extended with the content of every file the kernel is built
    from (its own, its callees', and theirs, transitively). The stamp is numba's internal API; if
    this numba has none, kernels with callees elsewhere are compiled without an on-disk cache
    (correct, only slower to start). ``error_model="numpy"``: a division by zero gives inf/NaN
    instead of raising, as in numpy.
    """
    def decorate(fn):
        files = {inspect.getsourcefile(fn)}
        for c in callees:
            files |= _KERNEL_SOURCES.get(c) or {inspect.getsourcefile(c.py_func)}
        kernel = numba.njit(cache=True, error_model="numpy")(fn)
        if len(files) > 1:
            cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
            if hasattr(cache_file, "_source_stamp"):
                digest = hashlib.sha256(b"".join(Path(f).read_bytes() for f in sorted(files))).hexdigest()
                cache_file._source_stamp = (cache_file._source_stamp, digest)
            else:
                kernel = numba.njit(error_model="numpy")(fn)
        _KERNEL_SOURCES[kernel] = frozenset(files)
        return kernel
    return decorate


# ---------------------------------------------------------------------------------------------
# Layout
# ---------------------------------------------------------------------------------------------

CAMERA_DIM = 13  #: numbers in the camera block x_v
FEATURE_DIM = 3  #: numbers per point feature
NOISE_DIM = 6  #: the impulse n = (V, Omega) = dt (a, alpha) of the motion model

R_SLICE = slice(0, 3)  #: r, optical centre, world, m
Q_SLICE = slice(3, 7)  #: q, w x y z, camera -> world
V_SLICE = slice(7, 10)  #: v, world, m/s
W_SLICE = slice(10, 13)  #: w, camera frame, rad/s
CAMERA_SLICE = slice(0, CAMERA_DIM)


def feature_start(k: int) -> int:
    """Index of the first number of feature ``k`` in the state vector."""
    return CAMERA_DIM + FEATURE_DIM * int(k)


def feature_slice(k: int) -> slice:
    """Slice of feature ``k`` (0-based) in the state vector."""
    s = feature_start(k)
    return slice(s, s + FEATURE_DIM)


def feature_indices(ks) -> np.ndarray:
    """(len(ks), 3) int array: the state indices of each feature in ``ks``."""
    ks = np.asarray(ks, dtype=np.intp).reshape(-1)
    return CAMERA_DIM + FEATURE_DIM * ks[:, None] + np.arange(FEATURE_DIM)[None, :]


def state_size(n_features: int) -> int:
    """Length of the state vector with ``n_features`` point features."""
    return CAMERA_DIM + FEATURE_DIM * int(n_features)


def count_features(n: int) -> int:
    """Number of features in a state vector of length ``n``; ValueError if ``n`` is not 13 + 3N."""
    if n < CAMERA_DIM or (n - CAMERA_DIM) % FEATURE_DIM:
        raise ValueError(f"a MonoSLAM state has 13 + 3 N numbers, got {n}")
    return (n - CAMERA_DIM) // FEATURE_DIM


# ---------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SlamConfig:
    """Every tunable number of the filter.

    sigma_a : standard deviation of the linear acceleration impulse, m/s^2 (MonoSLAM's
        hand-held value is 4). The velocity impulse per step is ``V = a dt``, variance
        ``(sigma_a dt)^2`` per axis.
    sigma_alpha : standard deviation of the angular acceleration impulse, rad/s^2 (MonoSLAM:
        6); ``Omega = alpha dt``, variance ``(sigma_alpha dt)^2`` per axis (camera frame).
    sigma_pixel : standard deviation of a feature's image measurement, pixels, per axis
        (:attr:`R_pix` is the matching 2x2 covariance, px^2).
    imu_accel_noise, imu_gyro_noise : noise densities of the IMU's specific force
        (m/s^2/sqrt(Hz)) and rate (rad/s/sqrt(Hz)) when an IMU drives the prediction
        (inertial.py): about twice a good MEMS IMU's (0.0015 and 0.00015, the twin's), for the
        samples' zero-order hold. They assume a calibrated IMU (biases removed); for a raw
        one, turn on MapSettings.bias_time_s. On the twin's walk, 0.01 and 0.001 gave 2.9 cm
        ATE against 0.6 cm.
    psd_rel_tol : the covariance guard accepts eigenvalues down to
        ``-psd_rel_tol * max(diag P)`` (rounding, and the quaternion's null direction).
    check_psd : run the positive-semi-definiteness check (a Cholesky factorisation of
        ``P + tol I``, O(n^3 / 3)) in the guard; finiteness and symmetry are always enforced.
    """

    sigma_a: float = 4.0
    sigma_alpha: float = 6.0
    imu_accel_noise: float = 0.003
    imu_gyro_noise: float = 0.0003
    sigma_pixel: float = 1.0
    psd_rel_tol: float = 1e-9
    check_psd: bool = True

    def __post_init__(self):
        for f in fields(self):
            if f.name == "check_psd":
                continue
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"SlamConfig.{f.name} = {v!r} must be a finite number >= 0")

    @property
    def R_pix(self) -> np.ndarray:
        """(2, 2) pixel measurement covariance, px^2: sigma_pixel^2 I."""
        return self.sigma_pixel**2 * np.eye(2)


DEFAULT_CONFIG = SlamConfig()


# ---------------------------------------------------------------------------------------------
# Quaternions (w x y z), see the module docstring
# ---------------------------------------------------------------------------------------------

def quat_multiply(q, p) -> np.ndarray:
    """Hamilton product ``q * p`` of two (4,) quaternions in w x y z order."""
    return quat_left_matrix(q) @ np.asarray(p, dtype=float)


@compiled_kernel()
def quat_left_kernel(w, x, y, z):
    """(4, 4) L(q) of :func:`quat_left_matrix`, from the four components."""
    return np.array([[w, -x, -y, -z],
                     [x, w, -z, y],
                     [y, z, w, -x],
                     [z, -y, x, w]])


@compiled_kernel()
def quat_right_kernel(w, x, y, z):
    """(4, 4) M(p) of :func:`quat_right_matrix`, from the four components."""
    return np.array([[w, -x, -y, -z],
                     [x, w, z, -y],
                     [y, -z, w, x],
                     [z, y, -x, w]])


def quat_left_matrix(q) -> np.ndarray:
    """(4, 4) ``L(q)`` with ``q * p = L(q) p`` (so ``d(q * p)/dp = L(q)``)."""
    w, x, y, z = q
    return quat_left_kernel(float(w), float(x), float(y), float(z))


def quat_right_matrix(p) -> np.ndarray:
    """(4, 4) ``M(p)`` with ``q * p = M(p) q`` (so ``d(q * p)/dq = M(p)``)."""
    w, x, y, z = p
    return quat_right_kernel(float(w), float(x), float(y), float(z))


def quat_conjugate(q) -> np.ndarray:
    """(w, -x, -y, -z): the inverse of a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return np.array([q[0], -q[1], -q[2], -q[3]])


# R(q) and dR/dq are compiled (numba) because the measurement model calls them from its own
# compiled kernel (measurement.py); the public functions below are thin wrappers around the same
# code, so each formula is written once.

@compiled_kernel()
def rotation_kernel(w, x, y, z):
    """(3, 3) R(q) of :func:`quat_to_rotation`, from the four components."""
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
    """(4, 3, 3) dR/dq_i of :func:`rotation_derivatives`, from the four components."""
    D = np.empty((4, 3, 3))
    # d/dw
    D[0, 0, 0], D[0, 0, 1], D[0, 0, 2] = w, -z, y
    D[0, 1, 0], D[0, 1, 1], D[0, 1, 2] = z, w, -x
    D[0, 2, 0], D[0, 2, 1], D[0, 2, 2] = -y, x, w
    # d/dx
    D[1, 0, 0], D[1, 0, 1], D[1, 0, 2] = x, y, z
    D[1, 1, 0], D[1, 1, 1], D[1, 1, 2] = y, -x, -w
    D[1, 2, 0], D[1, 2, 1], D[1, 2, 2] = z, w, -x
    # d/dy
    D[2, 0, 0], D[2, 0, 1], D[2, 0, 2] = -y, x, w
    D[2, 1, 0], D[2, 1, 1], D[2, 1, 2] = x, y, z
    D[2, 2, 0], D[2, 2, 1], D[2, 2, 2] = -w, z, -y
    # d/dz
    D[3, 0, 0], D[3, 0, 1], D[3, 0, 2] = -z, -w, x
    D[3, 1, 0], D[3, 1, 1], D[3, 1, 2] = w, -z, y
    D[3, 2, 0], D[3, 2, 1], D[3, 2, 2] = x, y, z
    return 2.0 * D


def quat_to_rotation(q) -> np.ndarray:
    """(3, 3) ``R(q)`` by the homogeneous quadratic formula (a rotation when ``|q| = 1``;
    ``R(s q) = s^2 R(q)``). ``R`` maps camera coordinates to world coordinates."""
    w, x, y, z = q
    return rotation_kernel(float(w), float(x), float(y), float(z))


def rotation_derivatives(q) -> np.ndarray:
    """(4, 3, 3): ``dR(q)/dq_i`` for i = w, x, y, z, of :func:`quat_to_rotation`.
    (Transpose each to get ``dR(q)^T / dq_i``.)"""
    w, x, y, z = q
    return rotation_derivatives_kernel(float(w), float(x), float(y), float(z))


# Below this rotation angle (rad) the rotation-vector maps use their Taylor series; at 1e-3
# the first neglected terms are ~1e-17, below double-precision rounding of the O(1) terms.
_SMALL_ANGLE = 1e-3


@compiled_kernel()
def rotvec_to_quat_jacobian_kernel(t0, t1, t2):
    """q(theta) (4,) and dq/dtheta (4, 3) of :func:`rotvec_to_quat_jacobian`, from theta's components."""
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
    J[0] = -0.5 * s * theta                          # d cos(a/2) = -sin(a/2)/2 * theta/a
    J[1:] = s * np.eye(3) + ds_over_a * np.outer(theta, theta)
    return q, J


def rotvec_to_quat_jacobian(theta) -> tuple[np.ndarray, np.ndarray]:
    """``q(theta) = (cos(a/2), sin(a/2) theta / a)``, ``a = |theta|`` (rad), and its (4, 3)
    Jacobian ``dq/dtheta``; exact (series) at and near ``theta = 0``, where ``dq/dtheta =
    [0; I/2]``."""
    t0, t1, t2 = np.asarray(theta, dtype=float).reshape(3)
    return rotvec_to_quat_jacobian_kernel(float(t0), float(t1), float(t2))


def rotvec_to_quat(theta) -> np.ndarray:
    """Rotation vector (rad) to unit quaternion, w x y z."""
    return rotvec_to_quat_jacobian(theta)[0]


def quat_to_rotvec(q) -> np.ndarray:
    """Unit quaternion (w x y z) to rotation vector (rad), angle in [0, pi]."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    v = q[1:]
    sv = float(np.linalg.norm(v))
    if sv < 1e-12:
        return 2.0 * v / q[0]
    return 2.0 * math.atan2(sv, q[0]) * v / sv


# ---------------------------------------------------------------------------------------------
# The covariance guard
# ---------------------------------------------------------------------------------------------

class SlamNumericalError(FloatingPointError):
    """The filter would put NaN/Inf into the state, or the covariance stopped being symmetric
    positive semi-definite. The message names the step and the problem; the state is left as it
    was before the failing step."""


def _where(where: str) -> str:
    return f" after {where}" if where else ""


def check_mean(x: np.ndarray, where: str = "") -> np.ndarray:
    """Raise :class:`SlamNumericalError` if the state vector has NaN/Inf; return it."""
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise SlamNumericalError(f"state mean x has NaN/Inf{_where(where)} at indices "
                                 f"{bad[:8].tolist()}{' ...' if bad.size > 8 else ''} "
                                 f"({_describe_index(int(bad[0]))})")
    return x


#: Tile edge of _symmetric_and_finite: a tile read by rows and its mirror read by columns stay in
#: cache together (numpy's ``P + P.T`` walks the transpose against the cache, several times
#: slower than a copy at n ~ 900).
_TILE = 32


@compiled_kernel()
def _symmetric_and_finite(P):
    """Whether the square C-contiguous ``P`` is exactly symmetric with every entry finite (one
    tiled pass over the upper triangle and its mirror, stopping after the first failing tile)."""
    n = P.shape[0]
    for i0 in range(0, n, _TILE):
        for j0 in range(i0, n, _TILE):
            ok = True                     # no branch in the inner loop, so it vectorises
            for i in range(i0, min(i0 + _TILE, n)):
                for j in range(max(j0, i), min(j0 + _TILE, n)):
                    a = P[i, j]
                    ok &= (a == P[j, i]) & (a - a == 0.0)     # a - a is NaN for NaN/Inf
            if not ok:
                return False
    return True


def check_covariance(P: np.ndarray, where: str = "", cfg: SlamConfig = DEFAULT_CONFIG) -> np.ndarray:
    """The symmetric-PSD guard: return ``(P + P^T) / 2`` after checking it (``P`` itself when it
    is already exactly symmetric, as the filter's steps keep it).

    Raises :class:`SlamNumericalError` naming the problem if ``P`` is not square, has NaN/Inf,
    has a negative variance on its diagonal, or (``cfg.check_psd``) has an eigenvalue below
    ``-cfg.psd_rel_tol * max(diag P)`` (tested by a Cholesky factorisation of ``P + tol I``; the
    message then reports the smallest eigenvalue).
    """
    P = np.asarray(P, dtype=float)
    if P.ndim != 2 or P.shape[0] != P.shape[1]:
        raise SlamNumericalError(f"covariance P{_where(where)} must be square, got shape {P.shape}")
    if not (P.flags.c_contiguous and _symmetric_and_finite(P)):
        finite = np.isfinite(P)
        if not finite.all():
            i, j = np.argwhere(~finite)[0]
            raise SlamNumericalError(f"covariance P has NaN/Inf{_where(where)}, first at ({i}, {j}) "
                                     f"({_describe_index(int(i))} / {_describe_index(int(j))})")
        P = 0.5 * (P + P.T)
    d = np.diag(P)
    scale = float(d.max()) if d.size else 0.0
    tol = cfg.psd_rel_tol * max(scale, np.finfo(float).tiny)
    if d.size and d.min() < -tol:
        i = int(np.argmin(d))
        raise SlamNumericalError(f"covariance P has a negative variance P[{i},{i}] = {d[i]:.3g}"
                                 f"{_where(where)} ({_describe_index(i)})")
    if cfg.check_psd and d.size:
        Pt = P.copy()
        Pt.flat[::len(Pt) + 1] += tol
        # LAPACK's Cholesky on the copy, in place: Pt is symmetric, so its C-order buffer read
        # as Fortran order (Pt.T, no copy) is the same matrix. (Measured ~4x faster than
        # np.linalg.cholesky at n = 313 with this environment's OpenBLAS builds.)
        _, info = scipy.linalg.lapack.dpotrf(Pt.T, lower=1, overwrite_a=1, clean=0)
        if info < 0:
            raise ValueError(f"dpotrf: illegal argument {-info}")
        if info > 0:   # a leading minor is not positive definite
            lam = np.linalg.eigvalsh(P)
            raise SlamNumericalError(
                f"covariance P is not positive semi-definite{_where(where)}: smallest eigenvalue "
                f"{lam[0]:.3g} < -{tol:.3g} (psd_rel_tol {cfg.psd_rel_tol:g} x max variance "
                f"{scale:.3g})")
    return P


def _describe_index(i: int) -> str:
    for name, sl in (("r", R_SLICE), ("q", Q_SLICE), ("v", V_SLICE), ("w", W_SLICE)):
        if sl.start <= i < sl.stop:
            return f"camera {name}"
    return f"feature {(i - CAMERA_DIM) // FEATURE_DIM}"


# ---------------------------------------------------------------------------------------------
# The container
# ---------------------------------------------------------------------------------------------

@dataclass
class State:
    """Mean ``x`` (n,) and full covariance ``P`` (n, n) of camera and map (layout above).

    Build with ``State(x, P)`` or :meth:`from_camera`; add and remove features with
    :meth:`add_feature` and :meth:`remove_feature`. The arrays are owned (copied on
    construction) and replaced, not resized in place, by the filter steps.
    """

    x: np.ndarray
    P: np.ndarray

    def __post_init__(self):
        self.x = np.array(self.x, dtype=float).reshape(-1)
        self.P = np.array(self.P, dtype=float)
        n = len(self.x)
        count_features(n)
        if self.P.shape != (n, n):
            raise ValueError(f"P must have shape ({n}, {n}) for a state of {n} numbers, got {self.P.shape}")
        check_mean(self.x, "construction")
        self.P = check_covariance(self.P, "construction", DEFAULT_CONFIG)

    @classmethod
    def from_camera(cls, x_v, P_vv) -> "State":
        """A state with no features: camera block (13,) and its (13, 13) covariance."""
        x_v = np.asarray(x_v, dtype=float).reshape(-1)
        if x_v.shape != (CAMERA_DIM,):
            raise ValueError(f"x_v must have {CAMERA_DIM} numbers (r, q wxyz, v, w), got {x_v.shape}")
        return cls(x_v, P_vv)

    def copy(self) -> "State":
        return State(self.x.copy(), self.P.copy())

    # -- views --
    @property
    def n(self) -> int:
        return len(self.x)

    @property
    def n_features(self) -> int:
        return (len(self.x) - CAMERA_DIM) // FEATURE_DIM

    @property
    def x_v(self) -> np.ndarray:
        """(13,) camera block (a view)."""
        return self.x[CAMERA_SLICE]

    @property
    def r(self) -> np.ndarray:
        return self.x[R_SLICE]

    @property
    def q(self) -> np.ndarray:
        return self.x[Q_SLICE]

    @property
    def v(self) -> np.ndarray:
        return self.x[V_SLICE]

    @property
    def w(self) -> np.ndarray:
        return self.x[W_SLICE]

    def feature(self, k: int) -> np.ndarray:
        """(3,) world position of feature ``k`` (a view)."""
        return self.x[feature_slice(self._check_k(k))]

    @property
    def features(self) -> np.ndarray:
        """(N, 3) all feature positions (a view)."""
        return self.x[CAMERA_DIM:].reshape(-1, FEATURE_DIM)

    def _check_k(self, k) -> int:
        if not (0 <= int(k) < self.n_features):
            raise IndexError(f"feature {k} does not exist (the map has {self.n_features})")
        return int(k)

    # -- map management --
    def add_feature(self, y, P_yy, P_yx, cfg: SlamConfig = DEFAULT_CONFIG) -> int:
        """Append a point feature and return its index ``k``.

        y : (3,) world position, m. P_yy : (3, 3) its covariance. P_yx : (3, n) its
        cross-covariance with the current state (camera and existing features), in state order.
        The grown covariance is checked by the guard; on failure nothing changes.
        """
        n = self.n
        y = np.asarray(y, dtype=float).reshape(-1)
        P_yy = np.asarray(P_yy, dtype=float)
        P_yx = np.asarray(P_yx, dtype=float)
        if y.shape != (FEATURE_DIM,) or P_yy.shape != (3, 3) or P_yx.shape != (3, n):
            raise ValueError(f"add_feature needs y (3,), P_yy (3, 3), P_yx (3, {n}); got "
                             f"{y.shape}, {P_yy.shape}, {P_yx.shape}")
        x_new = check_mean(np.concatenate([self.x, y]), "add_feature")
        P_new = np.empty((n + 3, n + 3))
        P_new[:n, :n] = self.P
        P_new[n:, :n] = P_yx
        P_new[:n, n:] = P_yx.T
        P_new[n:, n:] = P_yy
        self.P = check_covariance(P_new, "add_feature", cfg)
        self.x = x_new
        return self.n_features - 1

    def remove_feature(self, k: int) -> None:
        """Delete feature ``k``: its 3 entries of ``x`` and 3 rows and columns of ``P``. Later
        features shift down one index."""
        keep = np.ones(self.n, bool)
        keep[feature_slice(self._check_k(k))] = False
        self.x = self.x[keep]
        self.P = self.P[np.ix_(keep, keep)]

    def guard(self, where: str = "", cfg: SlamConfig = DEFAULT_CONFIG) -> None:
        """Run :func:`check_mean` and :func:`check_covariance` (symmetrising ``P`` in place)."""
        check_mean(self.x, where)
        self.P = check_covariance(self.P, where, cfg)
