"""Glances during a fixation (``--task fixate --glances``, issue 49 part 2): the head leaves its
target briefly when SLAM's camera position grows uncertain along one direction, looks where that
direction is best observed, and comes back.

The trigger: the camera position's covariance ``P_rr`` (the filter's, 3x3, m^2) has a largest
eigenvalue ``sigma^2``; when ``sigma`` passes ``bound_m`` (and ``min_interval_s`` has passed since
the last glance ended), a glance is due. Its direction ``v`` (the eigenvector) is the pose's
weakest.

The view: among the head's reachable views (the explore candidates, runtime.apps.explore), the
one whose predicted measurements bring the most information along ``v``:
``0.5 ln(w' Sigma w / w' Sigma+ w)`` with ``w = (v, 0)`` in the pose's (position, rotation)
space, ``Sigma`` the pose covariance carried through the head's motion and ``Sigma+`` after the
view's EKF update (the filter's own Jacobians; the pixel noise is the filter's over the square
root of the dwell's frames, each of which measures the view). A view bringing less than
``min_gain_nats`` is not worth leaving the target for: no glance.

The schedule: saccade to the view (``out``), stay ``dwell_s`` once landed (``at``; a saccade that
has not landed within ``give_up_s`` comes back at once), saccade back to the target (``back``),
and fixate again once landed. Nothing here reads the simulator: only SLAM's state and the head.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from kinematics import HeadGeometry
from kinematics.camera import CameraIntrinsics

from ..slam.state import State
from .explore import ExploreChoice, ExploreSettings, candidate_views, score_views

PHASES = ("fixating", "out", "at", "back")


@dataclass(frozen=True)
class GlanceSettings:
    """bound_m : the camera position's standard deviation along its weakest direction above which
    a glance is due, m. min_interval_s : at least this long between a glance's end and the next.
    dwell_s : time at the glance's view once landed, s. give_up_s : a saccade out that has not
    landed by then comes back, s. min_gain_nats : a view must bring at least this information
    along the weak direction. views : the candidate views (explore's grid)."""

    bound_m: float = 0.01
    min_interval_s: float = 4.0
    dwell_s: float = 0.5
    give_up_s: float = 1.5
    min_gain_nats: float = 0.05
    views: ExploreSettings = field(default_factory=ExploreSettings)

    def __post_init__(self):
        for name in ("bound_m", "dwell_s", "give_up_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"GlanceSettings.{name} = {v} must be a positive number")
        for name in ("min_interval_s", "min_gain_nats"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"GlanceSettings.{name} = {v} must be a finite number >= 0")


def weakest_direction(P_rr: np.ndarray) -> tuple[float, np.ndarray]:
    """(sigma m, v (3,) unit): the standard deviation of the camera position ``P_rr`` (3, 3) m^2
    along its weakest direction (largest eigenvalue) and that direction."""
    P = 0.5 * (np.asarray(P_rr, float) + np.asarray(P_rr, float).T)
    w, V = np.linalg.eigh(P)
    return math.sqrt(max(float(w[-1]), 0.0)), V[:, -1].copy()


def choose_glance(head: HeadGeometry, cam: CameraIntrinsics, state: State, T_world_mount: np.ndarray,
                  q_current: np.ndarray, sigma_pixel: float, direction: np.ndarray,
                  settings: GlanceSettings = GlanceSettings(),
                  map_points_world: np.ndarray | None = None) -> ExploreChoice:
    """The view that observes the camera position along ``direction`` (3,) best: an
    :class:`ExploreChoice` whose ``score`` is that information, nats (-inf where not a candidate);
    ``best`` is -1 when no candidate brings ``min_gain_nats``. The other arguments as
    :func:`runtime.apps.explore.choose_fixation`'s."""
    c = candidate_views(head, T_world_mount, q_current, settings.views, map_points_world)
    n, cand = len(c.directions), c.candidate
    info, along = np.zeros(n), np.zeros(n)
    empty, nvis = np.ones(n), np.zeros(n, int)
    if cand.any():
        w = np.concatenate([np.asarray(direction, float).reshape(3), np.zeros(3)])
        s = score_views(state, cam, c.T_cam_cand[cand], sigma_pixel, settings.views.margin_px,
                        settings.views.measure_max, settings.views.cells, direction=w)
        info[cand], along[cand], empty[cand], nvis[cand] = s.pose_info, s.along, s.empty, s.n_visible
    score = np.where(cand, along, -np.inf)
    best = int(np.argmax(score)) if cand.any() else -1
    if best >= 0 and score[best] < settings.min_gain_nats:
        best = -1
    return ExploreChoice(c.directions, c.points, c.reachable, c.q, info, empty, nvis, score, best)


class GlanceSchedule:
    """The phases of glances during one fixation task (module docstring): ``fixating``, ``out``
    (saccading to the view), ``at`` (dwelling there), ``back`` (saccading to the target).

    The closed loop asks :meth:`due` while fixating, calls :meth:`begin` when it sends the head
    out, :meth:`landed` when the controller reports a landing, and :meth:`step` every period,
    which says when to send the head back (``"return"``)."""

    def __init__(self, settings: GlanceSettings = GlanceSettings()):
        self.settings = settings
        self.phase = "fixating"
        self.point: np.ndarray | None = None       # the glance's fixation point, world, m
        self._t_phase = -math.inf
        self._t_end = -math.inf
        self.count = 0

    @property
    def away(self) -> bool:
        """Whether the head is away from the target for a glance (out, at or back)."""
        return self.phase != "fixating"

    def due(self, t: float, sigma_m: float) -> bool:
        """A glance is due: fixating, ``min_interval_s`` since the last ended, and the position's
        standard deviation ``sigma_m`` along its weakest direction above ``bound_m``."""
        s = self.settings
        return self.phase == "fixating" and t - self._t_end >= s.min_interval_s and sigma_m > s.bound_m

    def begin(self, t: float, point: np.ndarray) -> None:
        self.phase, self._t_phase, self.point = "out", t, np.asarray(point, float).copy()
        self.count += 1

    def not_worth(self, t: float) -> None:
        """No view was worth a glance: wait ``min_interval_s`` before asking again."""
        self._t_end = t

    def landed(self, t: float) -> None:
        if self.phase == "out":
            self.phase, self._t_phase = "at", t
        elif self.phase == "back":
            self.phase, self._t_end, self.point = "fixating", t, None

    def step(self, t: float) -> str | None:
        """``"return"`` when the head should go back to the target now (the dwell is over, or
        the saccade out did not land in time; the phase becomes ``back``); ``"resume"`` when the
        saccade back has not landed in time either (the phase becomes ``fixating``: the loop
        fixates the target again as the task does)."""
        s = self.settings
        if (self.phase == "at" and t - self._t_phase >= s.dwell_s) or \
                (self.phase == "out" and t - self._t_phase >= s.give_up_s):
            self.phase, self._t_phase = "back", t
            return "return"
        if self.phase == "back" and t - self._t_phase >= s.give_up_s:
            self.phase, self._t_end, self.point = "fixating", t, None
            return "resume"
        return None
