"""mount.toml: where the head's mount frame sits on a wearer segment; the schema, written once.

``wvr placement map`` writes it (the best polygon of a zone) and the twin reads it; neither may
import the other, so the file's one definition lives here, beside the head it carries::

    [mount]
    zone = "shoulder"            # optional: the placement zone it came from
    segment = "chest"            # the body segment it rides on
    polygon = 1234               # optional: the body polygon it was placed on
    position_m = [x, y, z]       # the mount frame's origin in the segment frame, metres
    forward = [x, y, z]          # the mount's x axis in the segment frame (unit)
    up = [x, y, z]               # the mount's z axis in the segment frame (unit, not parallel to forward)
    normal = [x, y, z]           # optional: the surface normal there (for reference)
    standoff_m = 0.02            # optional: distance out along the normal, metres
    stature_m = 1.75             # optional: the stature of the body it was placed on, metres

The segment frame has its origin at the segment's joint centre and the body's axes in the rest
pose (+Z up, facing -Y). The mount frame is the head's (x forward, y left, z up when worn
upright): z is ``up``, x is ``forward`` made perpendicular to ``up``.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tomli_w

from .outdir import OutputFolderError, check_complete
from .tomlfile import brief, read_toml

#: Unit vectors in the file are normalised if within this of length 1, else refused.
UNIT_TOL = 1e-3
#: A person's stature, m (placement.body.make_body's range): a mount was placed on a body this tall.
STATURE_RANGE_M = (0.5, 2.5)
#: How far a place on the body may lie from its segment's joint centre, m (a 2.5 m person's
#: longest segment is about 0.6 m, plus a stand-off).
MAX_POSITION_M = 1.5


class MountFileError(ValueError):
    """A mount.toml (or MountFile) that cannot be used; the message names the field and the fix."""


@dataclass(frozen=True)
class MountFile:
    """The contents of a mount.toml (module docstring for the fields and frames)."""

    segment: str
    position_m: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    zone: str = ""
    polygon: int | None = None
    normal: np.ndarray | None = None
    standoff_m: float | None = None
    stature_m: float | None = None

    def __post_init__(self):
        if not isinstance(self.segment, str) or not self.segment:
            raise MountFileError(f"[mount].segment = {brief(self.segment)} must name a body segment (e.g. 'chest')")
        for name in ("position_m", "forward", "up") + (("normal",) if self.normal is not None else ()):
            object.__setattr__(self, name, _vector(getattr(self, name), name))
        for name in ("up", "forward") + (("normal",) if self.normal is not None else ()):
            n = float(np.linalg.norm(getattr(self, name)))
            if abs(n - 1.0) > UNIT_TOL:
                raise MountFileError(f"[mount].{name} = {getattr(self, name).tolist()} must be a unit vector "
                                     f"(its length is {n:.4g})")
        if abs(float(self.up @ self.forward)) > 0.99:
            raise MountFileError("[mount].forward must not be parallel to [mount].up: the two fix the mount's axes")
        for name in ("standoff_m", "stature_m"):
            v = getattr(self, name)
            if v is not None and not (_real(v) and math.isfinite(v) and v >= 0):
                raise MountFileError(f"[mount].{name} = {brief(v)} must be a finite number >= 0, metres")
        lo, hi = STATURE_RANGE_M
        if self.stature_m is not None and not lo <= self.stature_m <= hi:
            raise MountFileError(f"[mount].stature_m = {self.stature_m:g} is not a person's stature; give metres, "
                                 f"{lo:g} to {hi:g} (e.g. 1.75), or leave it out")
        far = float(np.linalg.norm(self.position_m))
        if far > MAX_POSITION_M:
            raise MountFileError(f"[mount].position_m = {self.position_m.tolist()} is {far:.3g} m from the "
                                 f"{self.segment} segment's joint; a place on the body is within {MAX_POSITION_M:g} m "
                                 f"of it (metres, in the segment's frame)")


def _real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _vector(v, name: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise MountFileError(f"[mount].{name} = {brief(v)}: {name} must be 3 finite numbers")
    return a


_KEYS = ("zone", "segment", "polygon", "position_m", "forward", "up", "normal", "standoff_m", "stature_m")


def mount_to_dict(m: MountFile) -> dict:
    """The [mount] table as TOML-ready data (optional fields only when set)."""
    t = {"zone": m.zone, "segment": m.segment}
    if m.polygon is not None:
        t["polygon"] = int(m.polygon)
    t["position_m"] = [float(v) for v in m.position_m]
    t["forward"] = [float(v) for v in m.forward]
    t["up"] = [float(v) for v in m.up]
    if m.normal is not None:
        t["normal"] = [float(v) for v in m.normal]
    for name in ("standoff_m", "stature_m"):
        if getattr(m, name) is not None:
            t[name] = float(getattr(m, name))
    return {"mount": t}


def save_mount(m: MountFile, path: str | Path) -> None:
    """Write mount.toml; :func:`load_mount_file` gives back the same values."""
    Path(path).write_text(tomli_w.dumps(mount_to_dict(m)))


def load_mount_file(path: str | Path) -> MountFile:
    """Read and check a mount.toml; errors name the file and the field. A mount.toml in a
    placement folder whose run has not finished is refused."""
    path = Path(path)
    try:
        check_complete(path.parent, "placement result")
    except OutputFolderError as e:
        raise MountFileError(str(e)) from None
    d = read_toml(path, MountFileError, "a mount.toml written by 'wvr placement map'")
    t = d.get("mount")
    if not isinstance(t, dict):
        raise MountFileError(f"{path}: missing the [mount] table; a mount.toml holds one [mount] table "
                             f"(written by 'wvr placement map')")
    for k in t:
        if k not in _KEYS:
            raise MountFileError(f"{path}: [mount] has unknown key {k!r}; allowed keys are {sorted(_KEYS)}")
    for k in ("segment", "position_m", "forward", "up"):
        if k not in t:
            raise MountFileError(f"{path}: [mount].{k} is missing" + (" (e.g. 'chest')" if k == "segment" else ""))
    polygon = t.get("polygon")
    if polygon is not None and not (isinstance(polygon, int) and not isinstance(polygon, bool) and polygon >= 0):
        raise MountFileError(f"{path}: [mount].polygon = {brief(polygon)} must be a polygon index (an integer >= 0)")
    try:
        return MountFile(segment=t["segment"], position_m=t["position_m"], forward=t["forward"], up=t["up"],
                         zone=str(t.get("zone", "")), polygon=polygon, normal=t.get("normal"),
                         standoff_m=t.get("standoff_m"), stature_m=t.get("stature_m"))
    except MountFileError as e:
        raise MountFileError(f"{path}: {e}") from None
