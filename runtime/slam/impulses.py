"""Impulse adaptation: the constant-velocity model's impulses each track predicts with, scaled to
the accelerations its own velocity estimates show while the camera turns (motion.adapted_sigma_a,
motion.adapted_sigma_alpha), and the test of whether a frame's update starts a turn."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .config import SlamConfig
from .filter import FrameUpdate
from .layout import V_SLICE, W_SLICE
from .motion import adapted_sigma_a, adapted_sigma_alpha, turning
from .state import State


class ImpulseAdapter:
    """The impulses one track predicts with (``motion_cfg``: ``cfg`` with its ``sigma_a`` and
    ``sigma_alpha`` adapted, SlamConfig.impulses.adapt_sigma_a, adapt_sigma_alpha) and the
    history they are estimated from: (t, v (3,), trace of v's covariance, w (3,), trace of w's
    covariance)."""

    def __init__(self, cfg: SlamConfig):
        self.cfg = cfg
        self.motion_cfg = cfg
        self.v_hist: list[tuple[float, np.ndarray, float, np.ndarray, float]] = []
        self.t_start: float | None = None

    @property
    def at_priors(self) -> bool:
        """Whether the impulses are the configured priors."""
        return self.motion_cfg.motion == self.cfg.motion

    def reset(self) -> None:
        """Back to the priors (a lost track: nothing says how the camera moves now)."""
        self.motion_cfg = self.cfg

    def impulses(self, t: float, x: np.ndarray, var_v: float, var_w: float) -> tuple[list, float, float]:
        """The velocity and rate history with the estimates ``x`` now (the traces of their
        covariances ``var_v``, ``var_w``), and the impulses a prediction takes from it: the
        linear one while the camera turns faster than ``adapt_turn_rate``
        (motion.adapted_sigma_a), the angular one through a manoeuvre
        (motion.adapted_sigma_alpha)."""
        cfg = self.cfg
        span = cfg.impulses.adapt_window + cfg.impulses.adapt_lag
        t_keep = t - max(span, 1.05 * cfg.impulses.adapt_alpha_lag)
        hist = [h for h in self.v_hist if h[0] >= t_keep]
        hist.append((t, x[V_SLICE].copy(), var_v, x[W_SLICE].copy(), var_w))
        rate = float(np.linalg.norm(x[W_SLICE]))
        if not turning(cfg, rate):                  # both rules keep the priors: not built
            return hist, cfg.motion.sigma_a, cfg.motion.sigma_alpha
        th, v, tr_v, w, tr_w = (np.array([h[k] for h in hist]) for k in range(5))
        i = int(np.searchsorted(th, t - span))       # the linear rule's own span of the history
        sigma_a = adapted_sigma_a(cfg, th[i:], v[i:], tr_v[i:], rate)
        return hist, sigma_a, adapted_sigma_alpha(cfg, th, w, tr_w)

    def adapting(self, t: float) -> bool:
        """Whether the impulses adapt at time ``t``: an adaptation is on and ``adapt_after`` s
        have passed since the first frame asked."""
        cfg = self.cfg
        if not (cfg.impulses.adapt_sigma_a or cfg.impulses.adapt_sigma_alpha):
            return False
        if self.t_start is None:
            self.t_start = t
        return t - self.t_start >= cfg.impulses.adapt_after

    def adapt(self, t: float, state: State) -> None:
        """Keep the estimates of ``state`` after this frame and set the impulses the next
        prediction takes."""
        if self.adapting(t):
            x, P = state.x, state.P
            self.v_hist, sigma_a, sigma_alpha = self.impulses(t, x, float(np.trace(P[V_SLICE, V_SLICE])),
                                                              float(np.trace(P[W_SLICE, W_SLICE])))
            self.set(sigma_a, sigma_alpha)

    def set(self, sigma_a: float, sigma_alpha: float) -> None:
        """Predict with these impulses, m/s^2 and rad/s^2."""
        if (sigma_a, sigma_alpha) != (self.motion_cfg.motion.sigma_a, self.motion_cfg.motion.sigma_alpha):
            self.motion_cfg = replace(self.cfg, motion=replace(self.cfg.motion, sigma_a=sigma_a, sigma_alpha=sigma_alpha))

    def turn_began(self, t: float, fu: FrameUpdate, turn: list) -> bool:
        """Whether a frame's updates ``fu``, not yet written, start a turn: the impulses after
        them differ from the priors the frame was predicted with; if so they go in ``turn``."""
        cfg = self.cfg
        impulses = self.impulses(t, fu.x, float(fu.variances(V_SLICE).sum()),
                                 float(fu.variances(W_SLICE).sum()))[1:]
        if impulses == (cfg.motion.sigma_a, cfg.motion.sigma_alpha):
            return False
        turn.extend(impulses)
        return True
