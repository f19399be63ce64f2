"""EKF cost against map size, on one core: frames per second of predict + 10 sequential
updates (the visible features, most uncertain first, each preceded by recomputing that
feature's innovation covariance at the current mean, as the image search needs it) + one
covariance positive-semi-definiteness check per frame, with N mapped features; image decoding and
search excluded (simulated measurements). Then a profile of where the time goes at N = 100.
Targets (issue 7): >= 300 frames/s with 6 to 10 visible and up to 30 mapped features, >= 100
with 100 mapped.

The frame mirrors MonoSLAM.process: predict; order the visible features by the size of their
search ellipses (``innovation_covariances`` over all of them); then one
:class:`runtime.slam.filter.SequentialUpdate` for the frame: ``innovation(k)`` (the ellipse,
shrunk by the updates before it) -> search (here: the simulated match) -> ``update(k, z)``;
``commit()``; and the full covariance check once per frame.

The measurements are the true features seen from a true camera that sways and turns gently
(a few cm, a few degrees, at about 0.3 Hz), plus 1 px noise, all computed before the clock
starts, so the filter tracks a consistent scene at 30 frames/s for the whole run.

Run ``OMP_NUM_THREADS=1 python benchmarks/bench_slam_speed.py`` (add ``--old`` to time the
previous path, ``innovation_covariances`` + ``update_one`` per feature, for comparison)."""

import cProfile
import io
import pstats
import sys
import time
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.camera import default_camera, project
from runtime.slam.filter import SequentialUpdate, innovation_covariances, update_one
from runtime.slam.motion import predict
from runtime.slam.state import DEFAULT_CONFIG, State, check_covariance

# As MonoSLAM.process does: positive-definiteness checked once per frame, not per update.
STEP_CFG = replace(DEFAULT_CONFIG, check_psd=False)
R_PIX = DEFAULT_CONFIG.R_pix        # px^2
DT = 1.0 / 30.0                     # s
N_MAPPED = (10, 30, 100, 200, 300)
N_VISIBLE = 10
MAX_FRAMES = 4000                   # simulated per map size (the timing stops after 1 s)


def true_camera(t: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """The true optical centre (F, 3), world, m, and camera -> world rotations at times t (F,) s:
    a slow sway (<= 10 cm) and turn (<= 5 degrees) about the start pose, which looks along +z."""
    w = 2 * np.pi * 0.3             # rad/s
    r_world = np.column_stack([0.1 * np.sin(w * t), 0.05 * np.sin(1.3 * w * t), 0.05 * np.sin(0.7 * w * t)])
    rotvec = np.column_stack([0.05 * np.sin(0.9 * w * t), 0.08 * np.sin(w * t), 0.03 * np.sin(1.1 * w * t)])
    return r_world, Rotation.from_rotvec(rotvec)


def simulate(n_features: int, rng) -> tuple[State, np.ndarray]:
    """The filter's start (true pose, map = truth + 1 cm error, 1 cm sigma) and the measurements
    Z (MAX_FRAMES, N_VISIBLE, 2) px of features 0..N_VISIBLE-1 in frames 1, 2, ..."""
    Y_world = np.column_stack([rng.uniform(-0.8, 0.8, n_features), rng.uniform(-0.5, 0.5, n_features),
                               rng.uniform(1.5, 4, n_features)])
    t = DT * np.arange(MAX_FRAMES + 1)
    r_world, R_wc = true_camera(t)
    visible = min(N_VISIBLE, n_features)
    Z = np.empty((MAX_FRAMES, visible, 2))
    for f in range(MAX_FRAMES):
        P_cam = (Y_world[:visible] - r_world[f + 1]) @ R_wc[f + 1].as_matrix()   # rows R^T (y - r)
        Z[f] = project(default_camera(), P_cam) + rng.normal(0, DEFAULT_CONFIG.sigma_pixel, (visible, 2))
    x, y, z, w = R_wc[0].as_quat()
    x_v = np.r_[r_world[0], w, x, y, z, np.zeros(6)]
    st = State.from_camera(x_v, np.eye(13) * 1e-4)
    for y_true in Y_world:
        st.add_feature(y_true + rng.normal(0, 0.01, 3), np.eye(3) * 1e-4, np.zeros((3, st.n)))
    return st, Z


class Stages:
    """Accumulates the time of each stage of a frame (s), for the breakdown; ``lap(name)``
    charges the time since the previous lap to ``name``."""

    def __init__(self):
        self.seconds: dict[str, list[float]] = {}
        self._t = time.perf_counter()

    def start(self) -> None:
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        t = time.perf_counter()
        self.seconds.setdefault(name, [0.0])[-1] += t - self._t
        self._t = t

    def next_frame(self) -> None:
        for v in self.seconds.values():
            v.append(0.0)


def frame(st: State, cam, visible: np.ndarray, z: np.ndarray, stages: Stages | None = None) -> None:
    """One frame of the filter; z (len(visible), 2) px are the matches the search would find."""
    lap = stages.lap if stages else (lambda name: None)
    predict(st, DT, STEP_CFG)
    lap("predict")
    _, S, valid = innovation_covariances(st, visible, cam, R_PIX)
    order = visible[valid][np.argsort(-np.linalg.det(S[valid]), kind="stable")]
    lap("order by ellipse size")
    su = SequentialUpdate(st, cam, R_PIX, STEP_CFG)
    for k in order:
        uv_k, S_k, ok = su.innovation(k)           # the search ellipse, after the updates so far
        lap("10 x innovation")
        if ok:                                      # (the search would run here)
            su.update(k, z[k])
        lap("10 x update")
    su.commit()
    lap("commit (form P, check)")
    st.P = check_covariance(st.P, "frame", DEFAULT_CONFIG)
    lap("PSD check (Cholesky)")


def frame_old(st: State, cam, visible: np.ndarray, z: np.ndarray) -> None:
    """The same frame through the one-at-a-time functions (dense Joseph update per feature)."""
    predict(st, DT, STEP_CFG)
    _, S, valid = innovation_covariances(st, visible, cam, R_PIX)
    for k in visible[valid][np.argsort(-np.linalg.det(S[valid]), kind="stable")]:
        _, _, ok = innovation_covariances(st, [k], cam, R_PIX)
        if ok[0]:
            update_one(st, int(k), z[k], cam, R_PIX, STEP_CFG)
    st.P = check_covariance(st.P, "frame", DEFAULT_CONFIG)


def frames_per_second(step, n: int, cam, rng, seconds: float = 1.0) -> tuple[float, float]:
    """Frames per second over about ``seconds`` of frames: (from the median frame time, from the
    mean). The median is the robust figure on a shared machine, where other processes steal
    occasional milliseconds."""
    st, Z = simulate(n, rng)
    visible = np.arange(Z.shape[1])
    for f in range(3):                  # warm up (compiled kernels, caches)
        step(st, cam, visible, Z[f])
    times = []
    f, t_end = 3, time.perf_counter() + seconds
    while time.perf_counter() < t_end and f < MAX_FRAMES:
        t0 = time.perf_counter()
        step(st, cam, visible, Z[f])
        times.append(time.perf_counter() - t0)
        f += 1
    return 1.0 / float(np.median(times)), 1.0 / float(np.mean(times))


def main():
    step = frame_old if "--old" in sys.argv else frame
    cam = default_camera()
    rng = np.random.default_rng(0)
    print(f"path: {'innovation_covariances + update_one' if step is frame_old else 'SequentialUpdate'}")
    print(f"predict + {N_VISIBLE} updates + PSD check per frame, one core")
    print("mapped features   frames/s (median frame)   ms/frame   frames/s (mean)")
    for n in N_MAPPED:
        fps, fps_mean = frames_per_second(step, n, cam, rng)
        print(f"{n:15d}   {fps:22.0f}   {1e3 / fps:8.2f}   {fps_mean:15.0f}")
    st, Z = simulate(100, rng)
    visible = np.arange(N_VISIBLE)
    for f in range(3):
        step(st, cam, visible, Z[f])
    if step is frame:
        stages = Stages()
        for f in range(3, 403):
            stages.start()
            frame(st, cam, visible, Z[f], stages)
            stages.next_frame()
        print("\nwhere the time goes at 100 mapped features (median over 400 frames):")
        for name, v in stages.seconds.items():
            print(f"  {name:24s} {1e6 * np.median(v[:-1]):7.0f} us")
        st, Z = simulate(100, rng)
        for f in range(3):
            step(st, cam, visible, Z[f])
    pr = cProfile.Profile()
    pr.enable()
    for f in range(3, 203):
        step(st, cam, visible, Z[f])
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(14)
    print("\nprofile at 100 mapped features (200 frames), top by own time (LAPACK, ufuncs and the")
    print("compiled kernels' insides count towards their Python caller):")
    print("\n".join(line for line in s.getvalue().splitlines() if line.strip()))


if __name__ == "__main__":
    main()
