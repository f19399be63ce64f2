"""Recording a scenario into a sequence folder in the shared format (TUM layout + TOML files)."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from kinematics import ServoFilter
from kinematics.camera import project

from ..sequence import SequenceWriter, Target
from .twin import Observation, Twin

#: Scripted head motions respect the paper's controlled-motion limit, as a controller would.
SCRIPT_SPEED_RAD_S = np.radians(30.0)


def target_in_first_frame(twin: Twin) -> Target:
    """The target's four corners (world) and where the camera model projects them now."""
    T = twin.ground_truth.T_world_cam
    xyz = twin.scenario.target_corners()
    P_cam = (xyz - T[:3, 3]) @ T[:3, :3]
    uv = project(twin.camera, P_cam)
    cam = twin.camera
    inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) \
        & (uv[:, 1] <= cam.height - 1)
    if not inside.all():
        raise ValueError(f"the target is not in view at the start of {twin.scenario.name}: corners "
                         f"{np.flatnonzero(~inside).tolist()} fall outside the image; check the head, mount and camera")
    return Target(xyz=xyz, uv=uv)


def scripted_frames(twin: Twin, first: Observation) -> Iterator[Observation]:
    """The observations of a reset twin driven by its scenario's scripted head, from ``first``
    (reset's) to the last frame of the prepared duration. The script moves within the paper's
    controlled-motion limit; "still" holds the joints."""
    n_frames = int(round(twin.seconds * twin.frame_rate))
    script = ServoFilter(twin.head, twin.filter.q, speed_limit=SCRIPT_SPEED_RAD_S)
    dt = 1.0 / twin.frame_rate
    obs = first
    for i in range(n_frames):
        yield obs
        if i == n_frames - 1:
            return
        desired = script.q if twin.scenario.gaze == "still" else twin.scripted_command(obs.t + dt, script.q)
        obs = twin.step(script.step(desired, dt))


def record(twin: Twin, scenario, out: str | Path, seconds: float | None = None, seed: int = 0,
           progress: bool = True, depth: bool = False) -> Path:
    """Run a scenario (a name or a Scenario) with its scripted head and write the sequence to
    ``out``; with ``depth``, also the true depth of every frame (depth.txt, depth/<t>.png)."""
    out = Path(out)
    obs = twin.reset(scenario, seed=seed, seconds=seconds)
    n_frames = int(round(twin.seconds * twin.frame_rate))
    with SequenceWriter(out, twin.camera, target=target_in_first_frame(twin)) as w:
        for obs in tqdm(scripted_frames(twin, obs), total=n_frames, desc=f"record {twin.scenario.name}", unit="frame",
                        disable=not progress):
            gt = twin.ground_truth
            w.add_frame(obs.t, obs.image)
            if depth:
                w.add_depth(obs.t, twin.render_depth())
            w.add_groundtruth(obs.t, gt.T_world_cam)
            w.add_joints(obs.t, obs.encoders)
            for row in obs.imu:
                w.add_imu(row[0], row[1:4], row[4:7])
    return out
