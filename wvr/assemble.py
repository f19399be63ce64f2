"""The composition root: builds a twin or a hardware rig from files or objects, and the inputs
a run on them needs (the wearer's body for a scenario, a person's clicks on the first image).
The CLI, the demo, the tests and the benchmarks build robots here; nothing in the packages
imports this module.

Every closed loop drives its robot through the same safety chain (``runtime.safety.SafeRobot``:
joint range and rate, the controlled-motion limit, the watchdog, the latched stop): the twin
through :func:`safe_twin` (``wvr sim run``, the station on the twin), the rig through
:func:`make_rig` (``wvr run --rig``, the station on the rig).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kinematics import HeadGeometry, load_head, reference_head
from kinematics.camera import CameraIntrinsics, default_camera, load_camera

#: How far off (px) the simulated person clicks the target's corners in the first image.
CLICK_ERROR_PX = 2.5


#: turn-away: the wearer turns this far from the bench (its map then out of the head's reach).
TURN_AWAY_DEG = 120.0
#: stand-then-sit-down: the wearer stands still this long (time for a head-motion start) first.
STAND_FIRST_S = 8.0


def wearer_for(scenario, seconds: float):
    """The twin's wearer for a scenario: the placement body posed by the named placement motion,
    placed in the world where the scenario says (the twin never imports placement itself)."""
    from placement import motions
    from placement.body import SEGMENTS, make_body
    from runtime.twin.wearer import Wearer

    body = make_body()
    if scenario.motion == "stand":
        m = motions.stand(body, seconds)
    elif scenario.motion == "walk":
        m = motions.walk(body, seconds, speed_m_s=scenario.walk_speed_m_s, cycle_s=1.2)
    elif scenario.motion == "sit-down":
        m = motions.sit_down(body, seconds)
    elif scenario.motion == "stand-then-sit-down":
        m = motions.stand_then(body, motions.sit_down, STAND_FIRST_S, seconds)
    elif scenario.motion == "turn-round":
        m = motions.turn_round(body, seconds)
    elif scenario.motion == "turn-away":
        m = motions.turn_round(body, seconds, turns=1, angle_deg=TURN_AWAY_DEG, first_s=4.0)
    else:
        raise ValueError(f"scenario motion {scenario.motion!r} is not one of stand, walk, sit-down, "
                         "stand-then-sit-down, turn-round, turn-away")
    G = scenario.T_world_body() @ body.segment_transforms(m)
    return Wearer(SEGMENTS, body.vertices, body.faces, body.face_segment, body.joints, m.t, G)


def _head(head) -> HeadGeometry:
    if head is None:
        return reference_head()
    return head if isinstance(head, HeadGeometry) else load_head(head)


def _camera(camera) -> CameraIntrinsics:
    if camera is None:
        return default_camera()
    return camera if isinstance(camera, CameraIntrinsics) else load_camera(camera)


def make_twin(head=None, mount=None, camera=None, ideal_imu: bool = False, ideal_camera: bool = False, **twin_options):
    """A Twin with a head (a HeadGeometry, a head.toml path, or None for the reference head), a
    mount (a Mount, a mount.toml path, or None for the default shoulder mount) and a camera
    (CameraIntrinsics, a camera.toml path, or None for the default); a real IMU's errors
    (BMI088) and a real camera's blur, exposure and noise unless ``ideal_imu`` /
    ``ideal_camera``."""
    if ideal_imu:
        twin_options["imu"] = None
    if ideal_camera:
        twin_options["camera_sensor"] = None
    from runtime.twin.mount import Mount, default_shoulder_mount, load_mount
    from runtime.twin.twin import Twin

    if mount is None:
        m = default_shoulder_mount
    elif isinstance(mount, Mount) or callable(mount):
        m = mount
    else:
        m = load_mount(mount)
    return Twin(_head(head), _camera(camera), m, wearer_for, **twin_options)


def safe_twin(twin, motion_limit_rad_s: float | None = None):
    """The twin behind the safety chain the rig has (runtime.safety.SafeRobot), its latch in
    memory; ``motion_limit_rad_s`` the run's controlled-motion limit (None: the default). The
    twin itself stays the truth source and the thing to configure."""
    from runtime.safety import SafeRobot, SafetySettings

    settings = SafetySettings() if motion_limit_rad_s is None else SafetySettings(motion_limit_rad_s=motion_limit_rad_s)
    return SafeRobot(twin, settings, reset_hint="reset the station's stop (or start a new run) once it is safe")


def clicked_target(twin, error_px: float = CLICK_ERROR_PX, seed: int = 0):
    """A simulated person's clicks on the twin's current (first) image: the Target the closed
    loop starts from. Reads the twin's truth: the composition root's job, not the runtime's."""
    from runtime.twin.operator import clicked_target as click

    return click(twin, error_px, np.random.default_rng(seed))


def run_on_twin(twin, scenario, task, out, seconds: float | None = None, seed: int = 0, settings=None,
                progress: bool = True, on_period=None, start_target=None, click_error_px: float = CLICK_ERROR_PX,
                session_log: bool = True) -> dict:
    """The closed loop on the twin for a scenario: the twin, behind the safety chain
    (:func:`safe_twin`), as the Robot and the twin as the TruthSource for scoring, started from a simulated person's clicks on its first image, ``click_error_px``
    off (or from ``start_target``). Writes the files of ``wvr sim run`` into ``out`` (session.mcap
    too unless ``session_log`` is False); returns the summary."""
    from runtime.apps.closed_loop import run_closed_loop
    from runtime.gaze import ControllerSettings
    from runtime.twin.scenarios import get_scenario

    sc = get_scenario(scenario)
    twin.configure(sc, seed=seed, seconds=seconds)
    secs = sc.seconds if seconds is None else float(seconds)
    if not (np.isfinite(click_error_px) and click_error_px >= 0):
        raise ValueError(f"click error {click_error_px!r} px must be a distance >= 0 (pixels)")
    start = start_target if start_target is not None else \
        (lambda obs: clicked_target(twin, error_px=click_error_px, seed=seed))
    settings = settings or ControllerSettings()
    s = run_closed_loop(safe_twin(twin, settings.motion_limit_rad_s), task, out, start_target=start, seconds=secs,
                        settings=settings, progress=progress, truth=twin, label=sc.name,
                        task_info={"scenario": sc.name, "seed": seed}, on_period=on_period, session_log=session_log,
                        wearer=twin.tell)
    from kinematics import save_head

    save_head(twin.head, Path(out) / "head.toml")
    return s


def make_rig(rig):
    """The hardware rig from a rig.toml path (or a loaded RigConfig) behind the safety chain
    (runtime.safety.SafeRobot with rig.toml's [safety] and its latch file): opens the servo
    board, the camera and the IMU; a missing or busy port is a one-line error. The rig itself is
    ``.robot``; the chain's counts ``.report()``."""
    from runtime.drivers.rig import HardwareRig, RigConfig, load_rig
    from runtime.safety import EStop, SafeRobot

    cfg = rig if isinstance(rig, RigConfig) else load_rig(rig)
    return SafeRobot(HardwareRig(cfg), cfg.safety, EStop(cfg.estop_file),
                     reset_hint=f"clear it with wvr head --rig {cfg.path} reset once it is safe")
