"""Camera intrinsics and the lens models of shared/formats.md (camera.toml), with Jacobians.

Frames and units
----------------
optical frame
    x right, y down, z forward along the optic axis (OpenCV / TUM), metres.
normalised point
    ``(x, y) = (X / Z, Y / Z)`` of a point ``(X, Y, Z)`` in the optical frame, before distortion.
pixels
    OpenCV convention: the centre of pixel (0, 0) is at (0, 0), so the image spans
    ``-0.5 .. width - 0.5`` by ``-0.5 .. height - 0.5``.

Lens models (each maps an undistorted normalised point to pixels)
-----------------------------------------------------------------
``brown``
    OpenCV's radial-tangential model, exactly as ``cv2.projectPoints`` with
    ``distCoeffs = [k1, k2, p1, p2, k3]``.
``fisheye``
    OpenCV's equidistant model, exactly as ``cv2.fisheye.projectPoints`` with ``D = [k1..k4]``:
    ``theta = atan(r)``, ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``.
``radial-sqrt``
    MonoSLAM's one-parameter model with ``kd1`` in pixels^-2, applied in pixels about (cx, cy):
    ``d = c + (p - c) / sqrt(1 + 2 kd1 r^2)``; its exact inverse is
    ``p = c + (d - c) / sqrt(1 - 2 kd1 r_d^2)``.

Points that have no image
-------------------------
The array functions never raise (or warn) for individual points; such a point gets NaN, and so
does its Jacobian:

- :func:`project`: the point is on or behind the camera plane (``Z <= 0``);
- :func:`distort`: radial-sqrt only, outside the model's domain (``1 + 2 kd1 r^2 <= 0``);
- :func:`undistort`: Newton did not converge (no preimage), or its root lies beyond the fold of
  a brown/fisheye lens, where the model stops being one-to-one; for radial-sqrt,
  ``1 - 2 kd1 r_d^2 <= 0`` (never inside the image: :meth:`CameraIntrinsics.validate` checks).

Like OpenCV, brown and fisheye :func:`distort` return a value even past the fold; use
:func:`in_image` and ``np.isfinite(uv).all(axis=1)`` to select usable points.

Every function that has a derivative sits next to its ``*_jacobian`` twin, which returns the same
values plus the analytic Jacobian (the MonoSLAM ``f_and_df`` pattern).

Each lens model is one numba-compiled kernel for a single point (see "Lens models" below), looped
over points by the array functions and called directly by the SLAM measurement model.
"""

from __future__ import annotations

import difflib
import functools
import json
import math
import numbers
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Mapping

import numba
import numpy as np
import tomli_w

from .tomlfile import read_toml

#: Distortion terms each lens model takes, in the order OpenCV lists them.
LENS_MODELS: dict[str, tuple[str, ...]] = {
    "brown": ("k1", "k2", "p1", "p2", "k3"),
    "fisheye": ("k1", "k2", "k3", "k4"),
    "radial-sqrt": ("kd1",),
}
_ALL_TERMS = ("k1", "k2", "k3", "k4", "p1", "p2", "kd1")
#: The largest image side (px) a camera may have: MuJoCo's offscreen buffer and every reader
#: allocate whole frames, and no camera here comes near it.
MAX_IMAGE_SIDE = 8192
_REQUIRED = ("width", "height", "fx", "fy", "cx", "cy")

#: undistort's Newton iteration stops when its step is below this, in normalised coordinates.
#: Newton converges quadratically, so the error left after such a step is far smaller still.
UNDISTORT_TOL = 1e-12
#: ... or after this many iterations, when the unconverged points become NaN.
UNDISTORT_MAX_ITER = 50

# What each field means, appended to error messages so the user knows what to write.
_HINTS = {
    "width": "image width in pixels, e.g. 640",
    "height": "image height in pixels, e.g. 480",
    "fx": "focal length in pixels, e.g. 514.7",
    "fy": "focal length in pixels, e.g. 514.7",
    "cx": "principal point in pixels, OpenCV convention, e.g. 319.5 for a 640-wide image",
    "cy": "principal point in pixels, OpenCV convention, e.g. 239.5 for a 480-high image",
    "model": 'lens model: "brown", "fisheye" or "radial-sqrt"',
    "kd1": "radial-sqrt distortion in pixels^-2, e.g. 1e-6; 0 for none",
}
_TERM_HINT = "dimensionless distortion coefficient; 0 for none"


class CameraFileError(ValueError):
    """A camera.toml (or CameraIntrinsics) that cannot be used; a one-line message naming the
    file, the field and the fix."""


def _show(v) -> str:
    """A value as the user typed it, on one line and short."""
    if _is_int(v):
        v = int(v)  # numpy scalars print as np.int64(...) otherwise
    elif _is_real(v):
        v = float(v)
    s = json.dumps(v) if isinstance(v, str) else repr(v)
    s = s.replace("\n", " ")
    return s if len(s) <= 60 else s[:57] + "..."


def _is_real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _is_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics plus one lens model (see the module docstring and formats.md).

    width, height : image size in pixels.
    fx, fy : focal lengths in pixels.
    cx, cy : principal point in pixels (OpenCV convention: pixel (0, 0) is centred at (0, 0)).
    model : ``"brown"``, ``"fisheye"`` or ``"radial-sqrt"``.
    k1, k2, k3, k4, p1, p2, kd1 : distortion terms. Only the terms of ``model``
        (:data:`LENS_MODELS`) may be nonzero; ``k3`` is the r^6 term for brown and the
        theta^6 term for fisheye. ``kd1`` is in pixels^-2, the others are dimensionless.

    Instances are validated on construction, so every CameraIntrinsics is usable.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str = "brown"
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    kd1: float = 0.0

    def __post_init__(self):
        self.validate()
        # Normalise numeric types (numpy scalars, TOML ints for floats) so that equality,
        # hashing and tomli_w all see plain Python numbers.
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("width", "height"):
                object.__setattr__(self, f.name, int(v))
            elif f.name != "model":
                object.__setattr__(self, f.name, float(v))

    # -- derived --
    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> dict[str, float]:
        """The terms of this camera's model, in OpenCV order (e.g. brown: k1 k2 p1 p2 k3)."""
        return {t: getattr(self, t) for t in LENS_MODELS[self.model]}

    # -- validation --
    def validate(self, source: str | None = None) -> "CameraIntrinsics":
        """Check every rule of formats.md; raise :class:`CameraFileError` on the first broken one.

        ``source`` (a file name) prefixes the message. Returns ``self`` for chaining.
        """
        try:
            self._check()
        except CameraFileError as e:
            if source is None:
                raise
            raise CameraFileError(f"{source}: {e}") from None
        return self

    def _check(self) -> None:
        def fail(name, why, hint=None):
            hint = hint or _HINTS.get(name, _TERM_HINT)
            raise CameraFileError(f"[camera].{name} = {_show(getattr(self, name))} {why} ({hint})")

        for name in ("width", "height"):
            v = getattr(self, name)
            if not _is_int(v):
                fail(name, "must be an integer number of pixels")
            if v <= 0:
                fail(name, "must be positive")
            if v > MAX_IMAGE_SIDE:
                fail(name, f"is beyond {MAX_IMAGE_SIDE} pixels, more than the renderer and the readers take",
                     f"give the camera's real image size, at most {MAX_IMAGE_SIDE} a side")
        for name in ("fx", "fy", "cx", "cy") + _ALL_TERMS:
            v = getattr(self, name)
            if not _is_real(v):
                fail(name, "must be a number")
            if not math.isfinite(v):
                fail(name, "must be finite")
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                fail(name, "must be positive")
        for name, side in (("cx", self.width), ("cy", self.height)):
            if not -0.5 <= getattr(self, name) <= side - 0.5:
                fail(name, f"lies outside the {self.width}x{self.height} image (-0.5 .. {side - 0.5:g})",
                     "the principal point is a pixel of the image, near its centre; check the calibration")
        if not isinstance(self.model, str) or self.model not in LENS_MODELS:
            fail("model", "is not a known lens model")
        for name in _ALL_TERMS:
            if name not in LENS_MODELS[self.model] and getattr(self, name) != 0:
                fail(name, f"is not a term of model {_show(self.model)}",
                     f"{self.model} takes {', '.join(LENS_MODELS[self.model])}; set it to 0 or change model")
        if self.model == "radial-sqrt" and self.kd1 > 0:
            # The inverse divides by sqrt(1 - 2 kd1 r_d^2): it must stay positive over the whole
            # image, whose farthest points from (cx, cy) are its outer corners (pixel edges).
            corners = np.array([[-0.5, -0.5], [self.width - 0.5, -0.5],
                                [-0.5, self.height - 0.5], [self.width - 0.5, self.height - 0.5]])
            rd2 = np.sum((corners - [self.cx, self.cy]) ** 2, axis=1)
            worst = int(np.argmax(rd2))
            margin = 1.0 - 2.0 * self.kd1 * rd2[worst]
            if margin <= 0:
                u, v = corners[worst]
                fail("kd1", f"is too large for a {self.width}x{self.height} image",
                     f"1 - 2 kd1 r_d^2 = {margin:.3g} at the corner ({u:g}, {v:g}), so the lens has no "
                     f"inverse there; use kd1 < {1.0 / (2.0 * rd2[worst]):.6g}")

    # -- camera.toml --
    def to_dict(self) -> dict:
        """The camera.toml document, ``{"camera": {...}}``, with every term of the model written."""
        table = {name: getattr(self, name) for name in _REQUIRED}
        table["model"] = self.model
        table.update(self.distortion)
        return {"camera": table}

    @classmethod
    def from_dict(cls, d: Mapping, source: str = "camera.toml") -> "CameraIntrinsics":
        """Build from a parsed camera.toml document (the whole document, with its [camera] table).

        Unknown keys, terms of another model and unknown models raise :class:`CameraFileError`
        whose message starts with ``source``.
        """
        try:
            return cls(**_camera_table(d))
        except CameraFileError as e:
            raise CameraFileError(f"{source}: {e}") from None


def _camera_table(d: Mapping) -> dict:
    """Check the document's keys and return the [camera] table as CameraIntrinsics arguments."""
    if not isinstance(d, Mapping) or "camera" not in d:
        stray = isinstance(d, Mapping) and any(k in d for k in _REQUIRED)
        fix = 'put a "[camera]" line above width = ...' if stray else \
            "add a [camera] table with width, height, fx, fy, cx, cy (see shared/formats.md)"
        raise CameraFileError(f"no [camera] table; {fix}")
    for k in d:
        if k != "camera":
            raise CameraFileError(f"unknown top-level key {_show(k)}; camera.toml holds only the [camera] table, "
                                  f"so remove it or move it into [camera]")
    t = d["camera"]
    if not isinstance(t, Mapping):
        raise CameraFileError(f"[camera] = {_show(t)} must be a table; write a [camera] header line "
                              f"followed by width, height, fx, fy, cx, cy")
    model = t.get("model", "brown")
    if not isinstance(model, str) or model not in LENS_MODELS:
        raise CameraFileError(f"[camera].model = {_show(model)} is not a known lens model ({_HINTS['model']})")
    allowed = _REQUIRED + ("model",) + LENS_MODELS[model]
    for k in t:
        if k in allowed:
            continue
        if k in _ALL_TERMS:
            owners = ", ".join(_show(m) for m, terms in LENS_MODELS.items() if k in terms)
            raise CameraFileError(
                f"[camera].{k} is a term of model {owners}, not of model {_show(model)}; remove it or change "
                f"model (model {_show(model)} takes {', '.join(LENS_MODELS[model])})")
        close = difflib.get_close_matches(str(k), allowed, n=1)
        maybe = f"did you mean {close[0]}? " if close else ""
        raise CameraFileError(f"[camera].{k} is not a known key; {maybe}remove it "
                              f"(model {_show(model)} takes {', '.join(allowed)})")
    for k in _REQUIRED:
        if k not in t:
            raise CameraFileError(f"[camera].{k} is missing; add it ({_HINTS[k]})")
    return dict(t)


def load_camera(path: str | Path) -> CameraIntrinsics:
    """Read and validate a camera.toml (shared/formats.md). Errors name the file."""
    d = read_toml(path, CameraFileError, "the path of a camera.toml")
    return CameraIntrinsics.from_dict(d, source=str(path))


def save_camera(cam: CameraIntrinsics, path: str | Path) -> None:
    """Write camera.toml; ``load_camera`` gives back an equal CameraIntrinsics (floats round-trip
    exactly because tomli_w writes their shortest repr)."""
    cam.validate(str(path))
    Path(path).write_text(tomli_w.dumps(cam.to_dict()))


#: The paper's camera: a 640x480 Sony CCD; the focal length gives about a 64 x 50 degree view.
DEFAULT_CAMERA = CameraIntrinsics(width=640, height=480, fx=514.7, fy=514.7, cx=319.5, cy=239.5)


def default_camera() -> CameraIntrinsics:
    """640x480 brown camera, fx = fy = 514.7, (cx, cy) = (319.5, 239.5), no distortion."""
    return DEFAULT_CAMERA


# ---------------------------------------------------------------------------------------------
# Lens models. Each model is written once, as a numba-compiled kernel for ONE point (scalars in,
# scalars out, with its analytic 2x2 Jacobian). The array functions of this module loop those
# kernels over points in compiled code, and runtime.slam.measurement calls
# :func:`project_point_kernel` from its own compiled measurement model, so the EKF's per-feature
# path and the public vectorised API share one implementation of every formula (a single point
# costs microseconds instead of the ~100 us of numpy's per-call overhead). The brown and fisheye
# models distort in normalised coordinates and then apply K; radial-sqrt distorts in pixels
# about (cx, cy).
#
# The kernels take the camera as (model code, parameter vector), see :func:`lens_kernel_args`;
# ``error_model="numpy"`` makes a division by zero give inf/NaN instead of raising, as numpy does.
# The kernels call only kernels of this file, so numba's on-disk cache (invalidated when this
# file changes) is never stale.
# ---------------------------------------------------------------------------------------------

_jit = numba.njit(cache=True, error_model="numpy")

#: Model codes the kernels switch on (a string cannot be passed cheaply into compiled code).
BROWN, FISHEYE, RADIAL_SQRT = 0, 1, 2
_MODEL_CODES = {"brown": BROWN, "fisheye": FISHEYE, "radial-sqrt": RADIAL_SQRT}
#: Order of the kernels' parameter vector (pixels, and the dimensionless / px^-2 terms).
_PARAM_ORDER = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "p1", "p2", "kd1")
_FX, _FY, _CX, _CY, _K1, _K2, _K3, _K4, _P1, _P2, _KD1 = range(len(_PARAM_ORDER))


def lens_kernel_args(cam: CameraIntrinsics) -> tuple[int, np.ndarray]:
    """``(model code, parameters (11,))`` of ``cam`` for the compiled lens kernels
    (:func:`project_point_kernel` and friends), parameters in the order of ``_PARAM_ORDER``.

    Computed once per camera and kept on it (the camera is immutable); do not modify the array.
    """
    args = cam.__dict__.get("_lens_kernel_args")
    if args is None:
        args = (_MODEL_CODES[cam.model], np.array([getattr(cam, name) for name in _PARAM_ORDER], dtype=np.float64))
        # A frozen dataclass refuses setattr; the cache is not a field (equality, hashing,
        # to_dict and replace() never see it), so writing it into __dict__ is safe.
        cam.__dict__["_lens_kernel_args"] = args
    return args


def _nan_for_bad_points(func):
    """Silence numpy's floating-point warnings in an array function: invalid points (NaN, inf,
    outside a model's domain, a diverging Newton iteration) already come back as NaN."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            return func(*args, **kwargs)
    return wrapper


def _points(a, dim: int, name: str) -> np.ndarray:
    """``a`` as a C-contiguous (N, dim) float64 array (the one layout the kernels are compiled
    for), or ValueError."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {a.shape}")
    return np.ascontiguousarray(a)


def _focal(cam: CameraIntrinsics) -> np.ndarray:
    return np.array([cam.fx, cam.fy])


def _centre(cam: CameraIntrinsics) -> np.ndarray:
    return np.array([cam.cx, cam.cy])


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
def _radial_sqrt_point(p, x, y):
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


@_jit
def _normalised_point(model, p, x, y):
    """Distorted normalised point and its Jacobian for the models that distort in normalised
    coordinates (brown, fisheye)."""
    if model == BROWN:
        return _brown_point(p, x, y)
    return _fisheye_point(p, x, y)


@_jit
def _distort_point(model, p, x, y):
    """Pixels ``(u, v)`` of the undistorted normalised point ``(x, y)`` through the lens model,
    and ``d(uv)/d(xy)`` ``(j00, j01, j10, j11)``, pixels."""
    if model == RADIAL_SQRT:
        return _radial_sqrt_point(p, x, y)
    xd, yd, j00, j01, j10, j11 = _normalised_point(model, p, x, y)
    fx, fy = p[_FX], p[_FY]
    return (xd * fx + p[_CX], yd * fy + p[_CY], j00 * fx, j01 * fx, j10 * fy, j11 * fy)


@_jit
def project_point_kernel(model, p, X, Y, Z):
    """Pixels ``(u, v)`` of the optical-frame point ``(X, Y, Z)`` (m) and ``d(uv)/d(X, Y, Z)``
    as six numbers ``(j00, j01, j02, j10, j11, j12)``, px/m; all NaN when ``Z <= 0`` (or NaN).

    Compiled (numba): call it from other compiled code with ``lens_kernel_args(cam)``; from
    Python use :func:`project_jacobian`, which loops it over points."""
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
def _normalised_many(model, p, xy):
    """(N, 2) distorted normalised points and (N, 2, 2) Jacobians (brown, fisheye only)."""
    n = xy.shape[0]
    out = np.empty((n, 2))
    J = np.empty((n, 2, 2))
    for i in range(n):
        out[i, 0], out[i, 1], J[i, 0, 0], J[i, 0, 1], J[i, 1, 0], J[i, 1, 1] = \
            _normalised_point(model, p, xy[i, 0], xy[i, 1])
    return out, J


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


def _forward(cam, xy, jac: bool):
    """Pixels (N, 2) of normalised points (N, 2, C-contiguous) and, if jac, d(uv)/d(xy)."""
    model, p = lens_kernel_args(cam)
    uv, J = _distort_many(model, p, xy)
    return uv, (J if jac else None)


def _radial_sqrt_inverse(cam, uv, jac: bool):
    """Formats.md's closed-form inverse: normalised points (N, 2) and, if jac, d(xy)/d(uv)."""
    d = uv - _centre(cam)  # distorted offset, pixels
    w = 1.0 - 2.0 * cam.kd1 * np.sum(d * d, axis=1)
    t = 1.0 / np.sqrt(np.where(w > 0, w, np.nan))
    xy = d * t[:, None] / _focal(cam)
    if not jac:
        return xy, None
    # d(d t)/dd = t I + 2 kd1 t^3 d d^T, then xy = (.)/f scales the rows.
    J = t[:, None, None] * np.eye(2) + (2.0 * cam.kd1 * t**3)[:, None, None] * d[:, :, None] * d[:, None, :]
    return xy, J / _focal(cam)[None, :, None]


@_nan_for_bad_points
def distort(cam: CameraIntrinsics, xy) -> np.ndarray:
    """Undistorted normalised points to pixels through the lens model.

    cam : the camera.
    xy : (N, 2) float, undistorted normalised coordinates (X/Z, Y/Z), dimensionless.
    Returns uv : (N, 2) float, pixels (OpenCV convention). NaN outside the model's domain.
    """
    return _forward(cam, _points(xy, 2, "xy"), jac=False)[0]


@_nan_for_bad_points
def distort_jacobian(cam: CameraIntrinsics, xy) -> tuple[np.ndarray, np.ndarray]:
    """:func:`distort` and its Jacobian.

    Returns uv : (N, 2) pixels, and J : (N, 2, 2), J[i] = d(uv_i)/d(xy_i), pixels.
    """
    return _forward(cam, _points(xy, 2, "xy"), jac=True)


def _newton_brown(cam, xd):
    """Solve brown(x) = xd for x, vectorised 2-D Newton started at x = xd.

    xd : (N, 2) distorted normalised points. Returns (N, 2), NaN where it did not converge.
    """
    p = lens_kernel_args(cam)[1]
    x = xd.copy()
    active = np.isfinite(xd).all(axis=1)
    converged = np.zeros(len(xd), bool)
    for _ in range(UNDISTORT_MAX_ITER):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        d, J = _normalised_many(BROWN, p, x[idx])
        res = d - xd[idx]
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        step = np.stack([J[:, 1, 1] * res[:, 0] - J[:, 0, 1] * res[:, 1],
                         J[:, 0, 0] * res[:, 1] - J[:, 1, 0] * res[:, 0]], axis=1) / det[:, None]
        x[idx] -= step
        size = np.abs(step).max(axis=1)
        done = size <= UNDISTORT_TOL
        converged[idx[done]] = True
        active[idx[done | ~np.isfinite(size)]] = False  # finished, or diverged (singular J)
    # Past the fold the radial factor can turn negative, mapping points through the centre to
    # the opposite side (with det J > 0 again, so _inverse's check alone would not catch it).
    r2 = np.sum(x * x, axis=1)
    converged &= _brown_radial(p, r2) > 0
    return np.where(converged[:, None], x, np.nan)


def _newton_fisheye(cam, xd):
    """Invert the equidistant model: solve g(theta) = |xd| by 1-D Newton (as cv2.fisheye does),
    then r = tan(theta). Returns (N, 2), NaN where it did not converge or theta >= pi/2."""
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


_NEWTON = {"brown": _newton_brown, "fisheye": _newton_fisheye}


def _inverse(cam, uv, jac: bool):
    if cam.model != "fisheye" and not any(cam.distortion.values()):
        # brown or radial-sqrt with every term zero is the pinhole: its inverse exactly, no
        # iteration (a fisheye with zero terms is still equidistant, not a pinhole).
        xy = (uv - _centre(cam)) / _focal(cam)
        J = np.broadcast_to(np.diag(1.0 / _focal(cam)), (len(uv), 2, 2)).copy() if jac else None
        return xy, J
    if cam.model == "radial-sqrt":
        return _radial_sqrt_inverse(cam, uv, jac)
    xy = _NEWTON[cam.model](cam, (uv - _centre(cam)) / _focal(cam))
    # A root where the forward Jacobian is not orientation-preserving lies beyond the lens's fold
    # (e.g. strong barrel distortion turning back on itself): not a point the lens images.
    _, Jf = _forward(cam, xy, jac=True)
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


@_nan_for_bad_points
def undistort(cam: CameraIntrinsics, uv) -> np.ndarray:
    """Pixels to undistorted normalised points: the inverse of :func:`distort`.

    radial-sqrt uses the exact closed form of formats.md. brown and fisheye use Newton's method
    vectorised over points (2-D for brown, 1-D in theta for fisheye) started at the distorted
    point and iterated until the step is below UNDISTORT_TOL = 1e-12 in normalised coordinates.
    A point whose iteration does not converge in UNDISTORT_MAX_ITER steps, or converges beyond
    the fold of the lens model, gets NaN (nothing is raised).

    uv : (N, 2) float, pixels (OpenCV convention).
    Returns xy : (N, 2) float, normalised coordinates (X/Z, Y/Z).
    """
    return _inverse(cam, _points(uv, 2, "uv"), jac=False)[0]


@_nan_for_bad_points
def undistort_jacobian(cam: CameraIntrinsics, uv) -> tuple[np.ndarray, np.ndarray]:
    """:func:`undistort` and its Jacobian.

    Returns xy : (N, 2), and J : (N, 2, 2), J[i] = d(xy_i)/d(uv_i), per pixel.
    """
    return _inverse(cam, _points(uv, 2, "uv"), jac=True)


@_nan_for_bad_points
def project(cam: CameraIntrinsics, P_cam) -> np.ndarray:
    """Points in the optical frame to pixels (pinhole then lens model).

    P_cam : (N, 3) float, metres, optical frame (x right, y down, z forward).
    Returns uv : (N, 2) float, pixels. Points with Z <= 0 (on or behind the camera plane) give
    NaN, unlike cv2.projectPoints, which projects them through the centre anyway.
    """
    return project_jacobian(cam, P_cam)[0]


@_nan_for_bad_points
def project_jacobian(cam: CameraIntrinsics, P_cam) -> tuple[np.ndarray, np.ndarray]:
    """:func:`project` and its Jacobian.

    Returns uv : (N, 2) pixels, and J : (N, 2, 3), J[i] = d(uv_i)/d(P_i), pixels per metre
    (NaN for Z <= 0).
    """
    model, p = lens_kernel_args(cam)
    return _project_many(model, p, _points(P_cam, 3, "P_cam"))


@_nan_for_bad_points
def unproject(cam: CameraIntrinsics, uv) -> np.ndarray:
    """Pixels to unit ray directions in the optical frame (z forward, so rays have z > 0).

    uv : (N, 2) float, pixels.
    Returns rays : (N, 3) float, unit vectors; NaN where :func:`undistort` gives NaN.
    """
    xy = undistort(cam, uv)
    q = np.column_stack([xy, np.ones(len(xy))])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@_nan_for_bad_points
def unproject_jacobian(cam: CameraIntrinsics, uv) -> tuple[np.ndarray, np.ndarray]:
    """:func:`unproject` and its Jacobian.

    Returns rays : (N, 3) unit vectors, and J : (N, 3, 2), J[i] = d(ray_i)/d(uv_i), per pixel.
    """
    xy, Ju = undistort_jacobian(cam, uv)
    q = np.column_stack([xy, np.ones(len(xy))])
    n = np.linalg.norm(q, axis=1)
    rays = q / n[:, None]
    # d(q/|q|)/dq = (I - ray ray^T) / |q|, and dq/dxy picks its first two columns.
    Jq = (np.eye(3) - rays[:, :, None] * rays[:, None, :]) / n[:, None, None]
    return rays, Jq[:, :, :2] @ Ju


def in_image(cam: CameraIntrinsics, uv, margin: float = 0.0) -> np.ndarray:
    """Which pixels lie in the image, at least ``margin`` pixels inside its edge.

    The image spans -0.5 .. width - 0.5 and -0.5 .. height - 0.5 (OpenCV pixel centres at
    integers); the bounds are inclusive. NaN points are outside.
    uv : (N, 2) float, pixels. Returns (N,) bool.
    """
    uv = _points(uv, 2, "uv")
    lo = -0.5 + margin
    return ((uv[:, 0] >= lo) & (uv[:, 0] <= cam.width - 0.5 - margin)
            & (uv[:, 1] >= lo) & (uv[:, 1] <= cam.height - 0.5 - margin))


def fov_x_rad(cam: CameraIntrinsics) -> float:
    """Horizontal field of view of the pinhole part, 2 atan(width / 2 / fx), radians.

    With OpenCV's pixel-centre convention the image spans -0.5 .. width - 0.5, i.e. exactly
    ``width`` pixels, hence width / 2. The principal point's offset from the centre and the
    lens distortion are ignored.
    """
    return 2.0 * math.atan(cam.width / 2.0 / cam.fx)


def fov_y_rad(cam: CameraIntrinsics) -> float:
    """Vertical field of view of the pinhole part, 2 atan(height / 2 / fy), radians.

    The image spans -0.5 .. height - 0.5 (OpenCV convention), so height / 2 is its half-extent;
    the principal point's offset and the lens distortion are ignored.
    """
    return 2.0 * math.atan(cam.height / 2.0 / cam.fy)
