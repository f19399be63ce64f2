"""Named, seeded scenarios: the place, where the wearer is in it, what the body does, what a
recording's head does.

The place (``Scenario.scene``) is a workbench, a kitchen counter or an office desk, each with
its own known target (:mod:`runtime.twin.workbench`, :mod:`.kitchen`, :mod:`.office`); its
textures and layout come from the scene seed. The body's motion is named (``stand``, ``walk``,
``sit-down``, ``stand-then-sit-down``, ``turn-round``, ``turn-away``) and supplied by whoever builds the wearer (the placement motions, through
``wvr``); the scenario places the body in the world (``body_xy``, ``body_yaw``: the body frame
faces -y rotated by the yaw) and says what the scripted head looks at in a recording (the
closed loop replaces the script by a controller).

Gaze scripts (:meth:`Scenario.look_at`): ``sweep`` (over the target and around it),
``follow`` (the target, then the work surface beside the walking wearer), ``hold-target``,
``still`` (the target at t = 0, then the joints hold), ``follow-card`` (the hand-held card),
``gaze-away`` (the target, then away from it with the target out of view, then back).

A run's seed varies the motion a little (:meth:`Scenario.varied`): the body's place by up to
5 cm and the sweeps' amplitudes and relative phase by up to 20%, so runs over seeds differ in
motion as well as in sensor noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .places import KitchenCounter, OfficeDesk, Place, Workbench
from .props import MOVING_CARD_SIZE, MOVING_CARD_T, OCCLUDER_T

GAZES = ("sweep", "follow", "follow-card", "hold-target", "still", "gaze-away")

#: The seeded motion variation's bounds: body position (m, each axis), sweep amplitude (fraction),
#: phase of the second sweep component relative to the first (fraction of a cycle).
BODY_VARIATION_M = 0.05
SWEEP_VARIATION = 0.2

#: gaze-away: the gaze leaves the target at GAZE_AWAY_S[0] and is back at GAZE_AWAY_S[1] (each
#: move blends over GAZE_AWAY_BLEND_S; the script's 30 deg/s limit stretches it further).
GAZE_AWAY_S = (2.0, 5.0)
GAZE_AWAY_BLEND_S = 1.2


def _smoothstep(a: float) -> float:
    a = min(max(a, 0.0), 1.0)
    return a * a * (3 - 2 * a)


@dataclass(frozen=True)
class Scenario:
    name: str
    motion: str
    seconds: float
    body_xy: tuple[float, float]
    body_yaw: float
    gaze: str                     # one of GAZES
    walk_speed_m_s: float = 0.0
    scene: Place = field(default_factory=Workbench)
    light: float = 1.0
    dim_to: float | None = None   # light scale at the end of the scenario (linear ramp), if dimming
    stool: bool = False
    moving_card: bool = False     # a textured card moved about above the bench (2D tracking)
    sweep_scale: tuple[float, float] = (1.0, 1.0)   # the gaze sweeps' amplitudes (seeded variation)
    sweep_phase: float = 0.0      # rad, the second sweep component's phase (seeded variation)
    obeys_prompts: bool = False   # the wearer turns when a prompt asks (Twin.tell)

    def __post_init__(self):
        if self.gaze not in GAZES:
            raise ValueError(f"scenario {self.name}: unknown gaze script {self.gaze!r}; use one of {GAZES}")
        if self.moving_card and not isinstance(self.scene, Workbench):
            raise ValueError(f"scenario {self.name}: the moving card is held over a workbench")

    @property
    def bench(self) -> Place:
        """The place (older name, from when every place was a workbench); use ``scene``."""
        return self.scene

    def target_corners(self) -> np.ndarray:
        """(4, 3) the known target's corners, world, m (target.toml's points)."""
        return self.scene.target_corners()

    def varied(self, rng: np.random.Generator) -> "Scenario":
        """This scenario with the seeded motion variation drawn from ``rng``: the body moved by
        up to +-5 cm on each axis, each sweep amplitude scaled by 0.8..1.2 and the second sweep
        component's phase shifted by up to +-20% of a cycle. The place is untouched."""
        d = rng.uniform(-BODY_VARIATION_M, BODY_VARIATION_M, 2)
        s = rng.uniform(1 - SWEEP_VARIATION, 1 + SWEEP_VARIATION, 2)
        phase = float(rng.uniform(-SWEEP_VARIATION, SWEEP_VARIATION)) * 2 * math.pi
        return replace(self, body_xy=(self.body_xy[0] + float(d[0]), self.body_xy[1] + float(d[1])),
                       sweep_scale=(float(s[0]), float(s[1])), sweep_phase=phase)

    def T_world_card(self, t: float) -> np.ndarray:
        """(4, 4) the moving card's pose at time t: its centre and axes (x along its length, z
        out of its textured face), held 12 cm above the bench's front edge, between the wearer
        and the target, and moved as a hand would: sliding, lifting, turning and tilting."""
        b = self.scene
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

    def _sweep(self, t: float, scale: float = 1.0) -> np.ndarray:
        """The sweeping gaze's offset from the target at time t (the place's sweep axes)."""
        u, v = self.scene.sweep_axes()
        s1, s2 = self.sweep_scale
        return (scale * s1 * math.sin(2 * math.pi * t / 9.0)) * u + \
            (scale * s2 * math.sin(2 * math.pi * t / 6.0 + self.sweep_phase)) * v

    def look_at(self, t: float, wearer_xy: np.ndarray) -> np.ndarray:
        """World point the scripted head fixates at time t (recordings only). "still" fixates
        the target at t = 0 only; the recorder then holds the joints (the head rides the body)."""
        place = self.scene
        target = place.look_point()
        if self.gaze in ("hold-target", "still"):
            return target
        if self.gaze == "sweep":
            return target + self._sweep(t)
        if self.gaze == "follow-card":
            # Between the target and the moving card, so both stay in view and the camera moves.
            return 0.5 * (target + self.T_world_card(t)[:3, 3])
        if self.gaze == "follow":
            # First the target (for SLAM's start-up), then, blending in over a second, the work
            # surface beside the wearer, wandering ahead and back along it.
            follow = place.follow_point(wearer_xy[0] + 0.25 * (self.sweep_scale[0] *
                                                               math.sin(2 * math.pi * t / 7.0 + self.sweep_phase)))
            a = _smoothstep(t - 1.0)
            return (1 - a) * target + a * follow
        if self.gaze == "gaze-away":
            # A half-size sweep over the target, away to natural features only (looking about
            # there), and back.
            t0, t1 = GAZE_AWAY_S
            a = _smoothstep((t - t0) / GAZE_AWAY_BLEND_S) * (1 - _smoothstep((t - t1) / GAZE_AWAY_BLEND_S))
            home = target + self._sweep(t, 0.5)
            away = place.away_point() + np.array([0.15 * math.sin(2 * math.pi * (t - t0) / 4.0), 0.0,
                                                  0.08 * math.sin(2 * math.pi * (t - t0) / 3.0)])
            return (1 - a) * home + a * away
        raise ValueError(f"unknown gaze script {self.gaze!r}")


#: What the closed loop's controller may be asked to do (runtime.twin.loop.Task).
TASKS = ("fixate", "saccade", "stabilise", "body", "track", "explore")

_LONG_BENCH = dict(centre_xy=(0.0, -0.75), size=(3.6, 0.7))

SCENARIOS: dict[str, Scenario] = {
    "workbench-static": Scenario("workbench-static", "stand", 12.0, (0.0, 0.05), 0.0, "sweep"),
    # Walking slowly along a long bench on the wearer's right (the body faces +x).
    "walk": Scenario("walk", "walk", 12.0, (-1.6, 0.05), math.pi / 2, "follow", walk_speed_m_s=0.27,
                     scene=Workbench(**_LONG_BENCH, target_xy=(-1.35, -0.6))),
    "sit-down": Scenario("sit-down", "sit-down", 6.0, (0.0, 0.15), 0.0, "hold-target", stool=True),
    # Standing still for 8 s (time for a start without a target: --start head-motion), then
    # sitting down as in sit-down, the head on the target.
    "stand-then-sit-down": Scenario("stand-then-sit-down", "stand-then-sit-down", 14.0, (0.0, 0.15), 0.0,
                                    "hold-target", stool=True),
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
                           scene=Workbench(**_LONG_BENCH, target_xy=(0.2, -0.6))),
    # The gaze leaves the target for the far wall's poster (target out of view from about 3 s
    # to 7 s), looks about there, and comes back: natural features must hold the pose.
    "workbench-gaze-away": Scenario("workbench-gaze-away", "stand", 12.0, (0.0, 0.05), 0.0, "gaze-away"),
    # The kitchen counter: standing at the target and sweeping over the worktop and splash-back.
    "kitchen-static": Scenario("kitchen-static", "stand", 12.0, (-0.62, 0.05), 0.0, "sweep", scene=KitchenCounter()),
    # Walking along the counter from the target (the same place, another motion: map reuse).
    "kitchen-walk": Scenario("kitchen-walk", "walk", 12.0, (-1.0, 0.05), math.pi / 2, "follow", walk_speed_m_s=0.22,
                             scene=KitchenCounter()),
    # From the target on the worktop to the bright window and wall cupboards, and back.
    "kitchen-gaze-away": Scenario("kitchen-gaze-away", "stand", 12.0, (-0.62, 0.05), 0.0, "gaze-away",
                                  scene=KitchenCounter()),
    # The office: standing at the desk and sweeping over the sheet on it.
    "office-static": Scenario("office-static", "stand", 12.0, (-0.12, -0.15), 0.0, "sweep", scene=OfficeDesk()),
    # Sitting down at the desk, the head on the desk's target (the same place).
    "office-sit-down": Scenario("office-sit-down", "sit-down", 6.0, (-0.12, -0.05), 0.0, "hold-target", stool=True,
                                scene=OfficeDesk()),
    # The 21 x 15 cm target pinned to the wall at eye height, seen nearly frontally from about
    # 1.2 m by a small sweep (the planar PnP ambiguity case; the same place as office-static).
    "office-far-target": Scenario("office-far-target", "stand", 12.0, (-0.25, -0.05), 0.0, "sweep",
                                  scene=OfficeDesk(known="wall")),
    # Standing mid-room, 45 cm back from the workbench, and turning round in place to the left:
    # four 90 deg turns of 3 s, each after a pause (5 s still first, then 3.25 s after each). The
    # target on the bench is in view at the start only; the posters on all four sides and the
    # floor are what the map must grow over. The head rides the body in a recording.
    "turn-round-room": Scenario("turn-round-room", "turn-round", 30.0, (0.0, 0.05), 0.0, "still"),
    # The same place; the wearer turns 120 deg away from the bench after 4 s and then stands,
    # and obeys a prompt to turn (Twin.tell): the wearer in explore's dialogue (issue 49, part 3).
    "turn-away-ask": Scenario("turn-away-ask", "turn-away", 24.0, (0.0, 0.05), 0.0, "still", obeys_prompts=True),
}


def get_scenario(name: str | Scenario) -> Scenario:
    if isinstance(name, Scenario):
        return name
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}") from None
