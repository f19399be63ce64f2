"""The impulses each track adapts to its own motion: the linear one (SlamConfig.impulses.adapt_sigma_a,
motion.impulse_sigma / adapted_sigma_a), checked against velocity histories whose white
acceleration is known and on the fast turn of test_slam_turn after a still start; the angular
one through a manoeuvre (SlamConfig.impulses.adapt_sigma_alpha, motion.adapted_sigma_alpha), against rate
histories of known angular acceleration and in a track."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from runtime.slam.config import DEFAULT_CONFIG
from runtime.slam.motion import adapted_sigma_a, adapted_sigma_alpha, impulse_sigma

T0 = DEFAULT_CONFIG.motion.motion_noise_interval
DT = 1.0 / 30.0


def history(sigma: float, n: int, noise: float, seed: int = 0, v0=(0.3, 0.0, -0.1)):
    """t (n,), v (n, 3), var_v (n,): a velocity driven by white acceleration ``sigma`` m/s^2
    (increments of variance sigma^2 dt t0 per axis), seen through estimates with independent
    errors of ``noise`` m/s per axis (their covariance's trace 3 noise^2)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    v = np.asarray(v0) + np.cumsum(rng.normal(0.0, sigma * np.sqrt(DT * T0), (n, 3)), axis=0)
    return t, v + rng.normal(0.0, noise, (n, 3)), np.full(n, 3 * noise * noise)


@pytest.mark.parametrize("sigma", [0.25, 1.0, 3.0])
def test_the_acceleration_of_a_known_random_walk_is_recovered(sigma):
    est = np.array([impulse_sigma(*history(sigma, 3000, 0.02, seed), 0.15, T0) for seed in range(4)])
    assert np.all(np.abs(est / sigma - 1.0) < 0.1), est


def test_the_estimates_own_errors_are_taken_out():
    """A constant velocity seen through noisy estimates shows no acceleration; counting the
    noise (a version that does not subtract the covariances) would give about 0.95 m/s^2."""
    t, v, var = history(0.0, 3000, 0.05)
    assert impulse_sigma(t, v, var, 0.15, T0) < 0.2
    assert impulse_sigma(t, v, 0 * var, 0.15, T0) > 0.8


def test_a_lag_longer_than_the_history_gives_nothing():
    t, v, var = history(1.0, 4, 0.0)
    assert np.isnan(impulse_sigma(t, v, var, 0.15, T0))


def test_the_impulse_is_the_estimate_times_the_margin_within_its_bounds():
    cfg = DEFAULT_CONFIG
    imp, mo = cfg.impulses, cfg.motion
    turning = 2.0 * imp.adapt_turn_rate
    still = history(0.0, 40, 0.005)
    assert adapted_sigma_a(cfg, *still, turning) == imp.sigma_a_min               # at rest: the floor
    mid = history(0.5, 3000, 0.0)
    est = impulse_sigma(*mid, imp.adapt_lag, T0)
    assert adapted_sigma_a(cfg, *mid, turning) == pytest.approx(imp.adapt_margin * est)
    assert imp.sigma_a_min < adapted_sigma_a(cfg, *mid, turning) < mo.sigma_a
    assert adapted_sigma_a(cfg, *history(3.0, 40, 0.0), turning) == mo.sigma_a    # a walker's bob: the prior
    short = tuple(a[:12] for a in still)                                        # 0.37 s: too short to say
    assert adapted_sigma_a(cfg, *short, turning) == mo.sigma_a
    assert adapted_sigma_a(cfg, *still, 0.5 * imp.adapt_turn_rate) == mo.sigma_a  # not turning: the prior
    assert adapted_sigma_a(replace(cfg, adapt_sigma_a=False), *still, turning) == mo.sigma_a


def test_a_track_adapts_its_impulse_from_its_own_velocity_estimates():
    """MonoSLAM on a still camera (the ray-cast target and its textured card, 90 frames): with
    the turn condition lifted, once ``adapt_after`` has passed and a second of velocity
    estimates shows no acceleration, the track predicts with the floor (FrameStats.sigma_a);
    by default a camera that does not turn keeps MonoSLAM's prior, as it does with adapting off."""
    from test_slam_recovery import CAM, RECT, view

    from runtime.sequence import Target
    from runtime.slam.config import MapSettings
    from runtime.slam.system import MonoSLAM

    img, uv, _ = view(0.6, 60.0)
    floor, prior = DEFAULT_CONFIG.impulses.sigma_a_min, DEFAULT_CONFIG.motion.sigma_a
    for cfg, expected in ((replace(DEFAULT_CONFIG, adapt_turn_rate=0.0), floor), (DEFAULT_CONFIG, prior),
                          (replace(DEFAULT_CONFIG, adapt_sigma_a=False, adapt_turn_rate=0.0), prior)):
        slam = MonoSLAM(CAM, cfg, MapSettings(), imu=False)
        slam.start(img, 0.0, Target(RECT, uv + 1.5))
        used = np.array([slam.process(img, k / 30).sigma_a for k in range(1, 91)])
        t = np.arange(1, 91) / 30
        assert (used[t <= cfg.impulses.adapt_after] == prior).all() and used[-1] == expected


def test_the_linear_impulse_decides_a_fast_turn_s_split_too():
    """test_slam_turn's pan with the angular impulse left at 6 rad/s^2: with the linear impulse a
    camera at rest gets (the floor, 1 m/s^2) the unpredicted turn is followed, with MonoSLAM's
    4 m/s^2 it is taken partly as an orbit about the new features' depth prior."""
    from test_slam_turn import turn_errors

    fixed = replace(DEFAULT_CONFIG, adapt_sigma_a=False)
    floor = np.array([turn_errors(replace(fixed, sigma_a=DEFAULT_CONFIG.impulses.sigma_a_min), seed) for seed in range(4)])
    prior = np.array([turn_errors(fixed, seed) for seed in range(4)])
    for name, e in (("1 m/s^2", floor), ("4 m/s^2", prior)):
        print(f"{name}: position cm {np.round(100 * e[:, 0], 2)}, rotation deg {np.round(np.degrees(e[:, 1]), 2)}")
    assert (floor[:, 0] < 0.01).all() and (floor[:, 1] < np.radians(0.5)).all()
    assert np.median(prior[:, 0]) > 0.02


def rates(alpha: float, n: int = 12, axis=(0.0, 0.6, 0.8), w0=(2.0, 0.0, 0.0), noise: float = 0.0):
    """t (n,), w (n, 3), var_w (n,): a rate from ``w0`` rad/s changing at a steady ``alpha``
    rad/s^2 about ``axis``, its estimates with errors of covariance trace ``noise^2``."""
    t = 5.0 + np.arange(n) * DT
    return t, np.asarray(w0) + np.outer(t - t[0], alpha * np.asarray(axis)), np.full(n, noise * noise)


def test_the_angular_impulse_is_the_manoeuvre_times_the_margin_within_its_bounds():
    cfg = DEFAULT_CONFIG
    imp, mo = cfg.impulses, cfg.motion
    assert adapted_sigma_alpha(cfg, *rates(12.0)) == pytest.approx(imp.adapt_alpha_margin * 12.0)
    assert adapted_sigma_alpha(cfg, *rates(1.0)) == mo.sigma_alpha            # a walker's sway: the prior
    assert adapted_sigma_alpha(cfg, *rates(0.0)) == mo.sigma_alpha
    assert adapted_sigma_alpha(cfg, *rates(200.0)) == imp.sigma_alpha_max      # the cap
    assert adapted_sigma_alpha(replace(cfg, adapt_sigma_alpha=False), *rates(12.0)) == mo.sigma_alpha
    assert adapted_sigma_alpha(cfg, *rates(12.0, n=1)) == mo.sigma_alpha      # nothing to compare
    # Turning slower than adapt_turn_rate (a walker's sway), the prior.
    assert adapted_sigma_alpha(cfg, *rates(12.0, w0=(0.1, 0.0, 0.0), n=3)) == mo.sigma_alpha
    # Only the last adapt_alpha_lag counts: a turn that started and stopped before it does not.
    t, w, var = rates(12.0, n=20)
    w[-5:] = w[-6]
    assert adapted_sigma_alpha(cfg, t, w, var) == mo.sigma_alpha
    # The estimates' own errors are taken out: 0.5 rad/s over 0.1 s, each estimate 0.3 rad/s
    # uncertain, is 2.6 rad/s^2 beyond them (5 seen), under the prior at the default margin.
    t, w, var = rates(5.0, noise=0.3)
    assert adapted_sigma_alpha(replace(cfg, adapt_alpha_margin=1.0, sigma_alpha=0.0), t, w, var) \
        == pytest.approx(np.sqrt(0.5**2 - 2 * 0.3**2) / 0.1, rel=0.02)
    assert adapted_sigma_alpha(cfg, t, w, var) == mo.sigma_alpha
    assert adapted_sigma_alpha(cfg, *rates(5.0, noise=0.2)[:2], var * 0) > mo.sigma_alpha
    # A prior above the cap is kept, never lowered.
    assert adapted_sigma_alpha(replace(cfg, sigma_alpha=40.0), *rates(12.0)) == 40.0


def test_a_track_raises_its_angular_impulse_when_its_rate_estimate_jumps():
    """MonoSLAM on a still camera keeps the prior (FrameStats.sigma_alpha); a rate estimate 3
    rad/s from the last (90 rad/s^2) has the next frame predicted with the cap, and with the
    prior when adapting is off."""
    from test_slam_recovery import CAM, RECT, view

    from runtime.sequence import Target
    from runtime.slam.config import MapSettings
    from runtime.slam.state import W_SLICE
    from runtime.slam.system import MonoSLAM

    img, uv, _ = view(0.6, 60.0)
    for cfg, expected in ((DEFAULT_CONFIG, DEFAULT_CONFIG.impulses.sigma_alpha_max),
                          (replace(DEFAULT_CONFIG, adapt_sigma_alpha=False), DEFAULT_CONFIG.motion.sigma_alpha)):
        slam = MonoSLAM(CAM, cfg, MapSettings(), imu=False)
        slam.start(img, 0.0, Target(RECT, uv + 1.5))
        still = np.array([slam.process(img, k / 30).sigma_alpha for k in range(1, 76)])
        assert (still == cfg.motion.sigma_alpha).all()
        track = slam.track
        track.state.x[W_SLICE] += [0.0, 3.0, 0.0]
        track.impulses.adapt(76 / 30, track.state)        # as after a frame whose update left the rate there
        assert slam.process(img, 76 / 30).sigma_alpha == expected


class _Captured(Exception):
    pass


@pytest.mark.parametrize("flag, adapting", [([], True), (["--fixed-impulses"], False)])
def test_wvr_slam_fixed_impulses_turns_both_adaptations_off(monkeypatch, tmp_path, flag, adapting):
    """`wvr slam --fixed-impulses` reaches the filter's configuration (both adaptations off);
    without it both are on."""
    import runtime.slam.run as run
    from wvr.cli import main

    def capture(*args, cfg, **kwargs):
        raise _Captured(cfg)

    monkeypatch.setattr(run, "run_slam", capture)
    with pytest.raises(_Captured) as got:
        main(["slam", str(tmp_path / "seq"), "--out", str(tmp_path / "out")] + flag)
    cfg = got.value.args[0]
    imp = cfg.impulses
    assert imp.adapt_sigma_a is adapting and imp.adapt_sigma_alpha is adapting and imp.adapt_onset is adapting
