"""The twin in closed loop, a :class:`runtime.robot.Robot`: ``configure(scenario, seed)`` (or
``reset(scenario, seed)``), then ``step(JointCommand)`` per frame.

What a controller gets (:class:`runtime.robot.Observation`): the image (blurred, exposed and
noisy as a real camera's, :mod:`.image_realism`), the IMU samples since the last frame (gyro and
accelerometer in the camera's optical frame, with a real part's errors, :mod:`.imu_errors`), the
encoder angles and the time. Ground truth (:class:`runtime.robot.Truth`, through the
:class:`runtime.robot.TruthSource` methods ``truth()`` and ``landmarks()``) is kept apart for
evaluation and recording; no controller is handed it.

Physics: MuJoCo at 1 kHz. The wearer is kinematic (mocap bodies following the wearer's track);
the head's three hinges are simulated, driven by position servos with the HS-50's force limit
and reflected rotor inertia. Every command passes the kinematics servo filter (range, 10 rad/s)
first and is ramped over the frame period as the servo's controller does.

The IMU is derived from the simulated camera trajectory by central differences at the physics
rate (angular rate from consecutive orientations, specific force from the second difference of
position minus gravity): MuJoCo's own IMU sensors cannot see a mocap parent's motion, and the
wearer's motion is what the IMU must sense. The run's IMU errors are applied to that truth.

A run has two seeds: the run's (``seed``: motion variation, sensor noise and errors, the
operator's clicks; independent streams, see ``*_STREAM``) and the scene's (``scene_seed``:
the place's textures and layout, by default the run's).
"""

from __future__ import annotations

import math
import os
from typing import Callable

import cv2
import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import HeadGeometry, JOINT_NAMES, ServoFilter, gaze_at_point
from kinematics.camera import CameraIntrinsics
from kinematics.mjcf import R_OPT_MJCAM

from ..robot import JOINTS_MEASURED, ImuSamples, JointCommand, Observation, RobotInfo, Truth
from .image_realism import CAMERA_SENSOR, CameraSensor, Exposure
from .imu_errors import BMI088, ImuErrors, ImuSpec
from .mount import Mount
from .render import ImageFormation, image_formation
from .scenarios import Scenario, get_scenario
from .scene import CARD_BODY, HEAD_PREFIX, OCCLUDER_BODY, TIMESTEP, WEARER_PREFIX, build_scene
from .wearer import Wearer

GRAVITY = np.array([0.0, 0.0, -9.81])
#: Independent random streams drawn from a run's seed, one per use, so that adding one leaves
#: the others (and the white sensor noise of ``default_rng(seed)``) as they were.
MOTION_STREAM, IMU_STREAM, CAMERA_STREAM, CLICK_STREAM = 1, 2, 3, 4


def _egl_display_ready() -> None:
    """Re-initialise MuJoCo's EGL display before making a renderer.

    MuJoCo opens one EGL display per process when first asked; another EGL user in the same
    process (VTK, for pyvista's pictures) may terminate that display when it closes its window,
    after which MuJoCo's next context fails with EGL_NOT_INITIALIZED. eglInitialize on a live
    display is harmless, so do it every time.
    """
    if os.environ.get("MUJOCO_GL") != "egl":
        return
    from mujoco import egl
    from OpenGL import EGL

    if egl.EGL_DISPLAY is not None:   # None until MuJoCo's first context opens it
        EGL.eglInitialize(egl.EGL_DISPLAY, None, None)


#: The twin's truth record (the Robot seam's :class:`runtime.robot.Truth`).
GroundTruth = Truth


#: A wearer who obeys prompts (Scenario.obeys_prompts) starts a turn this long after being asked,
#: and turns at this rate (a person turning on the spot, unhurried).
REACTION_S = 0.8
TURN_RATE_RAD_S = math.radians(45.0)


def _about_z(pivot_xy: np.ndarray, psi: float) -> np.ndarray:
    """(4, 4) a turn by ``psi`` rad about the vertical through ``pivot_xy`` (2,) m."""
    c, s = math.cos(psi), math.sin(psi)
    W = np.eye(4)
    W[:2, :2] = [[c, -s], [s, c]]
    W[:2, 3] = pivot_xy - W[:2, :2] @ pivot_xy
    return W


class Twin:
    """Wearer + head + a place (workbench, kitchen counter, office desk) in MuJoCo.

    Parameters
    ----------
    head, camera : the head geometry and the camera's intrinsics (any lens model).
    mount : where the head sits on the wearer; or a callable wearer -> Mount (e.g. the default
        shoulder mount).
    wearer_for : callable (scenario, seconds) -> :class:`Wearer` in world coordinates.
    frame_rate, imu_rate : Hz. gyro_noise, accel_noise, encoder_noise : standard deviations.
    imu : the IMU's error model (:mod:`runtime.twin.imu_errors`): a constant bias per run, its
        random walk, white noise at the data sheet's density, scale and cross-axis errors and a
        clock offset; None gives an ideal IMU with white noise ``gyro_noise``, ``accel_noise``.
    camera_sensor : what a real camera adds to the renders (:mod:`runtime.twin.image_realism`):
        motion blur over the exposure, auto-exposure with a lag, shot and read noise on 8 bits;
        None gives the clean renders.
    motion_variation : each run's seed moves the body and varies the gaze sweeps a little
        (:meth:`Scenario.varied`); False runs the scenario exactly as named.
    """

    def __init__(self, head: HeadGeometry, camera: CameraIntrinsics, mount: Mount | Callable[[Wearer], Mount],
                 wearer_for: Callable[[Scenario, float], Wearer], frame_rate: float = 30.0, imu_rate: float = 200.0,
                 gyro_noise: float = 0.002, accel_noise: float = 0.02, encoder_noise: float = 0.0,
                 imu: ImuSpec | None = BMI088, camera_sensor: CameraSensor | None = CAMERA_SENSOR,
                 motion_variation: bool = True):
        self.head = head
        self.camera = camera
        self._mount = mount
        self.wearer_for = wearer_for
        self.frame_rate = frame_rate
        self.steps_per_frame = int(round(1.0 / (frame_rate * TIMESTEP)))
        self.steps_per_imu = int(round(1.0 / (imu_rate * TIMESTEP)))
        self.noise = (gyro_noise, accel_noise, encoder_noise)
        self.imu_spec = imu
        self.imu_errors: ImuErrors | None = None
        self.camera_sensor = camera_sensor
        self.exposure: Exposure | None = None
        self.motion_variation = motion_variation
        self.formation: ImageFormation = image_formation(camera)
        self.model = None
        self.renderer = None
        self._config = None          # (scenario, seed, seconds, scene_seed) for reset() without arguments

    # ------------------------------------------------------------------ the Robot seam
    @property
    def info(self) -> RobotInfo:
        return RobotInfo(head=self.head, camera=self.camera, frame_rate=self.frame_rate,
                         speed_limit=self.head.max_speed, name="twin", clock_waits=True)

    def configure(self, scenario: str | Scenario, seed: int = 0, seconds: float | None = None,
                  scene_seed: int | None = None) -> "Twin":
        """Choose what :meth:`reset` (without arguments, as the Robot protocol calls it) builds."""
        self._config = (get_scenario(scenario), int(seed), seconds, scene_seed)
        return self

    # ------------------------------------------------------------------ set-up
    def reset(self, scenario: str | Scenario | None = None, seed: int | None = None, seconds: float | None = None,
              q0=None, scene_seed: int | None = None) -> Observation:
        """Build the scene for a scenario and seed; returns the first observation (t = 0).
        Without a scenario, the one :meth:`configure` chose.

        ``seed`` : the run (motion variation, sensor noise). ``scene_seed`` : the place (textures,
        object layout); default the run's seed. ``q0`` : initial joint angles (default: the
        scripted gaze's first fixation)."""
        if scenario is None:
            if self._config is None:
                raise ValueError("the twin has no scenario: call configure(scenario, seed) or reset(scenario, seed)")
            scenario, seed0, seconds0, scene_seed0 = self._config
            seed = seed0 if seed is None else seed
            seconds = seconds0 if seconds is None else seconds
            scene_seed = scene_seed0 if scene_seed is None else scene_seed
        seed = 0 if seed is None else seed
        sc = get_scenario(scenario)
        if self.motion_variation:
            sc = sc.varied(np.random.default_rng([seed, MOTION_STREAM]))
        self.scenario = sc
        self.seed = seed
        self.scene_seed = seed if scene_seed is None else int(scene_seed)
        self.seconds = sc.seconds if seconds is None else float(seconds)
        self.rng = np.random.default_rng(seed)
        self.imu_errors = None if self.imu_spec is None else ImuErrors.draw(
            self.imu_spec, 1.0 / (self.steps_per_imu * TIMESTEP), np.random.default_rng([seed, IMU_STREAM]))
        self.exposure = None if self.camera_sensor is None else Exposure(
            self.camera_sensor, self.formation, 1.0 / self.frame_rate, np.random.default_rng([seed, CAMERA_STREAM]))
        self.wearer = self.wearer_for(sc, self.seconds + 1.0)
        self.mount = self._mount(self.wearer) if callable(self._mount) else self._mount
        self.ms = self.wearer.index(self.mount.segment)
        self.T_rest_mount = self.mount.T_rest_mount(self.wearer.joints[self.ms])
        stool = None
        if sc.stool:
            j = self.wearer.joints
            thigh = np.linalg.norm(j[self.wearer.index("shank_l")] - j[self.wearer.index("thigh_l")])
            c, s = math.cos(sc.body_yaw), math.sin(sc.body_yaw)
            back = np.array([-s, c]) * (thigh + 0.05)       # the body's +y (behind it) in the world
            stool = (sc.body_xy[0] + back[0], sc.body_xy[1] + back[1], j[self.wearer.index("shank_l"), 2] - 0.1)
        xml, assets = build_scene(self.head, self.formation.render_camera, self.wearer, self.mount, sc.scene,
                                  self.scene_seed, stool=stool, moving_card=sc.moving_card)
        self._close_renderer()
        self.model = mujoco.MjModel.from_xml_string(xml, assets)
        self.data = mujoco.MjData(self.model)
        rc = self.formation.render_camera
        _egl_display_ready()
        self.renderer = mujoco.Renderer(self.model, rc.height, rc.width)
        self.cam_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, HEAD_PREFIX + "camera")
        self.qadr = np.array([self.model.jnt_qposadr[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, HEAD_PREFIX + n)]
                              for n in JOINT_NAMES])
        self.vadr = np.array([self.model.jnt_dofadr[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, HEAD_PREFIX + n)]
                              for n in JOINT_NAMES])
        self.mocap = np.array([self.model.body_mocapid[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY,
                                                                          WEARER_PREFIX + s)] for s in self.wearer.segments])
        self.light0 = self.model.light_diffuse.copy()
        # The mounted segment's pose at every physics step (vectorised spline evaluation).
        n_steps = int(math.ceil(self.seconds / TIMESTEP)) + self.steps_per_frame + 2
        self.step_times = np.arange(n_steps) * TIMESTEP
        self.G_mount_seg = self.wearer.pose(self.ms, self.step_times)
        self.mount_quat_wxyz = Rotation.from_matrix(self.G_mount_seg[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
        self.k = 0
        self._turns: list[tuple[float, float, float, np.ndarray]] = []   # (t0, duration, psi, pivot): Twin.tell
        self.cam_p = np.zeros((n_steps + 1, 3))
        self.cam_R = np.zeros((n_steps + 1, 3, 3))
        self._imu_pending = []
        if q0 is None:
            q0 = self.scripted_command(0.0, np.zeros(3))
        self.filter = ServoFilter(self.head, q0)
        self.data.qpos[self.qadr] = self.filter.q
        self.data.ctrl[:] = self.filter.q
        self._cmd_prev = self.filter.q.copy()
        self._command = self.filter.q.copy()
        self._objects = []
        if sc.moving_card:
            self._objects = [(self.model.body_mocapid[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)], pose)
                             for name, pose in ((CARD_BODY, sc.T_world_card), (OCCLUDER_BODY, sc.T_world_occluder))]
        self._set_wearer(0.0, all_segments=True)
        mujoco.mj_forward(self.model, self.data)
        self._record_cam(0)
        self._imu_next = 0
        return self._observe()

    def set_light(self, scale: float) -> None:
        """Scale the scene's lights (1 = as built; 0.2 = dim)."""
        self.model.light_diffuse[:] = self.light0 * float(scale)

    # ------------------------------------------------------------------ loop
    @property
    def t(self) -> float:
        return self.k * TIMESTEP

    def step(self, command, profile=None) -> Observation:
        """Send one joint command (a :class:`JointCommand`, or (3,) rad); advance one frame
        period; return the next observation.

        ``profile`` : optional (steps_per_frame, 3) servo inputs, one per physics step, instead
        of the linear ramp to the command (the hardware-in-the-loop Maestro's ramped outputs);
        each passes the servo filter at the physics rate."""
        if self.model is None:
            raise RuntimeError("call reset(scenario, seed) first")
        q_command = command.q if isinstance(command, JointCommand) else command
        dt = self.steps_per_frame * TIMESTEP
        if profile is None:
            cmd = self.filter.step(q_command, dt)   # hard limits: range and servo speed
            start = self._cmd_prev
            ramp = [(1 - i / self.steps_per_frame) * start + i / self.steps_per_frame * cmd
                    for i in range(1, self.steps_per_frame + 1)]
        else:
            profile = np.asarray(profile, float).reshape(self.steps_per_frame, 3)
            ramp = [self.filter.step(p, TIMESTEP) for p in profile]
            cmd = ramp[-1]
        self._command = cmd
        self.set_light(self.scenario.light_at(self.t, self.seconds))
        if self.k + self.steps_per_frame >= len(self.step_times):
            raise RuntimeError(f"the scenario was prepared for {self.seconds:g} s; reset with a longer 'seconds'")
        for i in range(1, self.steps_per_frame + 1):
            self.data.ctrl[:] = ramp[i - 1]
            # The step integrates from the state at k with the wearer where it is at k.
            mujoco.mj_step(self.model, self.data)
            k = self.k + 1
            self._set_wearer(self.step_times[k], all_segments=False, index=k)
            self._record_cam(k)
            # k advances only once step k's camera is recorded: a scorer reading ground_truth
            # from another thread (the station's tests) never sees the unwritten (zero) pose.
            self.k = k
        self._cmd_prev = cmd
        self._set_wearer(self.t, all_segments=True)
        mujoco.mj_forward(self.model, self.data)
        return self._observe()

    def _set_wearer(self, t: float, all_segments: bool, index: int | None = None) -> None:
        if all_segments:
            # Scene objects moved by the scenario (they only need to be where they are when a
            # frame is rendered).
            for mocap_id, pose in self._objects:
                T = pose(t)
                self.data.mocap_pos[mocap_id] = T[:3, 3]
                self.data.mocap_quat[mocap_id] = Rotation.from_matrix(T[:3, :3]).as_quat()[[3, 0, 1, 2]]
            G = self.wearer.poses(t)
            W = self._turned(t)
            if W is not None:
                G = W @ G
            segs = np.arange(len(self.wearer.segments))
            pos = G[:, :3, 3]
            quat = Rotation.from_matrix(G[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
        else:
            segs = np.array([self.ms])
            W = self._turned(self.step_times[index])
            if W is None:
                pos = self.G_mount_seg[index][None, :3, 3]
                quat = self.mount_quat_wxyz[index][None]
            else:
                G = W @ self.G_mount_seg[index]
                pos = G[None, :3, 3]
                quat = Rotation.from_matrix(G[:3, :3]).as_quat()[[3, 0, 1, 2]][None]
        self.data.mocap_pos[self.mocap[segs]] = pos
        self.data.mocap_quat[self.mocap[segs]] = quat

    def _record_cam(self, k: int) -> None:
        # mj_step leaves positions from before its integration; refresh the kinematics so the
        # camera pose belongs to the state at step k.
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self.cam_p[k] = self.data.cam_xpos[self.cam_id]
        self.cam_R[k] = self.data.cam_xmat[self.cam_id].reshape(3, 3) @ R_OPT_MJCAM

    def _imu_samples(self) -> np.ndarray:
        """IMU rows for every sample time k (multiple of steps_per_imu) with k + 1 recorded."""
        if self.imu_errors is not None:
            return self._measured_imu_samples()
        rows = []
        while self._imu_next + 1 <= self.k:
            k = self._imu_next
            w, f = self._true_imu(k)
            g_n, a_n, _ = self.noise
            rows.append([k * TIMESTEP, *(w + self.rng.normal(0, g_n, 3)), *(f + self.rng.normal(0, a_n, 3))])
            self._imu_next += self.steps_per_imu
        return np.array(rows).reshape(-1, 7)

    def _true_imu(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(angular rate (3,) rad/s, specific force (3,) m/s^2) in the optical frame at physics
        step k, by central differences (needs step k + 1 recorded)."""
        if k == 0:
            km, kp = 0, 1                     # one-sided at the very start
        else:
            km, kp = k - 1, k + 1
        h = (kp - km) * TIMESTEP
        w = Rotation.from_matrix(self.cam_R[km].T @ self.cam_R[kp]).as_rotvec() / h
        if k == 0:
            a_world = np.zeros(3)             # at rest at t = 0
        else:
            a_world = (self.cam_p[kp] - 2 * self.cam_p[k] + self.cam_p[km]) / TIMESTEP**2
        return w, self.cam_R[k].T @ (a_world - GRAVITY)

    def _measured_imu_samples(self) -> np.ndarray:
        """IMU rows through the run's error model: each sample stamped k (IMU clock) is the truth
        at camera time k - time_offset (interpolated between physics steps), then biased,
        scaled, misaligned and noisy."""
        e = self.imu_errors
        stamps, w_true, f_true = [], [], []
        while True:
            k = self._imu_next
            j = max(k - e.time_offset_s / TIMESTEP, 0.0)   # the physics step (fractional) it was taken at
            j0 = int(math.floor(j))
            frac = j - j0
            if j0 + (2 if frac > 1e-9 else 1) > self.k:
                break
            w0, f0 = self._true_imu(j0)
            if frac > 1e-9:
                w1, f1 = self._true_imu(j0 + 1)
                w0, f0 = (1 - frac) * w0 + frac * w1, (1 - frac) * f0 + frac * f1
            stamps.append(k * TIMESTEP)
            w_true.append(w0)
            f_true.append(f0)
            self._imu_next += self.steps_per_imu
        if not stamps:
            return np.zeros((0, 7))
        w, f = e.measure(np.array(stamps), np.array(w_true), np.array(f_true))
        return np.column_stack([stamps, w, f])

    def _observe(self) -> Observation:
        self.renderer.update_scene(self.data, camera=self.cam_id)
        rendered = self.renderer.render()
        img = self.formation.form(rendered) if self.exposure is None else \
            self.exposure.image(rendered, self._rotation_over_half_exposure())
        enc = self.data.qpos[self.qadr] + self.rng.normal(0, self.noise[2], 3) if self.noise[2] else self.data.qpos[self.qadr].copy()
        return Observation(t=self.t, image=img, imu=ImuSamples.from_rows(self._imu_samples()), q=np.array(enc),
                           q_source=JOINTS_MEASURED)

    def _rotation_over_half_exposure(self) -> np.ndarray:
        """(3,) rad: the rotation vector of R_world_cam(t)^T R_world_cam(t - T/2) for the
        exposure T, from the recorded camera track (scaled from the nearest whole physics step;
        zero at the start)."""
        half = 0.5 * self.camera_sensor.exposure_s
        k0 = max(self.k - max(1, int(round(half / TIMESTEP))), 0)
        if k0 == self.k:
            return np.zeros(3)
        phi = Rotation.from_matrix(self.cam_R[self.k].T @ self.cam_R[k0]).as_rotvec()
        return phi * (half / ((self.k - k0) * TIMESTEP))

    # ------------------------------------------------------------------ truth (evaluation only)
    def render_depth(self) -> np.ndarray:
        """(H, W) float32 depth of the current view, metres along the optic axis, aligned with
        the camera's image (through the lens model's remap, nearest neighbour so that edges do
        not blend near and far surfaces). Ground truth for evaluating maps; not an input."""
        self.renderer.enable_depth_rendering()
        try:
            self.renderer.update_scene(self.data, camera=self.cam_id)
            z = self.renderer.render().astype(np.float32)
        finally:
            self.renderer.disable_depth_rendering()
        return self.formation.form(z, cv2.INTER_NEAREST)


    def truth(self) -> Truth:
        """The :class:`runtime.robot.TruthSource` view: this moment's truth (scoring only)."""
        return self.ground_truth

    def landmarks(self) -> dict[str, np.ndarray]:
        """Named world points of the scene for scoring: the known rectangle's corners (4, 3)."""
        return {"target_corners": self.scenario.scene.target_corners()}

    @property
    def ground_truth(self) -> GroundTruth:
        T = np.eye(4)
        T[:3, :3] = self.cam_R[self.k]
        T[:3, 3] = self.cam_p[self.k]
        return GroundTruth(t=self.t, T_world_cam=T, q=self.data.qpos[self.qadr].copy(),
                           T_world_mount=self.T_world_mount(self.t), command=self._command.copy())

    def T_world_mount(self, t: float) -> np.ndarray:
        T = self.wearer.pose(self.ms, t) @ self.T_rest_mount
        W = self._turned(t)
        return T if W is None else W @ T

    # ------------------------------------------------------------------ the wearer told
    def tell(self, t: float, prompt) -> bool:
        """A wearer prompt (runtime.gaze.prompts.Prompt) said to the wearer at ``t`` s. In a
        scenario whose wearer obeys (``Scenario.obeys_prompts``) a ``turn`` is made: it starts
        REACTION_S later and turns the whole body about the vertical through the mount at
        TURN_RATE_RAD_S (a smooth start and stop), on top of the scenario's own motion. A prompt
        said while a turn is under way, or of another kind, is not obeyed. Returns whether it is."""
        if not self.scenario.obeys_prompts or getattr(prompt, "kind", None) != "turn" or self.turning(t):
            return False
        psi = float(prompt.turn_rad)
        if not (math.isfinite(psi) and psi != 0.0):
            return False
        pivot = self.T_world_mount(t)[:2, 3].copy()
        self._turns.append((t + REACTION_S, max(abs(psi) / TURN_RATE_RAD_S, 0.5), psi, pivot))
        return True

    def turning(self, t: float) -> bool:
        """Whether an obeyed turn is under way (or about to start) at ``t``."""
        return bool(self._turns) and t < self._turns[-1][0] + self._turns[-1][1]

    def _turned(self, t: float) -> np.ndarray | None:
        """(4, 4) the obeyed turns' transform of the wearer at ``t`` (None: never asked)."""
        if not self._turns:
            return None
        W = np.eye(4)
        for t0, dur, psi, pivot in self._turns:
            s = min(max((t - t0) / dur, 0.0), 1.0)
            W = _about_z(pivot, psi * s * s * (3.0 - 2.0 * s)) @ W      # smoothstep: no jerk at either end
        return W

    def scripted_command(self, t: float, q_current: np.ndarray) -> np.ndarray:
        """The recording's head command: fixate the scenario's look-at point (uses ground truth:
        a scripted camera, not a controller). Holds the current angles if unreachable."""
        T = self.T_world_mount(t)
        wearer_xy = T[:2, 3]
        p_world = self.scenario.look_at(t, wearer_xy)
        p_mount = T[:3, :3].T @ (p_world - T[:3, 3])
        up_mount = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        res = gaze_at_point(self.head, p_mount, up_mount, q_current=q_current)
        return res.q if res.reachable else np.asarray(q_current, float)

    def _close_renderer(self) -> None:
        if self.renderer is None:
            return
        _egl_display_ready()
        try:
            self.renderer.close()
        except Exception as e:  # noqa: BLE001 - only EGL errors are expected here
            from OpenGL.error import Error as GLError

            if not isinstance(e, GLError):
                raise
            # Its context died with a display another library terminated: nothing left to free.
        self.renderer = None

    def close(self) -> None:
        self._close_renderer()
