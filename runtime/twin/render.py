"""Image formation: MuJoCo renders a pinhole image; lens distortion, if the camera has any, is
applied afterwards by remapping, exactly by the camera model of kinematics.camera.

For a camera with distortion the pinhole render covers the undistorted extent of the whole
distorted image (so a wide-angle radial-sqrt or fisheye camera sees its full field), at the
same focal length in the centre; every output pixel is then looked up through ``undistort``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics, undistort


def has_distortion(cam: CameraIntrinsics) -> bool:
    return any(v != 0.0 for v in cam.distortion.values())


@dataclass(frozen=True)
class ImageFormation:
    """How to turn a MuJoCo render into the camera's image.

    render_camera : the pinhole camera MuJoCo renders.
    map_x, map_y : (H, W) float32 remap tables from output pixels to render pixels, or None.
    """

    camera: CameraIntrinsics
    render_camera: CameraIntrinsics
    map_x: np.ndarray | None = None
    map_y: np.ndarray | None = None

    def form(self, rendered: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """The camera's image (or any per-pixel render, e.g. depth) from the pinhole render;
        ``interpolation`` an OpenCV flag (nearest for depth, so edges never blend surfaces)."""
        if self.map_x is None:
            return rendered
        return cv2.remap(rendered, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)


def image_formation(cam: CameraIntrinsics, max_render: int = 2048) -> ImageFormation:
    """The render camera and remap tables for ``cam`` (identity for a pinhole camera)."""
    if not has_distortion(cam):
        return ImageFormation(cam, cam)
    W, H = cam.width, cam.height
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    xy = undistort(cam, np.column_stack([u.ravel(), v.ravel()]))
    if not np.all(np.isfinite(xy)):
        raise ValueError("the camera's distortion has no inverse over the whole image; check the lens terms")
    # A pinhole render at the same focal length that contains every undistorted ray, capped.
    x_lo, x_hi = xy[:, 0].min(), xy[:, 0].max()
    y_lo, y_hi = xy[:, 1].min(), xy[:, 1].max()
    scale = 1.0
    w_r = cam.fx * (x_hi - x_lo) + 4
    h_r = cam.fy * (y_hi - y_lo) + 4
    if max(w_r, h_r) > max_render:
        scale = max_render / max(w_r, h_r)
    fx, fy = cam.fx * scale, cam.fy * scale
    Wr, Hr = int(math.ceil(fx * (x_hi - x_lo))) + 4, int(math.ceil(fy * (y_hi - y_lo))) + 4
    render = CameraIntrinsics(width=Wr, height=Hr, fx=fx, fy=fy, cx=-fx * x_lo + 2, cy=-fy * y_lo + 2)
    mx = (render.fx * xy[:, 0] + render.cx).reshape(H, W).astype(np.float32)
    my = (render.fy * xy[:, 1] + render.cy).reshape(H, W).astype(np.float32)
    return ImageFormation(cam, render, mx, my)
