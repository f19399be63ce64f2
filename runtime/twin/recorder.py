"""Recording a scenario into a sequence folder in the shared format (TUM layout + TOML files).

What a recording holds, beside the sequence itself (rgb/, rgb.txt, imu.txt, joints.txt,
camera.toml, target.toml with the operator's clicked pixels, none when a corner is hidden at
the start):

- ``head.toml``: the head it was made with (kinematics.geometry's writer);
- ``twin.toml``: how it was made (scenario, run seed, scene seed, sensor models, click error);
- truth for scoring, which nothing on the runtime path reads: ``groundtruth.txt`` (camera
  poses), ``target_truth.toml`` (the target's exact pixels), ``imu_truth.toml`` and
  ``imu_bias.txt`` (the IMU's drawn errors and its biases at every sample), ``exposure_truth.txt``
  (the camera's gain and blur streak per frame), and with ``depth`` the true depth images.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Iterator

import numpy as np
import tomli_w
from kinematics.progress import progress_bar

from kinematics import ServoFilter
from kinematics.geometry import save_head

from ..sequence import SequenceWriter, save_target
from .operator import CLICK_ERROR_PX, TargetHidden, clicked_target, target_in_first_frame
from .twin import Observation, Twin

__all__ = ["SCRIPT_SPEED_RAD_S", "record", "scripted_frames", "target_in_first_frame"]

#: Scripted head motions respect the paper's controlled-motion limit, as a controller would.
SCRIPT_SPEED_RAD_S = np.radians(30.0)


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
           progress: bool = True, depth: bool = False, scene_seed: int | None = None,
           click_error_px: float = CLICK_ERROR_PX) -> Path:
    """Run a scenario (a name or a Scenario) with its scripted head and write the sequence to
    ``out``; with ``depth``, also the true depth of every frame (depth.txt, depth/<t>.png).

    ``seed`` : the run (motion variation, sensor noise, the operator's clicks). ``scene_seed`` :
    the place (default: ``seed``). ``click_error_px`` : how far off the operator clicks the
    target's corners in target.toml (0: the exact projection)."""
    out = Path(out)
    obs = twin.reset(scenario, seed=seed, seconds=seconds, scene_seed=scene_seed)
    n_frames = int(round(twin.seconds * twin.frame_rate))
    exact = target_in_first_frame(twin)
    try:
        clicked = clicked_target(twin, click_error_px)
    except TargetHidden as e:
        # Recorded all the same (for a saved map's re-location, the 2D trackers), without clicks.
        clicked = None
        print(f"wvr sim record: no target.toml: {e}", file=sys.stderr)
    times = []
    with SequenceWriter(out, twin.camera, target=clicked) as w:
        save_head(twin.head, out / "head.toml")
        save_target(exact, out / "target_truth.toml")
        (out / "twin.toml").write_text(tomli_w.dumps(_recording_table(twin, click_error_px)))
        for obs in progress_bar(scripted_frames(twin, obs), total=n_frames, desc=f"record {twin.scenario.name}", unit="frame",
                        disable=not progress):
            gt = twin.ground_truth
            times.append(obs.t)
            w.add_frame(obs.t, obs.image)
            if depth:
                w.add_depth(obs.t, twin.render_depth())
            w.add_groundtruth(obs.t, gt.T_world_cam)
            w.add_joints(obs.t, obs.encoders)
            for row in obs.imu:
                w.add_imu(row[0], row[1:4], row[4:7])
    _write_sensor_truth(twin, out, np.array(times))
    return out


def _recording_table(twin: Twin, click_error_px: float) -> dict:
    sc = twin.scenario
    d = {"scenario": {"name": sc.name, "place": type(sc.scene).__name__, "seconds": twin.seconds,
                      "body_xy_m": [float(v) for v in sc.body_xy], "sweep_scale": [float(v) for v in sc.sweep_scale],
                      "sweep_phase_rad": float(sc.sweep_phase)},
         "seeds": {"run": int(twin.seed), "scene": int(twin.scene_seed),
                   "note": "recordings with one scene seed and one place show the same place"},
         "operator": {"click_error_px": float(click_error_px), "truth": "target_truth.toml"},
         "imu": {"model": "ideal (white noise only)" if twin.imu_errors is None else twin.imu_errors.spec.name},
         "camera": {"model": "ideal (clean renders)" if twin.camera_sensor is None else "CameraSensor"}}
    if twin.camera_sensor is not None:
        s = twin.camera_sensor
        d["camera"].update({"exposure_s": s.exposure_s, "e_per_dn": s.e_per_dn, "read_noise_e": s.read_noise_e,
                            "target_mean_dn": s.target_mean_dn, "ae_time_constant_s": s.ae_time_constant_s,
                            "gain_range": list(s.gain_range)})
    return d


def _write_sensor_truth(twin: Twin, out: Path, frame_times: np.ndarray) -> None:
    """imu_truth.toml, imu_bias.txt and exposure_truth.txt, for the sensor models in use."""
    e = twin.imu_errors
    if e is not None:
        (out / "imu_truth.toml").write_text(tomli_w.dumps(e.truth()))
        lines = ["# timestamp bgx bgy bgz bax bay baz  (IMU biases at each imu.txt sample: rad/s, m/s^2, camera frame)"]
        lines += [f"{t:.9f} " + " ".join(f"{v:.9e}" for v in np.r_[bg, ba]) for t, bg, ba in e.bias_log]
        (out / "imu_bias.txt").write_text("\n".join(lines) + "\n")
    if twin.exposure is not None:
        lines = ["# timestamp gain blur_px  (the camera's analog gain and longest motion-blur streak per frame)"]
        lines += [f"{t:.9f} {g:.6f} {b:.3f}" for t, (g, b) in zip(frame_times, twin.exposure.log)]
        (out / "exposure_truth.txt").write_text("\n".join(lines) + "\n")
