"""Twin benchmarks: rendered frames per second at 640x480, and the simulation's real-time factor
(simulated seconds per wall-clock second, rendering every frame at 30 Hz and physics at 1 kHz)."""

import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from wvr.cli import make_twin  # noqa: E402


def main():
    twin = make_twin()
    try:
        obs = twin.reset("walk", seed=0, seconds=6.0)
        for _ in range(5):   # warm up the renderer
            twin.renderer.update_scene(twin.data, camera=twin.cam_id)
            twin.renderer.render()
        n = 60
        t0 = time.perf_counter()
        for _ in range(n):
            twin.renderer.update_scene(twin.data, camera=twin.cam_id)
            twin.renderer.render()
        render_fps = n / (time.perf_counter() - t0)
        steps = 120
        t0 = time.perf_counter()
        for _ in range(steps):
            obs = twin.step(twin.scripted_command(obs.t, twin.filter.q))
        wall = time.perf_counter() - t0
        sim = steps * twin.steps_per_frame * 0.001
        print(f"rendered frames per second at {twin.camera.width}x{twin.camera.height}: {render_fps:.1f}")
        print(f"real-time factor (walk, physics 1 kHz, a frame rendered every {1000 * twin.steps_per_frame * 0.001:.0f} ms, "
              f"scripted gaze IK): {sim / wall:.2f}  ({steps / wall:.1f} frames per second end to end)")
    finally:
        twin.close()


if __name__ == "__main__":
    main()
