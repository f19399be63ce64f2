"""Kinematics throughput on one core: batched FK, RNEA, gaze IK, servo filter.

Figures are per second on this machine and as ratios (batched vs one-at-a-time), which carry
over between machines better than absolute rates.
"""

import time

import numpy as np

from kinematics import ServoFilter, forward_kinematics, gaze_at_direction, gaze_at_point, inverse_dynamics, reference_head


def rate(fn, n_items, min_time=0.5):
    reps, t0 = 0, time.perf_counter()
    while True:
        fn()
        reps += 1
        dt = time.perf_counter() - t0
        if dt >= min_time:
            return reps * n_items / dt


def main():
    head = reference_head()
    rng = np.random.default_rng(0)
    q = rng.uniform(head.lower, head.upper, (100_000, 3))
    fk_batch = rate(lambda: forward_kinematics(head, q), len(q))
    fk_single = rate(lambda: forward_kinematics(head, q[0]), 1)
    id_batch = rate(lambda: inverse_dynamics(head, q, q, q), len(q))
    dirs = forward_kinematics(head, q[:200]).optic_axis
    ik_dir = rate(lambda: [gaze_at_direction(head, d) for d in dirs], len(dirs))
    pts = forward_kinematics(head, q[:100]).p_mount_cam + dirs[:100]
    ik_pt = rate(lambda: [gaze_at_point(head, p) for p in pts], len(pts))
    f = ServoFilter(head)
    servo = rate(lambda: [f.step(t, 0.01) for t in q[:1000]], 1000)
    print(f"forward kinematics, batched:      {fk_batch:12,.0f} poses/s")
    print(f"forward kinematics, one at a time:{fk_single:12,.0f} poses/s   (batching gains x{fk_batch / fk_single:,.0f})")
    print(f"inverse dynamics (RNEA), batched: {id_batch:12,.0f} states/s")
    print(f"gaze IK, direction (closed form): {ik_dir:12,.0f} solves/s  ({1e3 / ik_dir:.2f} ms each; a 30 Hz loop needs 30)")
    print(f"gaze IK, point (Newton polish):   {ik_pt:12,.0f} solves/s  ({1e3 / ik_pt:.2f} ms each)")
    print(f"servo filter step:                {servo:12,.0f} steps/s")


if __name__ == "__main__":
    main()
