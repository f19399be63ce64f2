"""Named, seeded scenarios: where the wearer is, what the body does, what a recording's head does.

The body's motion is named (``stand``, ``walk``, ``sit-down``) and supplied by whoever builds
the wearer (the placement motions, through ``wvr``); the scenario places the body in the world
(``body_xy``, ``body_yaw``: the body frame faces -y rotated by the yaw) and says what the
scripted head looks at in a recording (the closed loop replaces the script by a controller).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from .scene import Workbench


@dataclass(frozen=True)
class Scenario:
    name: str
    motion: str
    seconds: float
    body_xy: tuple[float, float]
    body_yaw: float
    gaze: str                     # "sweep-bench", "follow-bench", "follow-card", "hold-target" or "still"
    walk_speed_m_s: float = 0.0
    bench: Workbench = field(default_factory=Workbench)
    light: float = 1.0
    dim_to: float | None = None   # light scale at the end of the scenario (linear ramp), if dimming
    stool: bool = False
    moving_card: bool = False     # a textured card moved about above the bench (2D tracking)

    def T_world_card(self, t: float) -> np.ndarray:
        """(4, 4) the moving card's pose at time t: its centre and axes (x along its length, z
        out of its textured face), held 12 cm above the bench's front edge, between the wearer
        and the target, and moved as a hand would: sliding, lifting, turning and tilting."""
        b = self.bench
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("zyx", [0.5 * math.sin(2 * math.pi * t / 8.0), 0.2 * math.sin(2 * math.pi * t / 7.0),
                                                0.25 * math.sin(2 * math.pi * t / 5.0)]).as_matrix()
        T[:3, 3] = [b.target_xy[0] + 0.08 * math.sin(2 * math.pi * t / 6.0),
                    b.target_xy[1] + 0.24 + 0.04 * math.sin(2 * math.pi * t / 4.5),
                    b.height + 0.12 + 0.02 * math.sin(2 * math.pi * t / 3.5)]
        return T

    def card_corners(self, t: float) -> np.ndarray:
        """(4, 3) world corners of the moving card's textured face at time t, in the order of
        its texture: (-x, -y), (+x, -y), (+x, +y), (-x, +y) in the card's frame."""
        w, h = MOVING_CARD_SIZE
        local = np.array([[-w / 2, -h / 2, MOVING_CARD_T / 2], [w / 2, -h / 2, MOVING_CARD_T / 2],
                          [w / 2, h / 2, MOVING_CARD_T / 2], [-w / 2, h / 2, MOVING_CARD_T / 2]])
        T = self.T_world_card(t)
        return local @ T[:3, :3].T + T[:3, 3]

    def T_world_occluder(self, t: float) -> np.ndarray:
        """(4, 4) the occluder (a finger-like bar across the card, 5 mm above its face): it
        slides in over 0.5 s from t = 1 s to cover the card's last quarter along x (25% of its
        area) until t = 3 s, then slides out."""
        w, _ = MOVING_CARD_SIZE
        a = min(max(t - 1.0, 0.0) / 0.5, 1.0) * (1.0 - min(max(t - 3.0, 0.0) / 0.5, 1.0))
        x = (w / 2 + w / 8 + 0.03) - a * (w / 8 + 0.03 + w / 8)   # from beyond the edge to centre 3w/8
        T_card_occ = np.eye(4)
        T_card_occ[:3, 3] = [x, 0.0, MOVING_CARD_T / 2 + 0.005 + OCCLUDER_T / 2]
        return self.T_world_card(t) @ T_card_occ

    def T_world_body(self) -> np.ndarray:
        """(4, 4) where the wearer's body frame is placed in the world at t = 0."""
        c, s = math.cos(self.body_yaw), math.sin(self.body_yaw)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = self.body_xy
        return T

    def light_at(self, t: float, duration: float | None = None) -> float:
        """Light scale at time t; a dimming ramp runs over ``duration`` (default the scenario's)."""
        if self.dim_to is None:
            return self.light
        a = min(max(t / (duration or self.seconds), 0.0), 1.0)
        return (1 - a) * self.light + a * self.dim_to

    def look_at(self, t: float, wearer_xy: np.ndarray) -> np.ndarray:
        """World point the scripted head fixates at time t (recordings only). "still" fixates
        the target at t = 0 only; the recorder then holds the joints (the head rides the body)."""
        b = self.bench
        target = np.r_[b.target_xy, b.height]
        if self.gaze in ("hold-target", "still"):
            return target
        if self.gaze == "sweep-bench":
            return target + np.array([0.35 * math.sin(2 * math.pi * t / 9.0), -0.12 * math.sin(2 * math.pi * t / 6.0), 0.0])
        if self.gaze == "follow-card":
            # Between the target and the moving card, so both stay in view and the camera moves.
            return 0.5 * (target + self.T_world_card(t)[:3, 3])
        if self.gaze == "follow-bench":
            # First the target (for SLAM's start-up), then, blending in over a second, the bench
            # point beside the wearer, wandering ahead and back along it.
            x = float(np.clip(wearer_xy[0] + 0.25 * math.sin(2 * math.pi * t / 7.0), b.centre_xy[0] - b.size[0] / 2 + 0.1,
                              b.centre_xy[0] + b.size[0] / 2 - 0.1))
            follow = np.array([x, b.target_xy[1], b.height])
            a = min(max(t - 1.0, 0.0), 1.0)
            a = a * a * (3 - 2 * a)
            return (1 - a) * target + a * follow
        raise ValueError(f"unknown gaze script {self.gaze!r}")


#: The moving card (m): its face (length, width), its thickness, and the occluder's thickness.
MOVING_CARD_SIZE = (0.14, 0.10)
MOVING_CARD_T = 0.003
OCCLUDER_T = 0.012

#: What the closed loop's controller may be asked to do (runtime.twin.loop.Task).
TASKS = ("fixate", "saccade", "stabilise", "body", "track")

SCENARIOS: dict[str, Scenario] = {
    "workbench-static": Scenario("workbench-static", "stand", 12.0, (0.0, 0.05), 0.0, "sweep-bench"),
    # Walking slowly along a long bench on the wearer's right (the body faces +x).
    "walk": Scenario("walk", "walk", 12.0, (-1.6, 0.05), math.pi / 2, "follow-bench", walk_speed_m_s=0.27,
                     bench=Workbench(centre_xy=(0.0, -0.75), size=(3.6, 0.7), target_xy=(-1.35, -0.6))),
    "sit-down": Scenario("sit-down", "sit-down", 6.0, (0.0, 0.15), 0.0, "hold-target", stool=True),
    # A textured card moved about in front of the camera, which follows it: 2D tracking data
    # with ground truth (card_corners), a quarter of the card occluded from 1 s to 3 s.
    "workbench-card": Scenario("workbench-card", "stand", 6.0, (0.0, 0.05), 0.0, "follow-card", moving_card=True),
    # Sitting down with the head held still on the body: the camera turns with the torso, a
    # rotation-dominated sequence for stabilisation (the scripted sit-down's head cancels it).
    "sit-down-head-still": Scenario("sit-down-head-still", "sit-down", 6.0, (0.0, 0.15), 0.0, "still", stool=True),
    # The same walk towards a target on the bench 1.8 m ahead, which the head can fixate for
    # the whole 6 s (the gaze task of the closed loop; walk's own target falls out of the
    # head's reach within a second as the wearer walks away from it).
    "walk-ahead": Scenario("walk-ahead", "walk", 6.0, (-1.6, 0.05), math.pi / 2, "hold-target", walk_speed_m_s=0.27,
                           bench=Workbench(centre_xy=(0.0, -0.75), size=(3.6, 0.7), target_xy=(0.2, -0.6))),
}


def get_scenario(name: str | Scenario) -> Scenario:
    if isinstance(name, Scenario):
        return name
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}") from None
