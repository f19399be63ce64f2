"""Servo catalogue: the physical limits of the motors that drive the head's axes.

The figures are the ones the paper gives for the HiTEC HS-50 (section 2): 160 degrees of
travel, up to 10 rad/s, 0.06 Nm of axis torque, 6 g in a volume of about 6 cm^3. They are hard
limits: the command filter in :mod:`kinematics.servo` never lets a command exceed them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class ServoModel:
    """One servo type.

    Attributes
    ----------
    name : str
    travel_rad : float
        Total angular travel (max - min), radians.
    max_speed_rad_s : float
        No-load speed limit, rad/s.
    stall_torque_nm : float
        Peak axis torque, N m.
    mass_kg : float
        Mass of the servo body, kg.
    size_m : tuple of 3 floats
        Box of the servo body as (length, width, height), metres. The output shaft runs along
        the height, centred across the width, half a width in from one end of the length (the
        usual hobby-servo layout); design's layouts place servo boxes by this rule.
    armature_kgm2 : float
        Rotor inertia reflected through the gear train, kg m^2, added to the joint's
        inertia in dynamics and in the MJCF model.
    """

    name: str
    travel_rad: float
    max_speed_rad_s: float
    stall_torque_nm: float
    mass_kg: float
    size_m: tuple[float, float, float]
    armature_kgm2: float = 0.0

    @property
    def volume_m3(self) -> float:
        return float(self.size_m[0] * self.size_m[1] * self.size_m[2])

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("name")
        d["travel_deg"] = math.degrees(d.pop("travel_rad"))
        d["size_m"] = list(d["size_m"])
        return d


# 24 x 12 x 21 mm = 6.05 cm^3, the paper's "about 6 cm^3" (the bare case is a little smaller;
# the box includes the output horn and mounting tabs, which is what collides).
HS50 = ServoModel(
    name="HS-50",
    travel_rad=math.radians(160.0),
    max_speed_rad_s=10.0,
    stall_torque_nm=0.06,
    mass_kg=0.006,
    size_m=(0.024, 0.012, 0.021),
    # Not published. Estimate: a ~6 mm coreless rotor (~1e-9 kg m^2) through the ~180:1 train
    # that turns ~2000 rad/s at the motor into 10 rad/s at the horn: 1e-9 * 180^2 = 3e-5.
    # It dominates the links' own inertia (~1e-6), as it does in any geared micro servo.
    armature_kgm2=3.0e-5,
)

SERVO_CATALOGUE: dict[str, ServoModel] = {HS50.name: HS50}

SERVO_KEYS = {"travel_deg", "max_speed_rad_s", "stall_torque_nm", "mass_kg", "size_m", "armature_kgm2"}


def servo_from_dict(name: str, d: dict, where: str) -> ServoModel:
    """Build a :class:`ServoModel` from a TOML table, raising ``ValueError`` naming the field."""
    unknown = set(d) - SERVO_KEYS
    if unknown:
        raise ValueError(
            f"{where}: unknown key {sorted(unknown)[0]!r}; a servo table accepts {sorted(SERVO_KEYS)}"
        )
    missing = (SERVO_KEYS - {"armature_kgm2"}) - set(d)
    if missing:
        raise ValueError(f"{where}: missing key {sorted(missing)[0]!r}; give it (see HS-50 in the reference head)")
    try:
        size = tuple(float(v) for v in d["size_m"])
        values = {k: float(d[k]) for k in ("travel_deg", "max_speed_rad_s", "stall_torque_nm", "mass_kg")}
        armature = float(d.get("armature_kgm2", 0.0))
    except (TypeError, ValueError):
        raise ValueError(f"{where}: every value must be a number (size_m three numbers), in the units its key "
                         f"names") from None
    return ServoModel(
        name=name,
        travel_rad=math.radians(values["travel_deg"]),
        max_speed_rad_s=values["max_speed_rad_s"],
        stall_torque_nm=values["stall_torque_nm"],
        mass_kg=values["mass_kg"],
        size_m=size,
        armature_kgm2=armature,
    )
