"""The augmented camera view: the live image with the world frame's axes, the active search
(predicted features and their 3-sigma ellipses, the matches), the operator's labels and virtual
objects, explore's candidate fixations coloured by their scores, all projected through SLAM's current pose and the lens model (curved edges are sampled,
so any lens model of the formats draws them where the camera sees them).

Drawn in the web server's threads, never in the control loop's."""

from __future__ import annotations

import math

import cv2
import numpy as np

from kinematics.camera import CameraIntrinsics

from .geometry import EXPLORE_OBJECTIVE, ExploreView, Label, VirtualObject, ellipse_axes, world_to_pixels
from .slam_view import MapView

AXIS_LENGTH_M = 0.1
#: Points per straight world edge when drawn through the lens model.
EDGE_SAMPLES = 12

_RED, _GREEN, _BLUE = (230, 40, 40), (40, 200, 40), (60, 90, 255)
_YELLOW, _CYAN, _MAGENTA, _WHITE = (250, 220, 0), (0, 220, 220), (230, 0, 230), (255, 255, 255)
#: Explore's candidate markers: radius, px, at the lowest and the highest score; the chosen one's ring.
EXPLORE_RADIUS_PX = (3, 9)
EXPLORE_RING_PX = 4


def score_colours(s: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 RGB for scores ``s`` (n,) in [0, 1]: viridis (dark blue low, yellow high)."""
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)[:, 0, ::-1]
    return lut[np.clip(np.round(np.asarray(s, float) * 255), 0, 255).astype(int)]


def _polyline(img, camera, T, segments, colour, thickness=2) -> int:
    """Draw world segments (E, 2, 3) sampled through the lens model; returns how many showed."""
    shown = 0
    s = np.linspace(0.0, 1.0, EDGE_SAMPLES)[:, None]
    for a, b in np.asarray(segments, float).reshape(-1, 2, 3):
        uv = world_to_pixels(camera, T, a + s * (b - a))
        ok = np.isfinite(uv).all(axis=1)
        if ok.sum() < 2:
            continue
        pts = np.round(uv[ok]).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, colour, thickness, cv2.LINE_AA)
        shown += 1
    return shown


def draw_world_axes(img, camera: CameraIntrinsics, T_world_cam, length: float = AXIS_LENGTH_M) -> None:
    o = np.zeros(3)
    for axis, colour in zip(np.eye(3), (_RED, _GREEN, _BLUE)):
        _polyline(img, camera, T_world_cam, [[o, length * axis]], colour, 2)


def draw_search(img, view: MapView) -> None:
    s = view.search
    if s is None:
        return
    for uv, S, z, used in zip(s.uv, s.S, s.z, s.used):
        if not (np.isfinite(uv).all() and np.isfinite(S).all()):
            continue
        axes, ang = ellipse_axes(S)
        colour = _GREEN if used else (_RED if np.isfinite(z).all() else _YELLOW)
        cv2.ellipse(img, (int(round(uv[0])), int(round(uv[1]))), (max(1, int(round(axes[0]))), max(1, int(round(axes[1])))),
                    math.degrees(ang), 0, 360, colour, 1, cv2.LINE_AA)
        if np.isfinite(z).all():
            cv2.circle(img, (int(round(z[0])), int(round(z[1]))), 2, colour, -1)


def draw_features(img, camera: CameraIntrinsics, view: MapView) -> None:
    """Every map feature's projection, with its id (target points in cyan)."""
    uv = world_to_pixels(camera, view.T_world_cam, view.xyz)
    for fid, p, known in zip(view.ids, uv, view.known):
        if not np.isfinite(p).all():
            continue
        c = (int(round(p[0])), int(round(p[1])))
        cv2.drawMarker(img, c, _CYAN if known else _YELLOW, cv2.MARKER_CROSS, 8, 1)
        cv2.putText(img, str(int(fid)), (c[0] + 4, c[1] - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, _WHITE, 1, cv2.LINE_AA)


def draw_labels(img, camera: CameraIntrinsics, T_world_cam, labels: list[Label]) -> None:
    if not labels:
        return
    uv = world_to_pixels(camera, T_world_cam, np.array([lb.xyz for lb in labels]))
    for lb, p in zip(labels, uv):
        if not np.isfinite(p).all():
            continue
        c = (int(round(p[0])), int(round(p[1])))
        cv2.circle(img, c, 5, _MAGENTA, 2, cv2.LINE_AA)
        cv2.putText(img, lb.text, (c[0] + 8, c[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, lb.text, (c[0] + 8, c[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.5, _MAGENTA, 1, cv2.LINE_AA)


def draw_objects(img, camera: CameraIntrinsics, T_world_cam, objects: list[VirtualObject]) -> None:
    for ob in objects:
        _polyline(img, camera, T_world_cam, ob.edges(), _MAGENTA if ob.kind == "arrow" else _CYAN, 2)


def _text(img, text, org, colour, scale=0.45) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def draw_explore(img, camera: CameraIntrinsics, T_world_cam, ev: ExploreView) -> int:
    """Explore's candidates: each fixation point a disc whose colour and size grow with its score
    (normalised over the candidates), its score beside it, the chosen one ringed in white; and a
    legend line stating the objective. Returns how many candidates are in the image."""
    h, w = img.shape[:2]
    uv = world_to_pixels(camera, T_world_cam, ev.points_world)
    inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    s = ev.normalised()
    colours = score_colours(s)
    r0, r1 = EXPLORE_RADIUS_PX
    # The chosen one last, so that no other candidate's disc covers it.
    for k in sorted(np.flatnonzero(inside), key=lambda k: k == ev.chosen):
        c = (int(round(uv[k, 0])), int(round(uv[k, 1])))
        r = int(round(r0 + (r1 - r0) * s[k]))
        cv2.circle(img, c, r + 1, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.circle(img, c, r, tuple(int(v) for v in colours[k]), -1, cv2.LINE_AA)
        if k == ev.chosen:
            cv2.circle(img, c, r + EXPLORE_RING_PX, _WHITE, 2, cv2.LINE_AA)
        _text(img, f"{ev.score[k]:.2f}", (c[0] + r + 6, c[1] + 4), _WHITE, 0.4)
    n_in = int(inside.sum())
    legend = f"explore: {EXPLORE_OBJECTIVE} | ring: chosen | {n_in}/{len(ev.score)} in view"
    _text(img, legend, (8, h - 10), _WHITE, 0.42)
    # The colour scale after it: low (left) to high (right).
    (tw, _), _ = cv2.getTextSize(legend, cv2.FONT_HERSHEY_SIMPLEX, 0.42, 1)
    x0, x1 = 8 + tw + 10, min(w - 8, 8 + tw + 90)
    if x1 > x0:
        bar = score_colours(np.linspace(0.0, 1.0, x1 - x0))
        img[h - 18:h - 10, x0:x1] = bar[None]
        cv2.rectangle(img, (x0 - 1, h - 19), (x1, h - 10), _WHITE, 1)
    return n_in


def camera_view(image: np.ndarray, camera: CameraIntrinsics, view: MapView, labels: list[Label],
                objects: list[VirtualObject], banner: str = "", explore: ExploreView | None = None) -> np.ndarray:
    """The augmented camera view (H, W, 3) uint8 RGB: a copy of ``image`` with the overlays
    drawn where SLAM's pose ``view.T_world_cam`` and the lens model put them (none while lost).
    ``explore`` : explore's candidates, while the loop explores (None otherwise)."""
    img = np.ascontiguousarray(image, dtype=np.uint8).copy()
    if view.localised:
        draw_world_axes(img, camera, view.T_world_cam)
        draw_search(img, view)
        draw_features(img, camera, view)
        draw_objects(img, camera, view.T_world_cam, objects)
        draw_labels(img, camera, view.T_world_cam, labels)
        if explore is not None:
            draw_explore(img, camera, view.T_world_cam, explore)
    if banner:
        cv2.putText(img, banner, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, banner, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, _WHITE, 1, cv2.LINE_AA)
    return img


def encode_jpeg(image_rgb: np.ndarray, quality: int = 80) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("the camera view could not be encoded as JPEG")
    return buf.tobytes()
