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
        for name in ("fx", "fy", "cx", "cy") + _ALL_TERMS:
            v = getattr(self, name)
            if not _is_real(v):
                fail(name, "must be a number")
            if not math.isfinite(v):
                fail(name, "must be finite")
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                fail(name, "must be positive")
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
# Lens models. The brown and fisheye models distort in normalised coordinates and then apply K;
# radial-sqrt distorts in pixels about (cx, cy). Each private forward model returns values and,
# if asked, the (N, 2, 2) Jacobian with respect to the normalised input.
# ---------------------------------------------------------------------------------------------

def _nan_for_bad_points(func):
    """Silence numpy's floating-point warnings in an array function: invalid points (NaN, inf,
    outside a model's domain, a diverging Newton iteration) already come back as NaN."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            return func(*args, **kwargs)
    return wrapper


def _points(a, dim: int, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {a.shape}")
    return a


def _focal(cam: CameraIntrinsics) -> np.ndarray:
    return np.array([cam.fx, cam.fy])


def _centre(cam: CameraIntrinsics) -> np.ndarray:
    return np.array([cam.cx, cam.cy])


def _brown_normalised(cam, xy, jac: bool):
    """Distorted normalised points (N, 2) and, if jac, d(distorted)/d(xy) (N, 2, 2)."""
    k1, k2, k3, p1, p2 = cam.k1, cam.k2, cam.k3, cam.p1, cam.p2
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    out = np.stack([xd, yd], axis=1)
    if not jac:
        return out, None
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d(radial)/d(r2)
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y  # the model's Jacobian is symmetric
    J = np.empty((len(xy), 2, 2))
    J[:, 0, 0] = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    J[:, 0, 1] = cross
    J[:, 1, 0] = cross
    J[:, 1, 1] = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return out, J


# Below this normalised radius the fisheye scale theta_d / r is 1 to double precision (its
# series is 1 + (k1 - 1/3) r^2 + ...), which is also the cut-off cv2.fisheye uses.
_FISHEYE_SMALL_R = 1e-8


def _fisheye_poly(cam, theta):
    """theta_d = g(theta) and g'(theta) of the equidistant model."""
    t2 = theta * theta
    g = theta * (1.0 + t2 * (cam.k1 + t2 * (cam.k2 + t2 * (cam.k3 + t2 * cam.k4))))
    dg = 1.0 + t2 * (3.0 * cam.k1 + t2 * (5.0 * cam.k2 + t2 * (7.0 * cam.k3 + t2 * 9.0 * cam.k4)))
    return g, dg


def _fisheye_normalised(cam, xy, jac: bool):
    """Distorted normalised points (N, 2) = xy * s(r), s = theta_d / r; and, if jac, the Jacobian."""
    r = np.hypot(xy[:, 0], xy[:, 1])
    theta = np.arctan(r)
    g, dg = _fisheye_poly(cam, theta)
    small = r < _FISHEYE_SMALL_R
    r_safe = np.where(small, 1.0, r)
    s = np.where(small, 1.0, g / r_safe)
    out = xy * s[:, None]
    if not jac:
        return out, None
    # d(xy s)/d(xy) = s I + (s'(r) / r) xy xy^T, with s'(r) = (g'(theta) / (1 + r^2) - s) / r.
    # The difference loses digits as r -> 0, but it is multiplied by |xy|^2 ~ r^2, so the
    # absolute error of the Jacobian stays at rounding level; at r = 0 use the limit.
    ds_over_r = np.where(small, 2.0 * (cam.k1 - 1.0 / 3.0), (dg / (1.0 + r * r) - s) / (r_safe * r_safe))
    J = s[:, None, None] * np.eye(2) + ds_over_r[:, None, None] * xy[:, :, None] * xy[:, None, :]
    return out, J


def _radial_sqrt_forward(cam, xy, jac: bool):
    """Pixels (N, 2) and, if jac, d(uv)/d(xy) (N, 2, 2). NaN where 1 + 2 kd1 r^2 <= 0."""
    e = xy * _focal(cam)  # undistorted offset from (cx, cy), pixels
    q = 1.0 + 2.0 * cam.kd1 * np.sum(e * e, axis=1)
    s = 1.0 / np.sqrt(np.where(q > 0, q, np.nan))
    uv = _centre(cam) + e * s[:, None]
    if not jac:
        return uv, None
    # d(e s)/de = s I - 2 kd1 s^3 e e^T, then de/dxy = diag(fx, fy) scales the columns.
    J = s[:, None, None] * np.eye(2) - (2.0 * cam.kd1 * s**3)[:, None, None] * e[:, :, None] * e[:, None, :]
    return uv, J * _focal(cam)[None, None, :]


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


_NORMALISED_MODELS = {"brown": _brown_normalised, "fisheye": _fisheye_normalised}


def _forward(cam, xy, jac: bool):
    if cam.model == "radial-sqrt":
        return _radial_sqrt_forward(cam, xy, jac)
    xd, J = _NORMALISED_MODELS[cam.model](cam, xy, jac)
    f = _focal(cam)
    return xd * f + _centre(cam), (None if J is None else J * f[None, :, None])


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
    x = xd.copy()
    active = np.isfinite(xd).all(axis=1)
    converged = np.zeros(len(xd), bool)
    for _ in range(UNDISTORT_MAX_ITER):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        d, J = _brown_normalised(cam, x[idx], jac=True)
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
    converged &= 1.0 + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3)) > 0
    return np.where(converged[:, None], x, np.nan)


def _newton_fisheye(cam, xd):
    """Invert the equidistant model: solve g(theta) = |xd| by 1-D Newton (as cv2.fisheye does),
    then r = tan(theta). Returns (N, 2), NaN where it did not converge or theta >= pi/2."""
    theta_d = np.hypot(xd[:, 0], xd[:, 1])
    theta = theta_d.copy()
    active = np.isfinite(theta_d)
    converged = np.zeros(len(xd), bool)
    for _ in range(UNDISTORT_MAX_ITER):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        g, dg = _fisheye_poly(cam, theta[idx])
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


def _normalise_points(P):
    """(N, 3) optical-frame points -> (N, 2) X/Z, Y/Z, with NaN for Z <= 0 (or non-finite Z)."""
    Z = P[:, 2]
    front = Z > 0
    Zs = np.where(front, Z, np.nan)
    return P[:, :2] / Zs[:, None], Zs


@_nan_for_bad_points
def project(cam: CameraIntrinsics, P_cam) -> np.ndarray:
    """Points in the optical frame to pixels (pinhole then lens model).

    P_cam : (N, 3) float, metres, optical frame (x right, y down, z forward).
    Returns uv : (N, 2) float, pixels. Points with Z <= 0 (on or behind the camera plane) give
    NaN, unlike cv2.projectPoints, which projects them through the centre anyway.
    """
    xy, _ = _normalise_points(_points(P_cam, 3, "P_cam"))
    return _forward(cam, xy, jac=False)[0]


@_nan_for_bad_points
def project_jacobian(cam: CameraIntrinsics, P_cam) -> tuple[np.ndarray, np.ndarray]:
    """:func:`project` and its Jacobian.

    Returns uv : (N, 2) pixels, and J : (N, 2, 3), J[i] = d(uv_i)/d(P_i), pixels per metre
    (NaN for Z <= 0).
    """
    P = _points(P_cam, 3, "P_cam")
    xy, Z = _normalise_points(P)
    uv, Jd = _forward(cam, xy, jac=True)
    # d(X/Z, Y/Z)/d(X, Y, Z) = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
    Jn = np.zeros((len(P), 2, 3))
    Jn[:, 0, 0] = Jn[:, 1, 1] = 1.0 / Z
    Jn[:, :, 2] = -xy / Z[:, None]
    return uv, Jd @ Jn


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
