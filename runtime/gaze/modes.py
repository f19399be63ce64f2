"""The controller's modes as small objects, each holding its own kind of target.

========== ===================== ================================================================
mode       target                what the head does
========== ===================== ================================================================
Hold       none                  holds still
Fixate     world point (3,) m    keeps the optic axis on it as the wearer moves
Saccade    world point (3,) m    moves there at the controlled-motion limit, then fixates
Stabilise  attitude (3, 3)       Path A: holds R_world_cam from the IMU alone
Body       mount direction (3,)  Path B: holds a gaze direction relative to the body (its angles)
Track      pixel (2,)            turns the optic axis onto an image point (a 2D tracker's)
Slave      joint angles (3,) rad follows angles given from outside (a tracked person's head)
========== ===================== ================================================================

Each mode's ``desired(estimate, head, camera)`` turns its target into the joint angles the
controller should reach this period (through the fixation IK and the image-vertical rule), given
the period's :class:`~.estimate.GazeEstimate` (where the mount is, how it turns, the joints, the
IMU's attitude): a frozen snapshot, the only thing of the controller a mode reads. The
controller owns the estimation, the rate QP and the prompts' rate limit; a mode owns only the
geometry of its target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import HeadGeometry, gaze_at_direction
from kinematics.camera import CameraIntrinsics, unproject

from .estimate import GazeEstimate, ik_point
from .prompts import Prompt, wearer_prompt


@dataclass(frozen=True)
class Desired:
    """One period's goal. q : (3,) the angles to reach, or None to hold. error_rad : the
    estimated error now (angle to the target, or attitude error), NaN if unknown. reachable :
    False when the target is out of reach this period. prompt : a wearer prompt to emit (the
    controller records it, at most every ``prompt_every_s``)."""

    q: np.ndarray | None
    error_rad: float = float("nan")
    reachable: bool = True
    prompt: Prompt | None = None


class Mode(Protocol):
    name: str

    def desired(self, estimate: GazeEstimate, head: HeadGeometry, camera: CameraIntrinsics) -> Desired: ...


def _rotation_exp(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(w).as_matrix()


@dataclass(frozen=True)
class Hold:
    name: str = field(default="hold", init=False)

    def desired(self, est: GazeEstimate, head: HeadGeometry, camera: CameraIntrinsics) -> Desired:
        return Desired(None)


@dataclass(frozen=True)
class Fixate:
    """Hold the optic axis on a world point. p_world : (3,) m."""

    p_world: np.ndarray
    name: str = field(default="fixate", init=False)

    def __post_init__(self):
        p = np.asarray(self.p_world, float)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError(f"gaze target must be a finite world point (x, y, z) m, got {p.tolist()}")
        object.__setattr__(self, "p_world", p)

    def desired(self, est: GazeEstimate, head: HeadGeometry, camera: CameraIntrinsics) -> Desired:
        if est.T_world_mount is None:
            return Desired(None)
        p = self.p_world
        T_now = est.T_world_mount @ est.T_mount_cam
        d = p - T_now[:3, 3]
        err = math.acos(float(np.clip(T_now[:3, 2] @ d / np.linalg.norm(d), -1.0, 1.0)))
        res = ik_point(head, p, est.predicted_mount(), est.q)
        if not res.reachable:
            # The prompt's search (up to 80 IK solves) only when the controller would repeat it.
            prompt = wearer_prompt(head, est.T_world_mount, p, est.q) if est.prompt_due else None
            return Desired(None, err, False, prompt)
        return Desired(res.q, err)


@dataclass(frozen=True)
class Saccade(Fixate):
    """Move the gaze to a world point at the controlled-motion limit, then fixate it."""

    name: str = field(default="saccade", init=False)


@dataclass(frozen=True)
class Stabilise:
    """Path A: hold the camera's attitude R_world_cam (3, 3) from the IMU alone."""

    R_world_cam: np.ndarray
    name: str = field(default="stabilise", init=False)

    def __post_init__(self):
        R = np.asarray(self.R_world_cam, float)
        if R.shape != (3, 3) or not np.isfinite(R).all() or abs(np.linalg.det(R) - 1.0) > 1e-6:
            raise ValueError("stabilise needs a rotation matrix (3, 3) R_world_cam")
        object.__setattr__(self, "R_world_cam", R.copy())

    def desired(self, est: GazeEstimate, head: HeadGeometry, camera: CameraIntrinsics) -> Desired:
        R_now = est.R_world_cam
        if R_now is None:
            return Desired(None)
        R_wm = R_now @ est.R_mount_cam.T
        R_wm_pred = _rotation_exp(est.w_mount * est.lead) @ R_wm
        R_mc_des = R_wm_pred.T @ self.R_world_cam
        err = float(Rotation.from_matrix(self.R_world_cam.T @ R_now).magnitude())
        # Optic axis from the desired z; "up" = the desired image's up (-y), so the vertical
        # rule reproduces the desired roll exactly (z x -y = x).
        res = gaze_at_direction(head, R_mc_des[:, 2], -R_mc_des[:, 1], q_current=est.q)
        return Desired(res.q if res.reachable else None, err, res.reachable)


@dataclass(frozen=True)
class Body:
    """Path B: hold a gaze direction relative to the wearer's body. d_mount : (3,) the direction
    (mount frame); q : (3,) the joint angles that point that way (resolved when the mode is set)."""

    d_mount: np.ndarray
    q: np.ndarray
    name: str = field(default="body", init=False)

    def desired(self, est: GazeEstimate, head: HeadGeometry, camera: CameraIntrinsics) -> Desired:
        return Desired(self.q, float(np.linalg.norm(self.q - est.q)))


@dataclass(frozen=True)
class Track:
    """Keep an image point (u, v) pixels centred, e.g. a 2D tracker's target."""

    uv: np.ndarray
    name: str = field(default="track", init=False)

    def __post_init__(self):
        uv = np.asarray(self.uv, float)
        if uv.shape != (2,) or not np.isfinite(uv).all():
            raise ValueError(f"track target must be a finite pixel (u, v), got {uv.tolist()}")
        object.__setattr__(self, "uv", uv)

    def desired(self, est: GazeEstimate, head: HeadGeometry, camera: CameraIntrinsics) -> Desired:
        ray = unproject(camera, self.uv[None])[0]
        ray = ray / np.linalg.norm(ray)
        err = math.acos(float(np.clip(ray[2], -1.0, 1.0)))
        d_mount = est.R_mount_cam @ ray
        if est.T_world_mount is not None or est.R_world_cam is not None:
            # The body keeps turning while the command is reached: look where the point will be.
            R_wm = est.T_world_mount[:3, :3] if est.T_world_mount is not None else \
                est.R_world_cam @ est.R_mount_cam.T
            d_mount = (R_wm.T @ _rotation_exp(-est.w_mount * est.lead) @ R_wm) @ d_mount
        res = gaze_at_direction(head, d_mount, est.up_mount(), q_current=est.q)
        return Desired(res.q if res.reachable else None, err, res.reachable)


@dataclass(frozen=True)
class Slave:
    """Follow joint angles given from outside, q (3,) rad, inside the joint ranges."""

    q: np.ndarray
    name: str = field(default="slave", init=False)

    def __post_init__(self):
        q = np.asarray(self.q, float)
        if q.shape != (3,) or not np.isfinite(q).all():
            raise ValueError(f"slave target must be 3 finite joint angles, rad, got {q.tolist()}")
        object.__setattr__(self, "q", q.copy())

    def desired(self, est: GazeEstimate, head: HeadGeometry, camera: CameraIntrinsics) -> Desired:
        return Desired(self.q, float(np.linalg.norm(self.q - est.q)))


#: The modes' names, in the order of the table above.
MODES = ("hold", "fixate", "saccade", "stabilise", "body", "track", "slave")
