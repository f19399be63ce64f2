"""The simulated operator: the person who clicks the known target's corners in the first image.

A person clicks each corner a couple of pixels off, on a half-pixel grid at best (a zoomed
view), so ``target.toml``'s pixels are approximate; start-up must refine them on the image.
The twin plays that person from the true projection (it knows where the corners are); what it
hands over, a :class:`~runtime.sequence.Target`, is all the runtime gets: the recorder writes it
as target.toml, and the closed loop can start SLAM from the same kind of input.
"""

from __future__ import annotations

import mujoco
import numpy as np

from kinematics.camera import project

from ..sequence import Target
from .twin import CLICK_STREAM, Twin

#: A person's click: this far off on average (px), uniformly 0.8 to 1.2 times it.
CLICK_ERROR_PX = 2.5


def target_in_first_frame(twin: Twin) -> Target:
    """The target's four corners (world) and where the camera model projects them now: exact
    pixels, the truth a click is scored against."""
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


class TargetHidden(ValueError):
    """The target's corners cannot all be seen in the first image, so no one could click them."""


def hidden_points(twin: Twin, eye: np.ndarray, xyz: np.ndarray, clearance: float = 0.02,
                  tol: float = 0.01) -> np.ndarray:
    """(n,) whether each world point ``xyz`` (n, 3), m, is hidden from ``eye`` (3,) by the
    twin's geometry as it stands: MuJoCo's ray from ``clearance`` m in front of the eye (past
    the camera's own housing) meets a geom more than ``tol`` m before the point (a point on a
    surface is hit at its own distance, within the sheet's thickness over the sine of a grazing
    view)."""
    out = np.zeros(len(xyz), bool)
    geom = np.zeros(1, np.int32)
    for i, p in enumerate(np.asarray(xyz, float)):
        d = p - eye
        dist = float(np.linalg.norm(d))
        u = d / dist
        hit = mujoco.mj_ray(twin.model, twin.data, eye + clearance * u, u, None, 1, -1, geom)
        out[i] = hit >= 0 and clearance + hit < dist - tol
    return out


def click(uv: np.ndarray, error_px: float, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """(n, 2) clicked pixels for true pixels ``uv`` (n, 2): each moved by 0.8..1.2 x ``error_px``
    in a random direction, rounded to the nearest half pixel, kept inside the image. An error of
    0 returns the true pixels unchanged (not rounded)."""
    uv = np.asarray(uv, float)
    if not np.isfinite(error_px) or error_px < 0:
        raise ValueError(f"click error {error_px!r} px: give 0 or more pixels")
    if error_px == 0:
        return uv.copy()
    angle = rng.uniform(0.0, 2 * np.pi, len(uv))
    r = error_px * rng.uniform(0.8, 1.2, len(uv))
    out = np.round(2.0 * (uv + r[:, None] * np.column_stack([np.cos(angle), np.sin(angle)]))) / 2.0
    return np.clip(out, 0.0, [width - 1, height - 1])


def clicked_target(twin: Twin, error_px: float = CLICK_ERROR_PX, rng: np.random.Generator | None = None) -> Target:
    """target.toml as a person makes it for the twin's current image: the known corners and
    where the operator clicked them (the true projection ``error_px`` off, see :func:`click`).
    Raises :class:`TargetHidden` if a corner is hidden behind the scene (:func:`hidden_points`).
    ``rng`` defaults to the run's own click stream (reproducible per seed)."""
    exact = target_in_first_frame(twin)
    hidden = np.flatnonzero(hidden_points(twin, twin.ground_truth.T_world_cam[:3, 3], exact.xyz))
    if len(hidden):
        raise TargetHidden(f"the target's corners {hidden.tolist()} are hidden behind the scene at the start of "
                           f"{twin.scenario.name} (no one could click them); use another seed")
    rng = np.random.default_rng([twin.seed, CLICK_STREAM]) if rng is None else rng
    return Target(xyz=exact.xyz, uv=click(exact.uv, error_px, rng, twin.camera.width, twin.camera.height))
