"""Which features a frame may measure and how much noise their templates carry
(views._views_kernel): inside the image by the margin, seen within the view angle and range
ratio of their first view (the target's own limits for its corners), the noise scaled by the
angle and the range ratio, against values computed by hand."""

from __future__ import annotations

import math

import numpy as np

from runtime.slam.views import _views_kernel

W, H, MARGIN = 320.0, 240.0, 5.0
LIMIT_DEG, LIMIT_KNOWN_DEG, RMAX, RMAX_KNOWN = 45.0, 60.0, 1.5, 3.0
ANGLE_UNIT_DEG, SCALE_UNIT, KNOWN_SCALE = 30.0, 2.0, 0.25


def views(uv, valid, Y, r, r0s, known):
    return _views_kernel(np.asarray(uv, float), np.asarray(valid, bool), np.asarray(Y, float), np.asarray(r, float),
                         np.asarray(r0s, float), np.asarray(known, bool), W, H, MARGIN,
                         math.cos(math.radians(LIMIT_DEG)), math.cos(math.radians(LIMIT_KNOWN_DEG)), RMAX, RMAX_KNOWN,
                         ANGLE_UNIT_DEG, math.log(SCALE_UNIT), KNOWN_SCALE)


def seen_from(deg: float, dist: float = 1.0) -> np.ndarray:
    """A camera centre ``dist`` m from the origin, ``deg`` degrees round from the -z axis."""
    a = math.radians(deg)
    return np.array([dist * math.sin(a), 0.0, -dist * math.cos(a)])


def test_view_angle_range_and_image_rules_and_the_noise_they_give():
    # Each row: a point at the origin, first seen from 1 m along -z, now seen from ``r``.
    cases = [  # (now from, known, uv, valid, expected ok, expected scale)
        (seen_from(0.0), False, (160, 120), True, True, 1.0),
        (seen_from(30.0), False, (160, 120), True, True, 1.0 + (30.0 / ANGLE_UNIT_DEG) ** 2),
        (seen_from(50.0), False, (160, 120), True, False, 1.0 + (50.0 / ANGLE_UNIT_DEG) ** 2),
        (seen_from(50.0), True, (160, 120), True, True, KNOWN_SCALE),
        (seen_from(0.0, 2.0), False, (160, 120), True, False, 1.0 + (math.log(2.0) / math.log(SCALE_UNIT)) ** 2),
        (seen_from(0.0, 2.0), True, (160, 120), True, True, KNOWN_SCALE),
        (seen_from(0.0, 1.4), False, (160, 120), True, True, 1.0 + (math.log(1.4) / math.log(SCALE_UNIT)) ** 2),
        (seen_from(0.0), False, (-0.5 + MARGIN, 120), True, True, 1.0),            # on the margin
        (seen_from(0.0), False, (-0.5 + MARGIN - 0.01, 120), True, False, None),   # just outside it
        (seen_from(0.0), False, (160, H - 0.5 - MARGIN + 0.01), True, False, None),
        (seen_from(0.0), False, (np.nan, np.nan), True, False, None),
        (seen_from(0.0), False, (160, 120), False, False, None),                   # no prediction
    ]
    r_now = np.array([c[0] for c in cases])
    ok, scale = [], []
    for c, r in zip(cases, r_now):               # one camera per call, as the filter has
        o, s = views([c[2]], [c[3]], [[0.0, 0.0, 0.0]], r, [[0.0, 0.0, -1.0]], [c[1]])
        ok.append(bool(o[0]))
        scale.append(float(s[0]))
    assert ok == [c[4] for c in cases]
    for c, s in zip(cases, scale):
        if c[5] is not None:
            assert math.isclose(s, c[5], rel_tol=1e-9), (c, s)
