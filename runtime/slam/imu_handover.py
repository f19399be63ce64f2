"""The IMU handed a map started from natural features: a visual-inertial start in the filter.

A two-view start fixes the map's unit arbitrarily and its frame to the first camera's, which
knows nothing of gravity, so the IMU cannot drive the prediction at first. The filter runs on
the camera alone while the camera's poses are kept; once the IMU's scale and gravity estimate
over them (imu_scale.estimate_scale, the linear initialisation of Mur-Artal and Tardos 2017) is
observed well enough, the IMU is handed the map: the camera block's scale state ``k`` (map
units per metre, layout.py) and its gravity state ``g`` (the map's frame) take the estimate with
priors wide enough for the filter to correct them, and the accelerometer's bias takes the
estimate's. From then the IMU drives the prediction (inertial.py) and the filter refines ``k``
and ``g`` with every frame (a gravity held at the estimate's, a degree or two off, put its error
into ``k``): the scale then follows the IMU's accelerations rather than the camera-only
filter's short-term motion, which overshoots them by a few percent (the constant-velocity model
trades some translation for rotation). As ORB-SLAM3 initialises its IMU after a visual-only
start, here in an EKF (Nutzi et al. 2011 keep such a scale state in theirs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import MapSettings
from .imu_scale import STRIDE_S, ScaleEstimate, preintegrate, solve_scale
from .layout import BA_SLICE, G_SLICE, SCALE_INDEX
from .state import State

#: The camera accelerated this much (RMS, m/s^2) for the scale to be observed.
MIN_EXCITATION_M_S2 = 0.2
#: Estimates are tried this often (s of the camera's poses), not every frame.
TRY_EVERY_S = 0.25
#: Frame triplets an estimate needs: three equations each for six unknowns (the scale, gravity's
#: direction, the accelerometer's bias), twice over, so that its spread means something.
MIN_TRIPLETS = 5
#: Gravity's magnitude is known (m/s^2): only its direction in the map is the estimate's to learn.
GRAVITY_MAGNITUDE_SIGMA = 0.05


@dataclass(frozen=True)
class Handover:
    """What the IMU was handed: at ``t`` (s), after ``seconds`` of the camera's poses, the scale
    estimate ``estimate``; ``k`` (map units per metre) and its prior standard deviation ``sigma_k``."""

    t: float
    seconds: float
    estimate: ScaleEstimate
    k: float
    sigma_k: float


class ImuHandover:
    """Keeps the camera's poses from a natural start until the IMU's estimate over them is good
    enough (:meth:`add` returns it), then is done. Only the frames an estimate takes are kept
    (imu_scale.kept_frames: the same choice over the same poses), each interval between them
    pre-integrated once, so a try costs the solve, not the whole run's integration again."""

    def __init__(self, settings: MapSettings):
        self.settings = settings
        self.t: list[float] = []
        self.r: list[np.ndarray] = []
        self.R: list[np.ndarray] = []
        self._pre: dict[int, tuple] = {}        # kept interval i (frames i, i + 1) -> its pre-integration
        self._t_first = self._t_last = None
        self._tried = -np.inf
        self.done: Handover | None = None

    def add(self, t: float, r: np.ndarray, R_world_cam: np.ndarray, imu_rows: np.ndarray) -> ScaleEstimate | None:
        """The camera at ``t`` (s), ``r`` (3,) map units, ``R_world_cam`` (3, 3); ``imu_rows``
        (m, 7) every IMU sample since the start. The estimate over the poses so far when it is
        observed well enough to hand the map over, else None."""
        t = float(t)
        if self._t_first is None:
            self._t_first = t
        self._t_last = t
        if not self.t or t - self.t[-1] >= STRIDE_S:
            self.t.append(t)
            self.r.append(np.array(r, float))
            self.R.append(np.array(R_world_cam, float))
        s = self.settings.imu
        if t - self._t_first < s.handover_min_s or t - self._tried < TRY_EVERY_S or len(imu_rows) < 3:
            return None
        self._tried = t
        t_imu = imu_rows[:, 0]
        inside = [i for i, ti in enumerate(self.t) if t_imu[0] <= ti <= t_imu[-1]]
        if len(inside) < 3:
            return None
        for i in inside[:-1]:
            if i not in self._pre:
                self._pre[i] = preintegrate(t_imu, imu_rows[:, 1:4], imu_rows[:, 4:7], self.t[i], self.t[i + 1])
        e = solve_scale(np.array(self.t)[inside], np.array(self.r)[inside], np.array(self.R)[inside],
                        [self._pre[i] for i in inside[:-1]])
        if e is None or e.triplets < MIN_TRIPLETS or not np.isfinite(e.scale) or e.scale <= 0 or \
                e.excitation < MIN_EXCITATION_M_S2 or e.sigma_rel > s.handover_max_sigma:
            return None
        return e

    def hand_over(self, state: State, e: ScaleEstimate) -> Handover:
        """Write the estimate ``e`` into ``state`` (a 24-number camera block): ``k`` = 1 / scale,
        with a relative standard deviation of at least ``handover_scale_sigma``; gravity ``g`` the
        estimate's, its direction with ``handover_gravity_sigma`` (rad) and its magnitude with
        GRAVITY_MAGNITUDE_SIGMA; both uncorrelated with the rest. The accelerometer's bias the
        estimate's."""
        k = 1.0 / e.scale
        s = self.settings.imu
        sigma_k = k * max(e.sigma_rel, s.handover_scale_sigma)
        g = np.asarray(e.g_world, float)
        u = g / np.linalg.norm(g)
        across = np.eye(3) - np.outer(u, u)
        x, P = state.x.copy(), state.P.copy()
        x[SCALE_INDEX] = k
        x[G_SLICE] = g
        for sl in (slice(SCALE_INDEX, SCALE_INDEX + 1), G_SLICE):
            P[sl, :] = 0.0
            P[:, sl] = 0.0
        P[SCALE_INDEX, SCALE_INDEX] = sigma_k**2
        P[G_SLICE, G_SLICE] = (np.linalg.norm(g) * s.handover_gravity_sigma) ** 2 * across \
            + GRAVITY_MAGNITUDE_SIGMA**2 * np.outer(u, u)
        x[BA_SLICE] = e.accel_bias
        state.x, state.P = x, P
        self.done = Handover(self._t_last, self._t_last - self._t_first, e, k, sigma_k)
        self.t, self.r, self.R, self._pre = [], [], [], {}
        return self.done
