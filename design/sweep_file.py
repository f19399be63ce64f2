"""sweep.toml: a design sweep as data (bounds, servo, camera, brackets, workload, budget, decision).

Loaded into a frozen :class:`SweepSpec`; every key is checked, unknown keys are errors, and the
spec has a content hash so a resumed sweep can refuse a changed file.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from kinematics import SERVO_CATALOGUE
from kinematics.tomlfile import brief, read_toml

#: The seven criteria, all minimised, named exactly so in every output (paper, section 2).
CRITERIA = (
    "working_volume_cm3", "self_collision", "integrated_torque", "max_torque_nm",
    "radius_elevation_mm", "radius_pan_mm", "radius_cyclotorsion_mm",
)
#: Inequality constraints (<= 0 is feasible).
CONSTRAINTS = ("torque_excess_nm", "rest_penetration_m", "part_overlap_m")
POSITIONS = ("elevation_motor", "pan_motor", "cyclotorsion_motor", "camera")
VARIABLES = tuple(f"{p}_{c}_m" for p in POSITIONS for c in "xyz")


#: The search algorithms (design.search): "surrogate" (the default) is AGE-MOEA2 with its
#: offspring pre-screened by a model, "agemoea2" AGE-MOEA2 alone, NSGA-III an earlier default,
#: random variation the paper's method and the baseline of design.convergence.
ALGORITHMS = ("agemoea2", "surrogate", "nsga3", "random")


class SweepFileError(ValueError):
    """A sweep.toml that cannot be used; the message names the field and the fix."""


#: Work-size bounds, checked before any work: each keeps one evaluation (or the algorithm's set
#: up) within about a second and its memory within tens of MB on a laptop.
MAX_COLLISION_STEPS = 40          # 64,000 postures
MIN_VOXEL_M = 0.0005              # the sweep costs ~ voxel_m**-4: 0.5 mm is ~1300 times 3 mm
MAX_VOXEL_M = 0.05
MAX_WORKLOAD_SAMPLES = 200_000    # 50 times the default workload's 3,983
MAX_SACCADE_DEG = 90.0            # a gaze redirection, not a turn of the head
MAX_REFERENCE_DIRECTIONS = 3003   # Das-Dennis, 7 objectives, 8 partitions


@dataclass(frozen=True)
class WorkloadSpec:
    rate_hz: float = 100.0
    saccade_amplitudes_deg: tuple[float, ...] = (5.0, 10.0, 20.0, 40.0)
    saccade_peak_rate_deg_s: float = 30.0
    walk_seconds: float = 2.0
    walk_step_hz: float = 2.0
    walk_bounce_m: float = 0.025
    walk_sway_m: float = 0.020
    walk_roll_deg: float = 3.0
    walk_pitch_deg: float = 2.0
    walk_yaw_deg: float = 4.0


@dataclass(frozen=True)
class SweepSpec:
    name: str
    servo: str
    range_deg: float
    evaluations: int
    seed: int
    algorithm: str
    partitions: int
    clearance_m: float
    camera_mass_kg: float
    camera_size_m: tuple[float, float, float]
    bracket_density_kg_m: float
    bracket_size_m: float
    bounds: tuple[tuple[float, float], ...]   # (12, 2) in VARIABLES order
    voxel_m: float
    collision_steps: int
    workload: WorkloadSpec
    decision_method: str
    decision_weights: tuple[float, ...]

    @property
    def xl(self) -> np.ndarray:
        return np.array([b[0] for b in self.bounds])

    @property
    def xu(self) -> np.ndarray:
        return np.array([b[1] for b in self.bounds])

    def digest(self) -> str:
        """Content hash of everything that changes results (budget, seed and algorithm excluded:
        those are run options a resume may not change either, checked separately)."""
        d = asdict(self)
        for k in ("evaluations", "seed", "algorithm"):
            d.pop(k)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


_SECTIONS = {
    "sweep": {"name", "servo", "range_deg", "evaluations", "seed", "algorithm", "partitions", "clearance_m"},
    "camera": {"mass_kg", "size_m"},
    "bracket": {"linear_density_kg_m", "size_m"},
    "bounds": set(POSITIONS),
    "criteria": {"voxel_m", "collision_steps"},
    "workload": set(WorkloadSpec.__dataclass_fields__),
    "decision": {"method", "weights"},
}


def _num(v, where: str, positive: bool = False, integer: bool = False, nonnegative: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise SweepFileError(f"{where} = {brief(v)} must be a finite number")
    if integer and int(v) != v:
        raise SweepFileError(f"{where} = {v!r} must be a whole number")
    if positive and v <= 0:
        raise SweepFileError(f"{where} = {v!r} must be positive")
    if nonnegative and v < 0:
        raise SweepFileError(f"{where} = {v!r} must be >= 0")
    return int(v) if integer else float(v)


def spec_from_dict(d: dict, source: str = "sweep.toml") -> SweepSpec:
    try:
        return _spec_from_dict(d)
    except SweepFileError as e:
        raise SweepFileError(f"{source}: {e}") from None


def _spec_from_dict(d: dict) -> SweepSpec:
    for sec in d:
        if sec not in _SECTIONS:
            raise SweepFileError(f"unknown section [{sec}]; sections are {sorted(_SECTIONS)}")
    for sec, keys in _SECTIONS.items():
        if sec not in d:
            raise SweepFileError(f"missing section [{sec}]; copy it from the default sweep (wvr design sweep-template)")
        for k in d[sec]:
            if k not in keys:
                raise SweepFileError(f"[{sec}]: unknown key {k!r}; allowed keys are {sorted(keys)}")
        required = keys - ({"name"} if sec == "sweep" else set()) - (set(WorkloadSpec.__dataclass_fields__) if sec == "workload" else set())
        for k in sorted(required):
            if k not in d[sec]:
                raise SweepFileError(f"[{sec}]: missing key {k!r}")
    s = d["sweep"]
    servo = str(s["servo"])
    if servo not in SERVO_CATALOGUE:
        raise SweepFileError(f"[sweep].servo = {servo!r} is not known; use one of {sorted(SERVO_CATALOGUE)}")
    travel = math.degrees(SERVO_CATALOGUE[servo].travel_rad)
    rng_deg = _num(s["range_deg"], "[sweep].range_deg", positive=True)
    if rng_deg > travel + 1e-9:
        raise SweepFileError(f"[sweep].range_deg = {rng_deg:g} exceeds the {servo}'s {travel:g} deg travel; use at most {travel:g}")
    algorithm = str(s["algorithm"])
    if algorithm not in ALGORITHMS:
        raise SweepFileError(f"[sweep].algorithm = {algorithm!r} must be one of {', '.join(map(repr, ALGORITHMS))}")
    bounds = []
    for pos in POSITIONS:
        b = d["bounds"][pos]
        where = f"[bounds].{pos}"
        try:
            arr = np.array(b, float)
        except (TypeError, ValueError):
            raise SweepFileError(f"{where} must be [[x_min, x_max], [y_min, y_max], [z_min, z_max]] in metres") from None
        if arr.shape != (3, 2) or not np.all(np.isfinite(arr)):
            raise SweepFileError(f"{where} must be [[x_min, x_max], [y_min, y_max], [z_min, z_max]] in metres")
        for c, (lo, hi) in zip("xyz", arr):
            if lo >= hi:
                raise SweepFileError(f"{where}: {c} bounds [{lo:g}, {hi:g}] must have min < max")
            if max(abs(lo), abs(hi)) > 1.0:
                raise SweepFileError(f"{where}: {c} bounds [{lo:g}, {hi:g}] look like millimetres; bounds are metres")
        bounds += [(float(lo), float(hi)) for lo, hi in arr]
    cam_size = d["camera"]["size_m"]
    if not (isinstance(cam_size, list) and len(cam_size) == 3):
        raise SweepFileError("[camera].size_m must be [depth, width, height] in metres")
    cam_size = tuple(_num(v, "[camera].size_m", positive=True) for v in cam_size)
    w = d["workload"]
    wl = WorkloadSpec(**{k: (tuple(_num(x, f"[workload].{k}", positive=True) for x in v) if isinstance(v, list)
                             else _num(v, f"[workload].{k}", positive=k not in ("walk_bounce_m", "walk_sway_m",
                                                                              "walk_roll_deg", "walk_pitch_deg",
                                                                              "walk_yaw_deg")))
                         for k, v in w.items()})
    dec = d["decision"]
    method = str(dec["method"])
    if method not in ("pseudo-weights", "knee"):
        raise SweepFileError(f"[decision].method = {method!r} must be 'pseudo-weights' or 'knee'")
    weights = dec["weights"]
    if not (isinstance(weights, list) and len(weights) == len(CRITERIA)):
        raise SweepFileError(f"[decision].weights must list {len(CRITERIA)} weights, one per criterion: {list(CRITERIA)}")
    weights = tuple(_num(v, "[decision].weights") for v in weights)
    if min(weights) < 0 or sum(weights) <= 0:
        raise SweepFileError("[decision].weights must be >= 0 with a positive sum")
    partitions = _num(s["partitions"], "[sweep].partitions", positive=True, integer=True)
    n_dirs = math.comb(partitions + len(CRITERIA) - 1, len(CRITERIA) - 1)
    if n_dirs > MAX_REFERENCE_DIRECTIONS:
        raise SweepFileError(f"[sweep].partitions = {partitions} gives {n_dirs:,} reference directions for "
                             f"{len(CRITERIA)} objectives (the population per generation); at most "
                             f"{MAX_REFERENCE_DIRECTIONS:,}: use partitions <= 8")
    voxel_m = _num(d["criteria"]["voxel_m"], "[criteria].voxel_m", positive=True)
    if not MIN_VOXEL_M <= voxel_m <= MAX_VOXEL_M:
        raise SweepFileError(f"[criteria].voxel_m = {voxel_m:g} must be from {MIN_VOXEL_M:g} to {MAX_VOXEL_M:g} m "
                             f"(the voxel sweep's work grows as voxel_m**-4; the default is 0.003)")
    steps = _num(d["criteria"]["collision_steps"], "[criteria].collision_steps", positive=True, integer=True)
    if not 2 <= steps <= MAX_COLLISION_STEPS:
        raise SweepFileError(f"[criteria].collision_steps = {steps} must be from 2 to {MAX_COLLISION_STEPS} "
                             f"(steps**3 postures per design; the default is 9)")
    for a in wl.saccade_amplitudes_deg:
        if a > MAX_SACCADE_DEG:
            raise SweepFileError(f"[workload].saccade_amplitudes_deg holds {a:g}: at most {MAX_SACCADE_DEG:g} deg")
    n = workload_samples(wl)
    if n > MAX_WORKLOAD_SAMPLES:
        raise SweepFileError(f"[workload] would have {n:,} samples (rate_hz x the saccades' and walk's seconds); at "
                             f"most {MAX_WORKLOAD_SAMPLES:,}: lower [workload].rate_hz, walk_seconds or the "
                             f"saccade amplitudes")
    return SweepSpec(
        name=str(s.get("name", "sweep")), servo=servo, range_deg=rng_deg,
        evaluations=_num(s["evaluations"], "[sweep].evaluations", positive=True, integer=True),
        seed=_num(s["seed"], "[sweep].seed", integer=True, nonnegative=True), algorithm=algorithm,
        partitions=partitions,
        # A negative clearance would let parts overlap and make every design feasible.
        clearance_m=_num(s["clearance_m"], "[sweep].clearance_m", nonnegative=True),
        camera_mass_kg=_num(d["camera"]["mass_kg"], "[camera].mass_kg", positive=True),
        camera_size_m=cam_size,
        bracket_density_kg_m=_num(d["bracket"]["linear_density_kg_m"], "[bracket].linear_density_kg_m",
                                  nonnegative=True),
        bracket_size_m=_num(d["bracket"]["size_m"], "[bracket].size_m", positive=True),
        bounds=tuple(bounds),
        voxel_m=voxel_m, collision_steps=steps,
        workload=wl, decision_method=method, decision_weights=weights,
    )


def workload_samples(wl: WorkloadSpec) -> int:
    """About the number of samples design.workload.build_workload makes (within a few), without making them."""
    h = 1.0 / wl.rate_hz
    n = 0
    for a in wl.saccade_amplitudes_deg:
        T = 1.875 * math.radians(a) / math.radians(wl.saccade_peak_rate_deg_s)
        n += 8 * max(min(int(round(T / h)), 10**12) + 1, 5)   # 4 directions from 2 starts
    return n + int(min(wl.walk_seconds / h, 10**12)) + 1


def load_sweep(path: str | Path | None = None) -> SweepSpec:
    """Read and validate a sweep.toml; ``None`` gives the shipped default sweep."""
    if path is None:
        return spec_from_dict(tomllib.loads(default_sweep_text()), "default_sweep.toml")
    d = read_toml(path, SweepFileError, "a sweep.toml (see: wvr design sweep-template)")
    return spec_from_dict(d, str(path))


def default_sweep_text() -> str:
    return resources.files("design").joinpath("data/default_sweep.toml").read_text()


def spec_to_dict(spec: SweepSpec) -> dict:
    """The sweep as a TOML-ready dict (the inverse of :func:`spec_from_dict`)."""
    b = [list(p) for p in spec.bounds]
    return {
        "sweep": {"name": spec.name, "servo": spec.servo, "range_deg": spec.range_deg,
                  "evaluations": spec.evaluations, "seed": spec.seed, "algorithm": spec.algorithm,
                  "partitions": spec.partitions, "clearance_m": spec.clearance_m},
        "camera": {"mass_kg": spec.camera_mass_kg, "size_m": list(spec.camera_size_m)},
        "bracket": {"linear_density_kg_m": spec.bracket_density_kg_m, "size_m": spec.bracket_size_m},
        "bounds": {pos: b[3 * k:3 * k + 3] for k, pos in enumerate(POSITIONS)},
        "criteria": {"voxel_m": spec.voxel_m, "collision_steps": spec.collision_steps},
        "workload": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(spec.workload).items()},
        "decision": {"method": spec.decision_method, "weights": list(spec.decision_weights)},
    }


def dump_spec(spec: SweepSpec) -> str:
    import tomli_w

    return tomli_w.dumps(spec_to_dict(spec))
