"""The lens models of camera.toml (shared/formats.md), one class each, and their compiled kernels.

A lens model maps an undistorted normalised point ``(x, y) = (X / Z, Y / Z)`` to pixels. Each
is a :class:`LensModel`: its name in camera.toml, its distortion terms (in the order OpenCV lists
them) and what they mean, a numba-compiled kernel for ONE point (scalars in, pixels and their
analytic 2x2 Jacobian out), its inverse (pixels to normalised points, with the Jacobian) and any
rule of its own that :meth:`kinematics.camera.CameraIntrinsics.validate` enforces. :data:`LENSES`
lists them; camera.toml's parsing, validation and saving and every array function of
:mod:`kinematics.camera` go through that table.

Adding a model: write its kernel and class here, add an instance to :data:`LENSES`, and a line
to :func:`_distort_point` (compiled code cannot look a kernel up in a table; a test checks every
model's line). A term no model had before also needs its place in :data:`TERMS` (and a field of
``CameraIntrinsics`` of the same name, which the camera module checks at import).

The array functions of :mod:`kinematics.camera` loop the kernels over points in compiled code,
and runtime.slam calls :func:`project_point_kernel` from its own compiled measurement model, so
the EKF's per-feature path and the public vectorised API share one implementation of every
formula (a single point costs microseconds instead of the ~100 us of numpy's per-call overhead).
The kernels take the camera as (model code, parameter vector), see :func:`lens_kernel_args`;
``error_model="numpy"`` makes a division by zero give inf/NaN instead of raising, as numpy does.
The kernels call only kernels of this file, so numba's on-disk cache (invalidated when this
file changes) is never stale.

Points with no image get NaN (never an exception or a warning), and so do their Jacobians.
"""

from __future__ import annotations

import math
from typing import Mapping

import numba
import numpy as np

#: Distortion terms of all models, in the order of ``CameraIntrinsics``' fields.
TERMS = ("k1", "k2", "k3", "k4", "p1", "p2", "kd1")
#: Order of the kernels' parameter vector (pixels, then the dimensionless / px^-2 terms).
PARAM_ORDER = ("fx", "fy", "cx", "cy") + TERMS
_FX, _FY, _CX, _CY, _K1, _K2, _K3, _K4, _P1, _P2, _KD1 = range(len(PARAM_ORDER))

#: undistort's Newton iteration stops when its step is below this, in normalised coordinates.
#: Newton converges quadratically, so the error left after such a step is far smaller still.
UNDISTORT_TOL = 1e-12
#: ... or after this many iterations, when the unconverged points become NaN.
UNDISTORT_MAX_ITER = 50

_jit = numba.njit(cache=True, error_model="numpy")


def _focal(cam) -> np.ndarray:
    return np.array([cam.fx, cam.fy])


def _centre(cam) -> np.ndarray:
    return np.array([cam.cx, cam.cy])


@_jit
def _to_pixels(p, xd, yd, j00, j01, j10, j11):
    """Apply K to a distorted normalised point and to its 2x2 Jacobian's rows."""
    fx, fy = p[_FX], p[_FY]
    return (xd * fx + p[_CX], yd * fy + p[_CY], j00 * fx, j01 * fx, j10 * fy, j11 * fy)


class LensModel:
    """One lens model (subclass it; one instance goes into :data:`LENSES`).

    name : the model's name in camera.toml. code : the kernels' switch value (its index in
    LENSES). terms : its distortion terms in OpenCV's order (all of :data:`TERMS`). hints : what
    a term means, for error messages (others: a dimensionless coefficient). zero_is_pinhole :
    with every term 0 the model is the pinhole, whose inverse needs no iteration.
    kernel : compiled ``(p, x, y) -> (u, v, du/dx, du/dy, dv/dx, dv/dy)``, pixels, for one
    normalised point and the parameter vector p of :func:`lens_kernel_args`.
    """

    name: str = ""
    code: int = -1
    terms: tuple[str, ...] = ()
    hints: Mapping[str, str] = {}
    zero_is_pinhole: bool = True
    kernel = None

    def check(self, cam) -> tuple[str, str, str] | None:
        """A rule of this model that ``cam`` breaks, as (term, what is wrong, the fix); None if
        none (the terms are already known to be finite numbers)."""
        return None

    def undistort(self, cam, uv: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Normalised points (N, 2) of pixels uv (N, 2, C-contiguous) and, if jac, d(xy)/d(uv)
        (N, 2, 2); NaN for a pixel with no preimage."""
        raise NotImplementedError


class _IterativeLens(LensModel):
    """A model inverted by Newton's method in normalised coordinates (:meth:`solve`). A root
    where the forward Jacobian is not orientation-preserving lies beyond the lens's fold (e.g.
    strong barrel distortion turning back on itself): not a point the lens images."""

    def solve(self, cam, xd: np.ndarray) -> np.ndarray:
        """Undistorted normalised points (N, 2) of distorted ones xd (N, 2); NaN where the
        iteration did not converge."""
        raise NotImplementedError

    def undistort(self, cam, uv, jac):
        xy = self.solve(cam, (uv - _centre(cam)) / _focal(cam))
        _, Jf = distort_points(cam, xy)
        det = Jf[:, 0, 0] * Jf[:, 1, 1] - Jf[:, 0, 1] * Jf[:, 1, 0]
        bad = ~(det > 0)
        xy[bad] = np.nan
        if not jac:
            return xy, None
        # Inverse function theorem: d(xy)/d(uv) = (d(uv)/d(xy))^-1 at the undistorted point.
        J = np.stack([np.stack([Jf[:, 1, 1], -Jf[:, 0, 1]], -1),
                      np.stack([-Jf[:, 1, 0], Jf[:, 0, 0]], -1)], -2) / det[:, None, None]
        J[bad] = np.nan
        return xy, J


# -- brown -------------------------------------------------------------------------------------

@_jit
def _brown_radial(p, r2):
    """The brown model's radial factor ``1 + k1 r^2 + k2 r^4 + k3 r^6`` (r2 = r^2, scalar or
    array)."""
    return 1.0 + r2 * (p[_K1] + r2 * (p[_K2] + r2 * p[_K3]))


@_jit
def _brown_point(p, x, y):
    """Brown-distorted normalised point ``(xd, yd)`` of the normalised point ``(x, y)`` and
    ``d(xd, yd)/d(x, y)`` as ``(j00, j01, j10, j11)``."""
    k1, k2, k3, p1, p2 = p[_K1], p[_K2], p[_K3], p[_P1], p[_P2]
    r2 = x * x + y * y
    radial = _brown_radial(p, r2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d(radial)/d(r2)
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y  # the model's Jacobian is symmetric
    j00 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j11 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, j00, cross, cross, j11


@_jit
def _brown_pixels(p, x, y):
    xd, yd, j00, j01, j10, j11 = _brown_point(p, x, y)
    return _to_pixels(p, xd, yd, j00, j01, j10, j11)


class Brown(_IterativeLens):
    """OpenCV's radial-tangential model, exactly as ``cv2.projectPoints`` with
    ``distCoeffs = [k1, k2, p1, p2, k3]``; inverted by 2-D Newton started at the distorted point."""

    name = "brown"
    code = 0
    terms = ("k1", "k2", "p1", "p2", "k3")
    kernel = staticmethod(_brown_pixels)

    def solve(self, cam, xd):
        p = lens_kernel_args(cam)[1]
        return _brown_solve_many(p, np.ascontiguousarray(xd, float), UNDISTORT_MAX_ITER, UNDISTORT_TOL)


@_jit
def _brown_solve_many(p, xd, max_iter, tol):
    """Brown.solve's Newton iteration, a point at a time (N, 2): NaN where it diverged, did not
    converge in ``max_iter`` steps or landed past the fold."""
    n = xd.shape[0]
    out = np.full((n, 2), np.nan)
    for i in range(n):
        x, y = xd[i, 0], xd[i, 1]
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        converged = False
        for _ in range(max_iter):
            d0, d1, j00, j01, j10, j11 = _brown_point(p, x, y)
            r0, r1 = d0 - xd[i, 0], d1 - xd[i, 1]
            det = j00 * j11 - j01 * j10
            s0 = (j11 * r0 - j01 * r1) / det
            s1 = (j00 * r1 - j10 * r0) / det
            x -= s0
            y -= s1
            size = max(abs(s0), abs(s1))
            if size <= tol:
                converged = True
                break
            if not np.isfinite(size):
                break
        # Past the fold the radial factor can turn negative, mapping points through the centre to
        # the opposite side (with det J > 0 again, so the fold check alone would not catch it).
        if converged and _brown_radial(p, x * x + y * y) > 0:
            out[i, 0], out[i, 1] = x, y
    return out


# -- fisheye -----------------------------------------------------------------------------------

# Below this normalised radius the fisheye scale theta_d / r is 1 to double precision (its
# series is 1 + (k1 - 1/3) r^2 + ...), which is also the cut-off cv2.fisheye uses.
_FISHEYE_SMALL_R = 1e-8


@_jit
def _fisheye_poly(p, theta):
    """theta_d = g(theta) and g'(theta) of the equidistant model (theta scalar or array, rad)."""
    k1, k2, k3, k4 = p[_K1], p[_K2], p[_K3], p[_K4]
    t2 = theta * theta
    g = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    dg = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    return g, dg


@_jit
def _fisheye_point(p, x, y):
    """Fisheye-distorted normalised point ``(x, y) s(r)``, ``s = theta_d / r``, and its Jacobian
    ``(j00, j01, j10, j11)``."""
    r = math.hypot(x, y)
    g, dg = _fisheye_poly(p, math.atan(r))
    if r < _FISHEYE_SMALL_R:
        s = 1.0
        ds_over_r = 2.0 * (p[_K1] - 1.0 / 3.0)   # the limit at r = 0
    else:
        # d(xy s)/d(xy) = s I + (s'(r) / r) xy xy^T, with s'(r) = (g'(theta) / (1 + r^2) - s) / r.
        # The difference loses digits as r -> 0, but it is multiplied by |xy|^2 ~ r^2, so the
        # absolute error of the Jacobian stays at rounding level.
        s = g / r
        ds_over_r = (dg / (1.0 + r * r) - s) / (r * r)
    cross = ds_over_r * x * y
    return x * s, y * s, s + ds_over_r * x * x, cross, cross, s + ds_over_r * y * y


@_jit
def _fisheye_pixels(p, x, y):
    xd, yd, j00, j01, j10, j11 = _fisheye_point(p, x, y)
    return _to_pixels(p, xd, yd, j00, j01, j10, j11)


class Fisheye(_IterativeLens):
    """OpenCV's equidistant model, exactly as ``cv2.fisheye.projectPoints`` with
    ``D = [k1..k4]``: ``theta = atan(r)``, ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``.
    Inverted by 1-D Newton in theta (as cv2.fisheye does); with zero terms it is still
    equidistant, not a pinhole."""

    name = "fisheye"
    code = 1
    terms = ("k1", "k2", "k3", "k4")
    zero_is_pinhole = False
    kernel = staticmethod(_fisheye_pixels)

    def solve(self, cam, xd):
        """r = tan(theta) with g(theta) = |xd|; NaN where it did not converge or theta >= pi/2."""
        p = lens_kernel_args(cam)[1]
        theta_d = np.hypot(xd[:, 0], xd[:, 1])
        theta = theta_d.copy()
        active = np.isfinite(theta_d)
        converged = np.zeros(len(xd), bool)
        for _ in range(UNDISTORT_MAX_ITER):
            idx = np.flatnonzero(active)
            if idx.size == 0:
                break
            g, dg = _fisheye_poly(p, theta[idx])
            step = (g - theta_d[idx]) / dg
            theta[idx] -= step
            # A step d(theta) moves the normalised radius r = tan(theta) by (1 + r^2) d(theta).
            size = np.abs(step) * (1.0 + np.tan(theta[idx]) ** 2)
            done = size <= UNDISTORT_TOL
            converged[idx[done]] = True
            active[idx[done | ~np.isfinite(size)]] = False
        converged &= (theta >= 0) & (theta < np.pi / 2)
        scale = np.where(theta_d > 0, np.tan(theta) / theta_d, 1.0)  # r / theta_d -> 1 as r -> 0
        return np.where(converged[:, None], xd * scale[:, None], np.nan)


# -- radial-sqrt -------------------------------------------------------------------------------

@_jit
def _radial_sqrt_pixels(p, x, y):
    """Pixels ``(u, v)`` of the normalised point ``(x, y)`` through MonoSLAM's radial-sqrt model
    and ``d(uv)/d(xy)`` ``(j00, j01, j10, j11)``, pixels; NaN where ``1 + 2 kd1 r^2 <= 0``."""
    fx, fy, kd1 = p[_FX], p[_FY], p[_KD1]
    ex, ey = x * fx, y * fy  # undistorted offset from (cx, cy), pixels
    q = 1.0 + 2.0 * kd1 * (ex * ex + ey * ey)
    s = 1.0 / math.sqrt(q) if q > 0 else np.nan
    # d(e s)/de = s I - 2 kd1 s^3 e e^T, then de/dxy = diag(fx, fy) scales the columns.
    c = 2.0 * kd1 * s * s * s
    return (p[_CX] + ex * s, p[_CY] + ey * s,
            (s - c * ex * ex) * fx, -c * ex * ey * fy, -c * ey * ex * fx, (s - c * ey * ey) * fy)


class RadialSqrt(LensModel):
    """MonoSLAM's one-parameter model with ``kd1`` in pixels^-2, applied in pixels about (cx, cy):
    ``d = c + (p - c) / sqrt(1 + 2 kd1 r^2)``; its exact inverse is
    ``p = c + (d - c) / sqrt(1 - 2 kd1 r_d^2)``, which must exist over the whole image."""

    name = "radial-sqrt"
    code = 2
    terms = ("kd1",)
    hints = {"kd1": "radial-sqrt distortion in pixels^-2, e.g. 1e-6; 0 for none"}
    kernel = staticmethod(_radial_sqrt_pixels)

    def check(self, cam):
        if cam.kd1 <= 0:
            return None
        # The inverse divides by sqrt(1 - 2 kd1 r_d^2): it must stay positive over the whole
        # image, whose farthest points from (cx, cy) are its outer corners (pixel edges).
        corners = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5],
                            [-0.5, cam.height - 0.5], [cam.width - 0.5, cam.height - 0.5]])
        rd2 = np.sum((corners - [cam.cx, cam.cy]) ** 2, axis=1)
        worst = int(np.argmax(rd2))
        margin = 1.0 - 2.0 * cam.kd1 * rd2[worst]
        if margin > 0:
            return None
        u, v = corners[worst]
        return ("kd1", f"is too large for a {cam.width}x{cam.height} image",
                f"1 - 2 kd1 r_d^2 = {margin:.3g} at the corner ({u:g}, {v:g}), so the lens has no "
                f"inverse there; use kd1 < {1.0 / (2.0 * rd2[worst]):.6g}")

    def undistort(self, cam, uv, jac):
        d = uv - _centre(cam)  # distorted offset, pixels
        w = 1.0 - 2.0 * cam.kd1 * np.sum(d * d, axis=1)
        t = 1.0 / np.sqrt(np.where(w > 0, w, np.nan))
        xy = d * t[:, None] / _focal(cam)
        if not jac:
            return xy, None
        # d(d t)/dd = t I + 2 kd1 t^3 d d^T, then xy = (.)/f scales the rows.
        J = t[:, None, None] * np.eye(2) + (2.0 * cam.kd1 * t**3)[:, None, None] * d[:, :, None] * d[:, None, :]
        return xy, J / _focal(cam)[None, :, None]


# -- the table ---------------------------------------------------------------------------------

#: Every lens model by its camera.toml name, in code order.
LENSES: dict[str, LensModel] = {m.name: m for m in (Brown(), Fisheye(), RadialSqrt())}
assert [m.code for m in LENSES.values()] == list(range(len(LENSES))), "lens codes must be 0, 1, ... in order"
assert all(t in TERMS for m in LENSES.values() for t in m.terms), "a lens term missing from TERMS"

#: Model codes the kernels switch on (a string cannot be passed cheaply into compiled code).
BROWN, FISHEYE, RADIAL_SQRT = (LENSES[n].code for n in ("brown", "fisheye", "radial-sqrt"))


@_jit
def _distort_point(model, p, x, y):
    """Pixels ``(u, v)`` of the undistorted normalised point ``(x, y)`` through the lens model,
    and ``d(uv)/d(xy)`` ``(j00, j01, j10, j11)``, pixels. One line per model of LENSES."""
    if model == BROWN:
        return _brown_pixels(p, x, y)
    if model == FISHEYE:
        return _fisheye_pixels(p, x, y)
    if model == RADIAL_SQRT:
        return _radial_sqrt_pixels(p, x, y)
    return np.nan, np.nan, np.nan, np.nan, np.nan, np.nan


@_jit
def project_point_kernel(model, p, X, Y, Z):
    """Pixels ``(u, v)`` of the optical-frame point ``(X, Y, Z)`` (m) and ``d(uv)/d(X, Y, Z)``
    as six numbers ``(j00, j01, j02, j10, j11, j12)``, px/m; all NaN when ``Z <= 0`` (or NaN).

    Compiled (numba): call it from other compiled code with ``lens_kernel_args(cam)``; from
    Python use :func:`kinematics.camera.project_jacobian`, which loops it over points."""
    if not Z > 0:
        return np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan
    x, y = X / Z, Y / Z
    u, v, a, b, c, d = _distort_point(model, p, x, y)
    # d(X/Z, Y/Z)/d(X, Y, Z) = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]], composed with the lens's 2x2.
    iz = 1.0 / Z
    return (u, v, a * iz, b * iz, -(a * x + b * y) * iz, c * iz, d * iz, -(c * x + d * y) * iz)


@_jit
def _distort_many(model, p, xy):
    """(N, 2) pixels and (N, 2, 2) d(uv)/d(xy) of the (N, 2) normalised points."""
    n = xy.shape[0]
    uv = np.empty((n, 2))
    J = np.empty((n, 2, 2))
    for i in range(n):
        uv[i, 0], uv[i, 1], J[i, 0, 0], J[i, 0, 1], J[i, 1, 0], J[i, 1, 1] = \
            _distort_point(model, p, xy[i, 0], xy[i, 1])
    return uv, J


@_jit
def _project_many(model, p, P):
    """(N, 2) pixels and (N, 2, 3) d(uv)/d(P) of the (N, 3) optical-frame points."""
    n = P.shape[0]
    uv = np.empty((n, 2))
    J = np.empty((n, 2, 3))
    for i in range(n):
        (uv[i, 0], uv[i, 1], J[i, 0, 0], J[i, 0, 1], J[i, 0, 2],
         J[i, 1, 0], J[i, 1, 1], J[i, 1, 2]) = project_point_kernel(model, p, P[i, 0], P[i, 1], P[i, 2])
    return uv, J


def lens_kernel_args(cam) -> tuple[int, np.ndarray]:
    """``(model code, parameters (11,))`` of a CameraIntrinsics for the compiled lens kernels
    (:func:`project_point_kernel` and friends), parameters in the order of :data:`PARAM_ORDER`.

    Computed once per camera and kept on it (the camera is immutable); do not modify the array.
    """
    args = cam.__dict__.get("_lens_kernel_args")
    if args is None:
        args = (LENSES[cam.model].code, np.array([getattr(cam, name) for name in PARAM_ORDER], dtype=np.float64))
        # A frozen dataclass refuses setattr; the cache is not a field (equality, hashing,
        # to_dict and replace() never see it), so writing it into __dict__ is safe.
        cam.__dict__["_lens_kernel_args"] = args
    return args


def distort_points(cam, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of normalised points xy (N, 2, C-contiguous float64) and d(uv)/d(xy)
    (N, 2, 2), through cam's lens model."""
    model, p = lens_kernel_args(cam)
    return _distort_many(model, p, xy)


def project_points(cam, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of optical-frame points P (N, 3, C-contiguous float64, metres) and
    d(uv)/d(P) (N, 2, 3), px/m; NaN for Z <= 0."""
    model, p = lens_kernel_args(cam)
    return _project_many(model, p, P)


def undistort_points(cam, uv: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Normalised points (N, 2) of pixels uv (N, 2, C-contiguous float64) and, if jac,
    d(xy)/d(uv) (N, 2, 2); NaN where the lens has no preimage."""
    lens = LENSES[cam.model]
    if lens.zero_is_pinhole and not any(getattr(cam, t) for t in lens.terms):
        # Every term zero: the pinhole, inverted exactly without iteration.
        xy = (uv - _centre(cam)) / _focal(cam)
        J = np.broadcast_to(np.diag(1.0 / _focal(cam)), (len(uv), 2, 2)).copy() if jac else None
        return xy, J
    return lens.undistort(cam, uv, jac)
