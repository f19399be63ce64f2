"""A person's clicks on the first image, simulated: the known target's corners where the camera
model projects them, each moved by a seeded error of ``error_px`` pixels in a random direction
(people click 2-3 px off). The closed loop takes the result as its start-up input, as it would
take a target.toml a person made; only the composition root calls this (it reads truth).

A stand-in for ``runtime.twin.operator.clicked_target`` (same signature), which the twin's own
work adds; ``wvr.assemble`` uses that one when it exists.
"""

from __future__ import annotations

import numpy as np

from ..sequence import Target
from .recorder import target_in_first_frame
from .twin import Twin


def clicked_target(twin: Twin, error_px: float = 2.5, rng: np.random.Generator | None = None) -> Target:
    """The target of the twin's current view (call after reset) with clicks ``error_px`` off."""
    exact = target_in_first_frame(twin)
    rng = np.random.default_rng(0) if rng is None else rng
    angle = rng.uniform(0.0, 2.0 * np.pi, len(exact.uv))
    uv = exact.uv + error_px * np.column_stack([np.cos(angle), np.sin(angle)])
    return Target(xyz=exact.xyz, uv=uv)
