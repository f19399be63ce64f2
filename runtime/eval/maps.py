"""Map metrics: the map's points against the true surfaces of a sequence with depth images."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MapErrors:
    """Map points against the true surfaces (a sequence with depth images).

    ids : (n,) feature ids evaluated; errors_m : (n,) distance from each point to the surface
    point seen through its projection in its first frame (ground-truth pose and depth), m.
    """

    ids: np.ndarray
    errors_m: np.ndarray
    #: Why each depth image that could not be read was skipped (its features left out).
    skipped: tuple[str, ...] = ()

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.errors_m**2))) if len(self.errors_m) else float("nan")

    @property
    def median_m(self) -> float:
        return float(np.median(self.errors_m)) if len(self.errors_m) else float("nan")


def map_errors(seq, map_csv) -> MapErrors:
    """Each mapped feature of ``map_csv`` (run.py's map.csv) against the sequence's true depth:
    the feature is projected with the ground-truth pose of its first frame, the depth image
    there gives the true surface point on that pixel's ray, and the error is the distance
    between the two. Features whose pixel falls outside the image or has no depth are left out,
    and so are those of a frame whose depth image is unreadable (not a 16-bit PNG): skipped,
    with the reason, in :attr:`MapErrors.skipped`.
    ``seq`` : an opened sequence (runtime.sequence.open_sequence) with groundtruth.txt and depth.txt."""
    import csv

    from kinematics.camera import project, unproject

    if seq.groundtruth is None or seq.depth_paths is None:
        raise ValueError(f"{seq.root}: map errors need groundtruth.txt and depth.txt (record with --depth)")
    T = seq.groundtruth.T_world_cam()
    from runtime.sequence import SequenceError

    ids, errs, cache, skipped = [], [], {}, []
    with open(map_csv, newline="") as fh:
        for row in csv.DictReader(fh):
            i = int(row["first_frame"])
            y = np.array([float(row["x"]), float(row["y"]), float(row["z"])])
            j = int(np.argmin(np.abs(seq.groundtruth.t - seq.timestamps[i])))
            R, r = T[j][:3, :3], T[j][:3, 3]
            uv = project(seq.camera, ((y - r) @ R)[None])[0]
            if not np.all(np.isfinite(uv)):
                continue
            u, v = int(round(uv[0])), int(round(uv[1]))
            if not (0 <= u < seq.camera.width and 0 <= v < seq.camera.height):
                continue
            if i not in cache:
                try:
                    cache[i] = seq.depth(i)
                except SequenceError as e:         # one bad image costs its frame's features, not the figure
                    cache[i] = None
                    skipped.append(str(e))
            d = None if cache[i] is None else cache[i][v, u]
            if d is None or not np.isfinite(d):
                continue
            ray = unproject(seq.camera, uv[None])[0]           # z = 1 in the optical frame
            X = r + R @ (d * ray / ray[2])
            ids.append(int(row["id"]))
            errs.append(float(np.linalg.norm(y - X)))
    return MapErrors(np.array(ids, dtype=int), np.array(errs), tuple(skipped))
