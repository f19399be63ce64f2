"""Placement benchmarks: rays per second per core, and the time of a full default map.

Rays per core are rays divided by the process's CPU time (all threads), so the figure does not
depend on how many threads Embree uses. Target: at least 4 million rays per second per core.
"""

import tempfile
import time


from placement.body import make_body
from placement.mapping import placement_map
from placement.motions import default_poses
from kinematics.rays import RayCaster
from placement.scores import camera_points, fov_fraction


def main():
    body = make_body()
    pose = default_poses(body)["walking"]
    occ = RayCaster(body.posed_vertices(pose), body.faces)
    cams, _ = camera_points(body, pose, 0.02)
    fov_fraction(occ, cams[:50], 2048)  # warm up
    c0, w0 = time.process_time(), time.perf_counter()
    fov_fraction(occ, cams, 2048)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    n = len(cams) * 2048
    print(f"field-of-view rays: {n:,} in {wall:.2f} s wall, {cpu:.2f} s CPU")
    print(f"rays per second per core: {n / cpu / 1e6:.2f} million (target 4; wall-clock rate {n / wall / 1e6:.2f} million)")
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        s = placement_map(d, body, progress=False)
        dt = time.perf_counter() - t0
    print(f"full default map ({s.polygons} places, {s.rays} rays, {len(s.poses)} poses, "
          f"{len(s.motions)} motions, maps and zones): {dt:.1f} s")


if __name__ == "__main__":
    main()
