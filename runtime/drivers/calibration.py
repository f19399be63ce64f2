"""Per-channel servo calibration: joint angle <-> pulse width (rig.toml [servo.calibration.*])."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import DriverError


@dataclass(frozen=True)
class ServoCalibration:
    """pulse_us = neutral_us + sign * us_per_deg * degrees(q), within the board's min_us..max_us."""

    neutral_us: float
    us_per_deg: float
    sign: int
    min_us: float
    max_us: float

    def __post_init__(self):
        if self.sign not in (1, -1):
            raise DriverError(f"sign = {self.sign!r} must be +1 or -1 (which way a positive angle turns)")
        if not (math.isfinite(self.us_per_deg) and self.us_per_deg > 0):
            raise DriverError(f"us_per_deg = {self.us_per_deg!r} must be positive")
        if not (0 < self.min_us < self.neutral_us < self.max_us < 4096):
            raise DriverError(f"min_us < neutral_us < max_us must hold (got {self.min_us}, {self.neutral_us}, "
                              f"{self.max_us}), all within the Maestro's 0..4096 us")

    @property
    def us_per_rad(self) -> float:
        return self.us_per_deg * 180.0 / math.pi

    def to_us(self, q_rad) -> np.ndarray:
        return self.neutral_us + self.sign * self.us_per_rad * np.asarray(q_rad, float)

    def to_rad(self, us) -> np.ndarray:
        return (np.asarray(us, float) - self.neutral_us) / (self.sign * self.us_per_rad)

    def to_qus(self, q_rad) -> int:
        """The Maestro target (quarter-microseconds) for an angle, clipped to min_us..max_us (the
        last software guard: never a pulse outside the calibrated range)."""
        us = float(np.clip(self.to_us(q_rad), self.min_us, self.max_us))
        return int(np.clip(round(4.0 * us), math.ceil(4.0 * self.min_us), math.floor(4.0 * self.max_us)))

    def angle_range(self) -> tuple[float, float]:
        """(lo, hi) rad reachable inside min_us..max_us."""
        a, b = float(self.to_rad(self.min_us)), float(self.to_rad(self.max_us))
        return (min(a, b), max(a, b))
