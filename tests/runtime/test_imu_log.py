"""imu.txt as a sensor writes it: glitched rows dropped and counted, not fatal; a dropout is a gap
the camera-only prediction bridges, never a stale sample held through it."""

import numpy as np

from runtime.sequence import read_imu
from runtime.slam.config import MapSettings
from runtime.slam.inertial import ImuStream


def _rows(t):
    rng = np.random.default_rng(0)
    return np.column_stack([t, rng.normal(0, 0.1, (len(t), 3)), rng.normal(0, 0.1, (len(t), 3)) + [0, 0, 9.81]])


def test_glitched_rows_are_dropped_and_counted(tmp_path):
    t = np.arange(0.0, 1.0, 0.005)
    a = _rows(t)
    lines = [" ".join(f"{v:.9f}" for v in row) for row in a]
    lines[10] = lines[10].replace(lines[10].split()[3], "nan", 1)        # a NaN
    lines.insert(20, lines[19])                                            # a repeated row
    lines.insert(40, lines[30])                                            # an earlier stamp
    (tmp_path / "imu.txt").write_text("# timestamp wx wy wz ax ay az\n" + "\n".join(lines) + "\n")
    log = read_imu(tmp_path / "imu.txt")
    assert log.dropped == {"non_finite": 1, "duplicate": 1, "out_of_order": 1}
    assert len(log) == len(t) - 1 and np.isfinite(log.gyro).all() and (np.diff(log.t) > 0).all()
    np.testing.assert_allclose(log.t, np.delete(t, 10), atol=1e-9)


def test_a_dropout_is_a_gap_not_a_stale_sample():
    t = np.arange(0.0, 3.0, 0.005)
    t = t[(t < 0.745) | (t > 1.75)]                                       # a 1 s dropout
    imu = ImuStream(MapSettings())
    imu.add(_rows(t))
    frames = np.arange(0.0, 3.0, 1 / 30)
    covered = [imu.covering(a, b) is not None for a, b in zip(frames[:-1], frames[1:])]
    inside = (frames[1:] > 0.745 + 0.05) & (frames[:-1] < 1.75)
    assert not any(c for c, i in zip(covered, inside) if i)              # no frame in it uses the IMU
    outside = (frames[1:] < 0.74) | (frames[:-1] > 1.76)
    assert all(c for c, o in zip(covered, outside) if o)                   # every frame outside it does
    assert imu.counts.gaps >= inside.sum()
