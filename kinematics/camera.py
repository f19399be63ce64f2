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

Lens models
-----------
Each maps an undistorted normalised point to pixels; each is one class of
:mod:`kinematics.lenses` (its terms, kernel, inverse and rules), listed in its table ``LENSES``,
which camera.toml's parsing, validation and saving use:

``brown``
    OpenCV's radial-tangential model, exactly as ``cv2.projectPoints`` with
    ``distCoeffs = [k1, k2, p1, p2, k3]``.
``fisheye``
    OpenCV's equidistant model, exactly as ``cv2.fisheye.projectPoints`` with ``D = [k1..k4]``.
``radial-sqrt``
    MonoSLAM's one-parameter model with ``kd1`` in pixels^-2, applied in pixels about (cx, cy).

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

Each lens model is one numba-compiled kernel for a single point (:mod:`kinematics.lenses`), looped
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

import numpy as np
import tomli_w

from .lenses import (BROWN, FISHEYE, LENSES, RADIAL_SQRT, TERMS, UNDISTORT_MAX_ITER, UNDISTORT_TOL,  # noqa: F401
                     distort_points, lens_kernel_args, project_point_kernel, project_points, undistort_points)
from .tomlfile import read_toml

#: Distortion terms each lens model takes, in the order OpenCV lists them (from ``LENSES``).
LENS_MODELS: dict[str, tuple[str, ...]] = {name: lens.terms for name, lens in LENSES.items()}
_ALL_TERMS = TERMS
#: The largest image side (px) a camera may have: MuJoCo's offscreen buffer and every reader
#: allocate whole frames, and no camera here comes near it.
MAX_IMAGE_SIDE = 8192
_REQUIRED = ("width", "height", "fx", "fy", "cx", "cy")

# What each field means, appended to error messages so the user knows what to write.
_HINTS = {
    "width": "image width in pixels, e.g. 640",
    "height": "image height in pixels, e.g. 480",
    "fx": "focal length in pixels, e.g. 514.7",
    "fy": "focal length in pixels, e.g. 514.7",
    "cx": "principal point in pixels, OpenCV convention, e.g. 319.5 for a 640-wide image",
    "cy": "principal point in pixels, OpenCV convention, e.g. 239.5 for a 480-high image",
    "model": "lens model: " + ", ".join(f'"{m}"' for m in list(LENSES)[:-1]) + f' or "{list(LENSES)[-1]}"',
    **{term: hint for lens in LENSES.values() for term, hint in lens.hints.items()},
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
        broken = LENSES[self.model].check(self)
        if broken is not None:
            fail(*broken)

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


# A lens term is a field of CameraIntrinsics (of the same name, in the order of lenses.TERMS).
assert tuple(f.name for f in fields(CameraIntrinsics)) == _REQUIRED + ("model",) + TERMS, \
    "CameraIntrinsics' fields must be width, height, fx, fy, cx, cy, model and lenses.TERMS"


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
    allowed = _REQUIRED + ("model", "depth_scale") + LENS_MODELS[model]
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
    t = dict(t)
    # The depth images' units per metre: the sequence's, read by its depth reader, not the lens's.
    ds = t.pop("depth_scale", 5000.0)
    if not _is_real(ds) or not math.isfinite(ds) or ds <= 0:
        raise CameraFileError(f"[camera].depth_scale = {_show(ds)} must be a positive number (depth image units "
                              "per metre; TUM RGB-D: 5000)")
    return t


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


@_nan_for_bad_points
def distort(cam: CameraIntrinsics, xy) -> np.ndarray:
    """Undistorted normalised points to pixels through the lens model.

    cam : the camera.
    xy : (N, 2) float, undistorted normalised coordinates (X/Z, Y/Z), dimensionless.
    Returns uv : (N, 2) float, pixels (OpenCV convention). NaN outside the model's domain.
    """
    return distort_points(cam, _points(xy, 2, "xy"))[0]


@_nan_for_bad_points
def distort_jacobian(cam: CameraIntrinsics, xy) -> tuple[np.ndarray, np.ndarray]:
    """:func:`distort` and its Jacobian.

    Returns uv : (N, 2) pixels, and J : (N, 2, 2), J[i] = d(uv_i)/d(xy_i), pixels.
    """
    return distort_points(cam, _points(xy, 2, "xy"))


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
    return undistort_points(cam, _points(uv, 2, "uv"), jac=False)[0]


@_nan_for_bad_points
def undistort_jacobian(cam: CameraIntrinsics, uv) -> tuple[np.ndarray, np.ndarray]:
    """:func:`undistort` and its Jacobian.

    Returns xy : (N, 2), and J : (N, 2, 2), J[i] = d(xy_i)/d(uv_i), per pixel.
    """
    return undistort_points(cam, _points(uv, 2, "uv"), jac=True)


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
    return project_points(cam, _points(P_cam, 3, "P_cam"))


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
