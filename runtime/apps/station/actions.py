"""What an operator can ask of the station, as typed actions, and their answers.

The page and the JSON API build the same actions (:func:`from_json` for the API's bodies); the
live loop applies them between periods and answers each with an :class:`ActionResult`: accepted,
or refused with the reason (unreachable, with the wearer's prompt; not a finite point; an unknown
feature; the emergency stop is latched).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import OBJECT_KINDS

#: Modes an operator may switch to (fixation is a click or a fixate action: it needs a point).
#: explore maps: it chooses fixations itself (runtime.apps.explore) until another mode or a fixation.
OPERATOR_MODES = ("hold", "stabilise", "body", "track", "explore")
MAX_TEXT = 200
#: How far from the world's origin a point may be named, m (a wearable's scene is metres across;
#: a point 1e300 m away is a mistake, not a direction).
MAX_POINT_M = 1000.0
#: An object's size: each box edge and the arrow's length in [MIN_SIZE_M, MAX_SIZE_M], m.
MIN_SIZE_M, MAX_SIZE_M = 1e-3, 10.0
#: Feature ids are map indices: at most this.
MAX_FEATURE_ID = 2**31 - 1


def short(value, limit: int = 60) -> str:
    """``value`` for a reason: numbers as %.3g, anything else its repr cut to ``limit`` characters."""
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, np.ndarray) and value.dtype.kind == "f":
        return "[" + ", ".join(f"{v:.3g}" for v in value.ravel()) + "]"
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


class BadAction(ValueError):
    """An action that is malformed (not a finite point, a missing field): the API's 422."""


@dataclass(frozen=True)
class Fixate:
    """Saccade to and fixate: a map feature (``feature`` id), a world point (``xyz`` (3,) m), or
    the map feature under a camera-view pixel (``uv`` (2,))."""

    feature: int | None = None
    xyz: np.ndarray | None = None
    uv: np.ndarray | None = None
    name: str = field(default="fixate", init=False)


@dataclass(frozen=True)
class AddLabel:
    """A label at a world point: ``xyz`` (3,) m, or a feature's point, or the point under a pixel."""

    text: str
    xyz: np.ndarray | None = None
    feature: int | None = None
    uv: np.ndarray | None = None
    name: str = field(default="label", init=False)


@dataclass(frozen=True)
class AddObject:
    """A virtual object (kind "box" or "arrow") with ``size`` (3,) m, at a world point ``xyz``
    (3,) m, or a feature's point, or the point under a pixel."""

    kind: str
    size: np.ndarray
    xyz: np.ndarray | None = None
    feature: int | None = None
    uv: np.ndarray | None = None
    name: str = field(default="object", init=False)


@dataclass(frozen=True)
class SetMode:
    mode: str
    name: str = field(default="mode", init=False)


@dataclass(frozen=True)
class Stop:
    reason: str = "operator's emergency stop"
    name: str = field(default="stop", init=False)


@dataclass(frozen=True)
class Reset:
    name: str = field(default="reset", init=False)


Action = Fixate | AddLabel | AddObject | SetMode | Stop | Reset


@dataclass(frozen=True)
class ActionResult:
    """accepted, or refused with ``reason``. t : the loop's time when it was applied (s).
    detail : what it resolved to (the feature's id and point, the label's id)."""

    accepted: bool
    reason: str = ""
    t: float = float("nan")
    detail: dict = field(default_factory=dict)

    def as_json(self) -> dict:
        return {"accepted": self.accepted, "reason": self.reason, "t": self.t if math.isfinite(self.t) else None,
                **self.detail}


def finite_vector(value, n: int, what: str) -> np.ndarray:
    """``value`` as a finite (n,) float vector, or BadAction naming the problem."""
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise BadAction(f"{what} must be a list of {n} numbers, got {short(value)}") from None
    if v.shape != (n,):
        raise BadAction(f"{what} must be a list of {n} numbers, got {short(value)}")
    if not np.isfinite(v).all():
        raise BadAction(f"{what} {short(v)} has NaN or infinity; give finite numbers")
    return v


def world_point(value, what: str = "xyz") -> np.ndarray:
    """``value`` as a (3,) world point, m, within :data:`MAX_POINT_M` of the origin."""
    p = finite_vector(value, 3, what)
    if np.abs(p).max() > MAX_POINT_M:
        raise BadAction(f"{what} {short(p)} m is beyond {MAX_POINT_M:g} m of the world's origin; give a point "
                        "in the scene (world frame, metres)")
    return p


def feature_id(value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or int(value) != value or not 0 <= value <= MAX_FEATURE_ID:
        raise BadAction(f"feature must be an integer id 0..{MAX_FEATURE_ID}, got {short(value)}")
    return int(value)


def _target(body: dict, what: str) -> dict:
    """Exactly one of feature / xyz / uv from a JSON body."""
    given = [k for k in ("feature", "xyz", "uv") if k in body]
    if len(given) != 1:
        raise BadAction(f"{what} needs exactly one of 'feature' (an id), 'xyz' ([x, y, z] m) or 'uv' ([u, v] px)")
    k = given[0]
    if k == "feature":
        return {"feature": feature_id(body[k])}
    return {k: world_point(body[k]) if k == "xyz" else finite_vector(body[k], 2, k)}


def from_json(kind: str, body) -> Action:
    """The action for an API call (``kind``: fixate, label, object, mode, stop, reset) and its
    JSON body; BadAction when the body does not describe one."""
    if body is None:
        body = {}
    if not isinstance(body, dict):
        raise BadAction("the request body must be a JSON object")
    if kind == "fixate":
        return Fixate(**_target(body, "fixate"))
    if kind == "label":
        text = body.get("text")
        if not isinstance(text, str) or not text.strip() or len(text) > MAX_TEXT:
            raise BadAction(f"label needs 'text', a non-empty string of at most {MAX_TEXT} characters")
        return AddLabel(text.strip(), **_target(body, "label"))
    if kind == "object":
        ob = body.get("kind")
        if ob not in OBJECT_KINDS:
            raise BadAction(f"object 'kind' must be one of {', '.join(OBJECT_KINDS)}, got {short(ob)}")
        size = finite_vector(body.get("size", [0.05, 0.05, 0.05] if ob == "box" else [0.0, 0.0, 0.1]), 3, "size")
        # The arrow's length from its largest component first: the plain norm of 1e-300 underflows.
        scale = float(np.abs(size).max())
        length = scale * float(np.linalg.norm(size / scale)) if scale > 0 else 0.0
        extents = size if ob == "box" else np.array([length])
        if not ((extents >= MIN_SIZE_M).all() and (extents <= MAX_SIZE_M).all()):
            raise BadAction(f"object size {short(size)} m: a box's edges and an arrow's length must be positive, "
                            f"{MIN_SIZE_M * 1000:g} mm to {MAX_SIZE_M:g} m")
        return AddObject(ob, size, **_target(body, "object"))
    if kind == "mode":
        mode = body.get("mode")
        if mode not in OPERATOR_MODES:
            raise BadAction(f"mode must be one of {', '.join(OPERATOR_MODES)} (fixation: POST /api/fixate), "
                            f"got {short(mode)}")
        return SetMode(mode)
    if kind == "stop":
        reason = body.get("reason", "operator's emergency stop")
        return Stop(str(reason)[:MAX_TEXT])
    if kind == "reset":
        return Reset()
    raise BadAction(f"unknown action {short(kind)}")
