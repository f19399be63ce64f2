"""EKF cost against map size, on one core: frames per second of predict + 10 sequential
updates (the visible features, most uncertain first) with N mapped features, image search
excluded (simulated measurements), and a profile of where the time goes at N = 100.
Targets (issue 7): >= 300 frames/s with up to 30 mapped features, >= 100 with 100."""

import cProfile
import io
import pstats
import time

import numpy as np

from kinematics.camera import default_camera
from runtime.slam.filter import innovation_covariances, update_one
from runtime.slam.motion import predict
from dataclasses import replace

from runtime.slam.state import DEFAULT_CONFIG, State, check_covariance

# As MonoSLAM.process does: positive-definiteness checked once per frame, not per update.
STEP_CFG = replace(DEFAULT_CONFIG, check_psd=False)


def make_state(n_features: int, rng) -> tuple[State, np.ndarray]:
    x_v = np.r_[0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0.0]
    st = State.from_camera(x_v, np.eye(13) * 1e-4)
    Y = np.column_stack([rng.uniform(-1, 1, n_features), rng.uniform(-0.7, 0.7, n_features), rng.uniform(1.5, 4, n_features)])
    for y in Y:
        st.add_feature(y, np.eye(3) * 1e-4, np.zeros((3, st.n)))
    return st, Y


def frame(st: State, cam, visible: np.ndarray, rng) -> None:
    predict(st, 1 / 30, STEP_CFG)
    uv, S, valid = innovation_covariances(st, visible, cam, DEFAULT_CONFIG.R_pix)
    for k in visible[valid][np.argsort(-np.linalg.det(S[valid]))]:
        uvk, _, ok = innovation_covariances(st, [k], cam, DEFAULT_CONFIG.R_pix)
        if ok[0]:
            update_one(st, int(k), uvk[0] + rng.normal(0, 1, 2), cam, DEFAULT_CONFIG.R_pix, STEP_CFG)
    st.P = check_covariance(st.P, "frame", DEFAULT_CONFIG)


def main():
    cam = default_camera()
    rng = np.random.default_rng(0)
    print("mapped features   frames/s (predict + 10 updates)")
    for n in (10, 30, 100, 200, 300):
        st, _ = make_state(n, rng)
        visible = np.arange(min(10, n))
        for _ in range(3):
            frame(st, cam, visible, rng)
        k, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < 1.0:
            frame(st, cam, visible, rng)
            k += 1
        print(f"{n:15d}   {k / (time.perf_counter() - t0):8.0f}")
    st, _ = make_state(100, rng)
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(30):
        frame(st, cam, np.arange(10), rng)
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(8)
    print("\nprofile at 100 mapped features (30 frames), top by own time:")
    print("\n".join(line for line in s.getvalue().splitlines() if line.strip())[:3000])


if __name__ == "__main__":
    main()
