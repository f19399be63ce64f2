"""HeadGeometry: the elevation-pan-cyclotorsion chain from collar to camera, and head.toml.

Frames
------
``mount``
    Fixed to the collar mount on the wearer. Convention used by the reference head: x forward,
    y to the wearer's left, z up (when the wearer stands upright). Any mount orientation works;
    only the numbers in head.toml change.
``elevation``, ``pan``, ``cyclotorsion``
    The three links, in chain order (paper, Fig. 2a). Link i's frame sits at its joint's
    ``origin_m`` in the parent frame and, at zero angle, is parallel to the parent frame; the
    joint turns it about ``axis`` (a unit vector in the parent frame, right-handed).
``camera``
    The optical frame on the cyclotorsion link: x right, y down, z forward along the optic axis
    (OpenCV / TUM convention). The cyclotorsion axis must be parallel to the optic axis.

Every part (servo bodies, camera body, brackets) is a box with a mass, attached to one of
``mount`` or the three links; the parts are used for inertia, torque, collision and volume.

Units inside: metres, kilograms, radians. head.toml states units in its key names
(``origin_m``, ``range_deg``, ``mass_kg``) because people edit it.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np
import tomli_w

from .tomlfile import brief, read_toml
from .transforms import cross3
from .servo_models import SERVO_CATALOGUE, ServoModel, servo_from_dict

JOINT_NAMES: tuple[str, str, str] = ("elevation", "pan", "cyclotorsion")
LINK_NAMES: tuple[str, ...] = ("mount",) + JOINT_NAMES
#: Tolerance for "unit vector" and "parallel" checks on numbers people type into head.toml.
AXIS_TOL = 1e-6


class HeadFileError(ValueError):
    """A head.toml (or HeadGeometry) that cannot be used; the message names the field and the fix."""


@dataclass(frozen=True)
class Joint:
    """One revolute joint.

    origin_m : (3,) position of the child link frame in the parent link frame, metres.
    axis : (3,) unit rotation axis in the parent frame.
    range_rad : (lo, hi) joint limits, radians, lo < 0 < hi not required but lo < hi.
    servo : name of the servo model that drives it.
    """

    name: str
    origin_m: tuple[float, float, float]
    axis: tuple[float, float, float]
    range_rad: tuple[float, float]
    servo: str = "HS-50"


@dataclass(frozen=True)
class CameraMount:
    """The optical frame on the cyclotorsion link.

    origin_m : (3,) optical centre in the cyclotorsion link frame, metres.
    forward : (3,) optical z axis in the link frame (unit).
    right : (3,) optical x axis in the link frame (unit, orthogonal to forward).
    """

    origin_m: tuple[float, float, float]
    forward: tuple[float, float, float]
    right: tuple[float, float, float]

    @property
    def R_link_cam(self) -> np.ndarray:
        """(3, 3) rotation taking optical-frame vectors to the cyclotorsion link frame."""
        z = np.asarray(self.forward, float)
        x = np.asarray(self.right, float)
        return np.column_stack([x, cross3(z, x), z])

    @property
    def T_link_cam(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R_link_cam
        T[:3, 3] = self.origin_m
        return T


@dataclass(frozen=True)
class Part:
    """A rigid box carried by one link.

    link : one of ``mount``, ``elevation``, ``pan``, ``cyclotorsion``.
    center_m : (3,) box centre in that link's frame, metres.
    size_m : (3,) full edge lengths along the link frame's axes, metres.
    mass_kg : mass, uniformly distributed in the box.
    kind : ``servo``, ``camera`` or ``bracket`` (for reports and collision rules).
    """

    name: str
    link: str
    center_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    mass_kg: float
    kind: str = "bracket"

    @property
    def volume_m3(self) -> float:
        return float(np.prod(self.size_m))

    def inertia_about_center(self) -> np.ndarray:
        """(3, 3) inertia tensor of the solid box about its centre, in the link frame, kg m^2."""
        a, b, c = self.size_m
        m = self.mass_kg
        return np.diag([m * (b * b + c * c), m * (a * a + c * c), m * (a * a + b * b)]) / 12.0


@dataclass(frozen=True)
class HeadGeometry:
    """The whole head: three joints in chain order, the camera on the last link, the parts."""

    name: str
    joints: tuple[Joint, Joint, Joint]
    camera: CameraMount
    parts: tuple[Part, ...]
    servos: dict[str, ServoModel] = field(default_factory=lambda: dict(SERVO_CATALOGUE))

    # -- derived arrays (cheap; recomputed on demand so the dataclass stays plain data) --
    @property
    def origins(self) -> np.ndarray:
        """(3, 3) joint origins, row i in link i's parent frame, metres."""
        return np.array([j.origin_m for j in self.joints], float)

    @property
    def axes(self) -> np.ndarray:
        """(3, 3) joint axes, row i in link i's parent frame (= link i frame, same at any angle)."""
        return np.array([j.axis for j in self.joints], float)

    @property
    def lower(self) -> np.ndarray:
        return np.array([j.range_rad[0] for j in self.joints], float)

    @property
    def upper(self) -> np.ndarray:
        return np.array([j.range_rad[1] for j in self.joints], float)

    def servo_of(self, joint: int | str) -> ServoModel:
        j = self.joints[joint] if isinstance(joint, int) else self.joints[JOINT_NAMES.index(joint)]
        return self.servos[j.servo]

    @property
    def max_speed(self) -> np.ndarray:
        """(3,) per-joint speed limits from the servo models, rad/s."""
        return np.array([self.servo_of(i).max_speed_rad_s for i in range(3)], float)

    @property
    def max_torque(self) -> np.ndarray:
        """(3,) per-joint stall torques, N m."""
        return np.array([self.servo_of(i).stall_torque_nm for i in range(3)], float)

    def parts_on(self, link: str) -> tuple[Part, ...]:
        return tuple(p for p in self.parts if p.link == link)

    def validate(self) -> "HeadGeometry":
        """Check every physical and structural rule; raise :class:`HeadFileError` on the first."""
        names = tuple(j.name for j in self.joints)
        if names != JOINT_NAMES:
            raise HeadFileError(f"joints must be {list(JOINT_NAMES)} in that order (collar to camera), got {list(names)}")
        for j in self.joints:
            where = f"joints.{j.name}"
            _check_vec(j.origin_m, f"{where}.origin_m")
            _check_unit(j.axis, f"{where}.axis")
            lo, hi = j.range_rad
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo >= hi:
                raise HeadFileError(
                    f"{where}.range_deg = [{math.degrees(lo):g}, {math.degrees(hi):g}] must be [min, max] with min < max"
                )
            if j.servo not in self.servos:
                raise HeadFileError(
                    f"{where}.servo = {j.servo!r} is not a known servo; use one of {sorted(self.servos)} "
                    f"or define it in a [servos.{j.servo!r}] table"
                )
            travel = self.servos[j.servo].travel_rad
            if hi - lo > travel + 1e-9:
                raise HeadFileError(
                    f"{where}.range_deg spans {math.degrees(hi - lo):.1f} deg, more than the {j.servo}'s "
                    f"{math.degrees(travel):.0f} deg travel; narrow it to at most {math.degrees(travel):.0f} deg"
                )
        for s in self.servos.values():
            where = f"servos.{s.name}"
            for attr in ("travel_rad", "max_speed_rad_s", "stall_torque_nm", "mass_kg"):
                v = getattr(s, attr)
                if not (math.isfinite(v) and v > 0):
                    raise HeadFileError(f"{where}.{attr} = {v} must be positive")
            if s.armature_kgm2 < 0:
                raise HeadFileError(f"{where}.armature_kgm2 = {s.armature_kgm2} must be >= 0")
        cam = self.camera
        _check_vec(cam.origin_m, "camera.origin_m")
        _check_unit(cam.forward, "camera.forward")
        _check_unit(cam.right, "camera.right")
        if abs(float(np.dot(cam.forward, cam.right))) > AXIS_TOL:
            raise HeadFileError("camera.right must be perpendicular to camera.forward (optical x is orthogonal to the optic axis)")
        if np.linalg.norm(np.cross(cam.forward, self.joints[2].axis)) > AXIS_TOL:
            raise HeadFileError(
                "camera.forward must be parallel to joints.cyclotorsion.axis: the cyclotorsion axis is "
                "aligned with the optic axis (paper, Fig. 2a); set one equal to the other"
            )
        seen = set()
        for k, p in enumerate(self.parts):
            where = f"parts[{k}] ({p.name})"
            if p.name in seen:
                raise HeadFileError(f"{where}.name is used twice; give each part its own name")
            seen.add(p.name)
            if p.link not in LINK_NAMES:
                raise HeadFileError(f"{where}.link = {p.link!r} must be one of {list(LINK_NAMES)}")
            if p.kind not in ("servo", "camera", "bracket"):
                raise HeadFileError(f"{where}.kind = {p.kind!r} must be 'servo', 'camera' or 'bracket'")
            _check_vec(p.center_m, f"{where}.center_m")
            _check_vec(p.size_m, f"{where}.size_m")
            if min(p.size_m) <= 0:
                raise HeadFileError(f"{where}.size_m = {list(p.size_m)} must have positive edge lengths (metres)")
            if not math.isfinite(p.mass_kg):
                raise HeadFileError(f"{where}.mass_kg = {p.mass_kg} is not a finite number; give the mass in kg "
                                    f"(a 6 g servo is 0.006)")
            if p.mass_kg < 0:
                raise HeadFileError(f"{where}.mass_kg = {p.mass_kg} is negative; masses are >= 0 kg (a 6 g servo is 0.006)")
        for link in JOINT_NAMES:
            if sum(p.mass_kg for p in self.parts_on(link)) <= 0:
                raise HeadFileError(
                    f"link {link!r} carries no mass; attach its servo, camera or bracket as a part with mass_kg > 0"
                )
        return self

    def with_joint_ranges(self, lower, upper) -> "HeadGeometry":
        joints = tuple(replace(j, range_rad=(float(lo), float(hi))) for j, lo, hi in zip(self.joints, lower, upper))
        return replace(self, joints=joints)

    # -- TOML --
    def to_dict(self) -> dict:
        d: dict = {"name": self.name, "joints": {}, "camera": {}, "parts": []}
        for j in self.joints:
            d["joints"][j.name] = {
                "origin_m": [float(v) for v in j.origin_m],
                "axis": [float(v) for v in j.axis],
                "range_deg": [math.degrees(j.range_rad[0]), math.degrees(j.range_rad[1])],
                "servo": j.servo,
            }
        d["camera"] = {
            "origin_m": [float(v) for v in self.camera.origin_m],
            "forward": [float(v) for v in self.camera.forward],
            "right": [float(v) for v in self.camera.right],
        }
        for p in self.parts:
            d["parts"].append({
                "name": p.name, "link": p.link, "kind": p.kind,
                "center_m": [float(v) for v in p.center_m],
                "size_m": [float(v) for v in p.size_m],
                "mass_kg": float(p.mass_kg),
            })
        custom = {n: s.to_dict() for n, s in self.servos.items() if SERVO_CATALOGUE.get(n) != s}
        if custom:
            d["servos"] = custom
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "head.toml") -> "HeadGeometry":
        try:
            return _from_dict(d).validate()
        except HeadFileError as e:
            raise HeadFileError(f"{source}: {e}") from None


_TOP_KEYS = {"name", "joints", "camera", "parts", "servos"}
_JOINT_KEYS = {"origin_m", "axis", "range_deg", "servo"}
_CAMERA_KEYS = {"origin_m", "forward", "right"}
_PART_KEYS = {"name", "link", "kind", "center_m", "size_m", "mass_kg"}


def _check_keys(table: dict, allowed: set, where: str, required: set | None = None) -> None:
    if not isinstance(table, dict):
        raise HeadFileError(f"{where} must be a table")
    for k in table:
        if k not in allowed:
            raise HeadFileError(f"{where}: unknown key {k!r}; allowed keys are {sorted(allowed)}")
    for k in sorted(required if required is not None else allowed):
        if k not in table:
            raise HeadFileError(f"{where}: missing key {k!r}; add it (see the reference head: wvr kinematics show reference)")


def _vec(v, where: str, n: int = 3) -> tuple[float, ...]:
    try:
        arr = [float(x) for x in v]
    except (TypeError, ValueError):
        raise HeadFileError(f"{where} = {brief(v)} must be a list of {n} numbers") from None
    if len(arr) != n:
        raise HeadFileError(f"{where} = {brief(v)} must have {n} numbers, not {len(arr)}")
    return tuple(arr)


#: No length of a wearable head reaches this (metres): a larger one is a unit mistake, and one
#: near 1e308 overflows to inf in the first product.
MAX_LENGTH_M = 10.0


def _check_vec(v, where: str) -> None:
    if not all(math.isfinite(x) for x in v):
        raise HeadFileError(f"{where} = {list(v)} has a non-finite value; give finite numbers in metres")
    if max(abs(x) for x in v) > MAX_LENGTH_M:
        raise HeadFileError(f"{where} = {brief(list(v))} is beyond {MAX_LENGTH_M:g} m; give the head's lengths in "
                            f"metres (a servo is about 0.02)")


def _check_unit(v, where: str) -> None:
    n = float(np.linalg.norm(v))
    if not math.isfinite(n) or abs(n - 1.0) > AXIS_TOL:
        hint = np.asarray(v, float) / n if n > 0 and math.isfinite(n) else None
        fix = f"; use {np.round(hint, 6).tolist()}" if hint is not None else ""
        raise HeadFileError(f"{where} = {list(v)} is not a unit vector (norm {n:.6g}){fix}")


def _from_dict(d: dict) -> HeadGeometry:
    _check_keys(d, _TOP_KEYS, "top level", required={"name", "joints", "camera", "parts"})
    servos = dict(SERVO_CATALOGUE)
    for sname, table in d.get("servos", {}).items():
        try:
            servos[sname] = servo_from_dict(sname, table, f"servos.{sname}")
        except ValueError as e:
            raise HeadFileError(str(e)) from None
    jt = d["joints"]
    _check_keys(jt, set(JOINT_NAMES), "joints", required=set(JOINT_NAMES))
    joints = []
    for name in JOINT_NAMES:
        t = jt[name]
        where = f"joints.{name}"
        _check_keys(t, _JOINT_KEYS, where, required={"origin_m", "axis", "range_deg"})
        lo, hi = _vec(t["range_deg"], f"{where}.range_deg", 2)
        joints.append(Joint(
            name=name,
            origin_m=_vec(t["origin_m"], f"{where}.origin_m"),
            axis=_vec(t["axis"], f"{where}.axis"),
            range_rad=(math.radians(lo), math.radians(hi)),
            servo=str(t.get("servo", "HS-50")),
        ))
    ct = d["camera"]
    _check_keys(ct, _CAMERA_KEYS, "camera")
    camera = CameraMount(
        origin_m=_vec(ct["origin_m"], "camera.origin_m"),
        forward=_vec(ct["forward"], "camera.forward"),
        right=_vec(ct["right"], "camera.right"),
    )
    parts = []
    if not isinstance(d["parts"], list):
        raise HeadFileError("parts must be an array of tables ([[parts]])")
    for k, t in enumerate(d["parts"]):
        where = f"parts[{k}]"
        _check_keys(t, _PART_KEYS, where, required=_PART_KEYS - {"kind"})
        try:
            mass = float(t["mass_kg"])
        except (TypeError, ValueError):
            raise HeadFileError(f"{where}.mass_kg = {brief(t['mass_kg'])} must be a number in kg") from None
        parts.append(Part(
            name=str(t["name"]), link=str(t["link"]), kind=str(t.get("kind", "bracket")),
            center_m=_vec(t["center_m"], f"{where}.center_m"),
            size_m=_vec(t["size_m"], f"{where}.size_m"),
            mass_kg=mass,
        ))
    return HeadGeometry(name=str(d["name"]), joints=tuple(joints), camera=camera, parts=tuple(parts), servos=servos)


def load_head(path: str | Path) -> HeadGeometry:
    """Read and validate a head.toml. ``"reference"`` loads the shipped reference head."""
    if str(path) == "reference":
        return reference_head()
    d = read_toml(path, HeadFileError, "a head.toml path or 'reference'")
    return HeadGeometry.from_dict(d, source=str(path))


def save_head(head: HeadGeometry, path: str | Path) -> None:
    """Write head.toml (validated first, so a saved file always loads)."""
    head.validate()
    Path(path).write_text(tomli_w.dumps(head.to_dict()))


def reference_head() -> HeadGeometry:
    """The reference head, modelled on the paper's (HS-50 servos, shoulder-worn, Fig. 1a/2a)."""
    text = resources.files("kinematics").joinpath("data/reference_head.toml").read_text()
    return HeadGeometry.from_dict(tomllib.loads(text), source="reference_head.toml")
