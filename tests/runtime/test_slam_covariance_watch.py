"""The full covariance check beside the tracker (covariance_watch.CovarianceWatch): a covariance
that is not positive semi-definite is reported (naming the frame it was found at) however the
check is collected; a healthy one never is; the cheap checks still run on the frame itself."""

from __future__ import annotations

import numpy as np
import pytest
from test_slam_core import guarded_state

from runtime.slam.covariance_watch import CovarianceWatch
from runtime.slam.state import SlamNumericalError


def _not_psd(s):
    """``s`` with a feature's variance made inconsistent with its correlation (|corr| > 1)."""
    P = s.P.copy()
    i, j = s.n - 1, 0
    P[i, j] = P[j, i] = 10 * np.sqrt(P[i, i] * P[j, j])
    s.P = P
    return s


def test_a_covariance_that_is_not_psd_is_reported_with_its_frame():
    w = CovarianceWatch()
    s = _not_psd(guarded_state(np.random.default_rng(1)))
    w.submit(s, "frame 40", 1e-9)
    with pytest.raises(SlamNumericalError, match="not positive semi-definite.*frame 40"):
        w.wait()
    # Collected by the per-frame look once it is done.
    w.submit(s, "frame 50", 1e-9)
    with pytest.raises(SlamNumericalError, match="frame 50"):
        for _ in range(10_000):
            w.raise_if_failed()
        w.wait()
    # ... or by the next submission.
    w.submit(s, "frame 60", 1e-9)
    with pytest.raises(SlamNumericalError, match="frame 60"):
        w.submit(guarded_state(np.random.default_rng(2)), "frame 70", 1e-9)


def test_a_healthy_covariance_passes_and_negative_variances_are_caught_at_once():
    w = CovarianceWatch()
    s = guarded_state(np.random.default_rng(3))
    for frame in range(5):
        w.submit(s, f"frame {frame}", 1e-9)
        w.raise_if_failed()
    w.wait()
    s.P[2, 2] = -1.0
    with pytest.raises(SlamNumericalError, match="negative variance"):
        w.submit(s, "frame 9", 1e-9)
