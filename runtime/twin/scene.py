"""The twin's MJCF scene: a room, a workbench with textured objects and a known target, the
wearer's segments (kinematically driven mocap bodies) and the head mounted on one of them.

World frame: metres, z up, origin on the floor. The workbench stands in front of the origin
along -y. The target is a black rectangle on a white card lying on the bench; its four outer
corners are the known points of target.toml.

Textures are procedural (random rectangles, checks, lines and letters drawn with OpenCV,
seeded), so every object offers plenty of corners at 0.5 to 2 m without any fetched data.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import HeadGeometry
from kinematics.camera import CameraIntrinsics
from kinematics.mjcf import head_actuators_and_sensors, head_body

from .mount import Mount
from .wearer import Wearer

HEAD_PREFIX = "head/"
WEARER_PREFIX = "wearer/"
CARD_BODY = "object/card"
OCCLUDER_BODY = "object/occluder"
TIMESTEP = 0.001


@dataclass(frozen=True)
class Workbench:
    """Where the bench and its target are (world frame, metres)."""

    centre_xy: tuple[float, float] = (0.0, -0.75)
    size: tuple[float, float] = (1.6, 0.7)      # along x, along y
    height: float = 0.85
    target_xy: tuple[float, float] = (0.0, -0.62)
    target_yaw: float = 0.0
    card_size: tuple[float, float] = (0.297, 0.210)   # A4, landscape
    rect_size: tuple[float, float] = (0.200, 0.130)   # the black rectangle

    def target_corners(self) -> np.ndarray:
        """(4, 3) world corners of the black rectangle: the known points (counter-clockwise from above)."""
        w, h = self.rect_size
        local = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
        c, s = math.cos(self.target_yaw), math.sin(self.target_yaw)
        xy = local @ np.array([[c, s], [-s, c]]) + np.asarray(self.target_xy)
        return np.column_stack([xy, np.full(4, self.height + _CARD_T + _RECT_T)])


_CARD_T = 0.0005   # card thickness above the bench top, m
_RECT_T = 0.0002   # the printed rectangle's thickness above the card


def _texture(rng: np.random.Generator, size: int = 256, style: str = "clutter") -> bytes:
    """A PNG of a corner-rich pattern: coloured rectangles, checks, lines and letters."""
    img = np.full((size, size, 3), rng.integers(150, 255, 3), np.uint8)
    for _ in range(int(size * size / 900)):
        x, y = rng.integers(0, size, 2)
        w, h = rng.integers(size // 32, size // 6, 2)
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        kind = rng.integers(0, 4 if style == "clutter" else 2)
        if kind == 0:
            cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), colour, -1)
        elif kind == 1:
            cv2.line(img, (int(x), int(y)), (int(x + w), int(y + h)), colour, int(rng.integers(1, 4)))
        elif kind == 2:
            k = int(rng.integers(2, 5))
            cell = max(int(w) // k, 2)
            for i in range(k):
                for j in range(k):
                    if (i + j) % 2 == 0:
                        cv2.rectangle(img, (int(x) + i * cell, int(y) + j * cell),
                                      (int(x) + (i + 1) * cell, int(y) + (j + 1) * cell), colour, -1)
        else:
            letters = "ABEFHKLMNTXYZ47"
            text = "".join(rng.choice(list(letters), int(rng.integers(1, 4))))
            cv2.putText(img, text, (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, float(rng.uniform(0.4, 1.2)),
                        colour, int(rng.integers(1, 3)))
    ok, png = cv2.imencode(".png", img)
    return png.tobytes()


def _bench_top_texture(rng: np.random.Generator, size_m: tuple[float, float], px_per_m: float = 320.0) -> bytes:
    """A PNG covering the whole bench top once (no tiling: a repeated pattern would invite
    mismatches a tile apart): wood with scattered sheets, notes and marks."""
    W, H = int(px_per_m * size_m[0]), int(px_per_m * size_m[1])
    img = np.zeros((H, W, 3), np.uint8)
    img[:] = (84, 122, 158)                       # wood, BGR
    for y in range(0, H, 6):                      # grain
        shade = int(rng.integers(-10, 10))
        img[y:y + 3] = np.clip(img[y:y + 3].astype(int) + shade, 0, 255)
    for _ in range(int(45 * size_m[0] * size_m[1])):
        x, y = int(rng.integers(0, W - 40)), int(rng.integers(0, H - 40))
        w, h = (int(v) for v in rng.integers(20, 70, 2))
        colour = tuple(int(c) for c in rng.integers(150, 255, 3)) if rng.uniform() < 0.7 else \
            tuple(int(c) for c in rng.integers(0, 90, 3))
        cv2.rectangle(img, (x, y), (x + w, y + h), colour, -1)
        if rng.uniform() < 0.5:                   # print on the sheet
            cv2.putText(img, "".join(rng.choice(list("ABEFHKLMNTXYZ47"), 2)), (x + 3, y + h - 5),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.5, (20, 20, 20), 1)
    ok, png = cv2.imencode(".png", img)
    return png.tobytes()


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(v))


def _quat(R: np.ndarray) -> str:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return _fmt([w, x, y, z])


def build_scene(head: HeadGeometry, camera_render: CameraIntrinsics, wearer: Wearer, mount: Mount,
                bench: Workbench = Workbench(), seed: int = 0, n_objects: int | None = None,
                stool: tuple[float, float, float] | None = None, moving_card: bool = False) -> tuple[str, dict]:
    """(MJCF string, assets dict of PNG bytes) of the whole scene.

    ``camera_render`` is the pinhole camera MuJoCo renders (see :mod:`runtime.twin.render`).
    The wearer's segments are mocap bodies named ``wearer/<segment>``, whose frames are the
    rest-pose body frame: setting a mocap pose to a segment's world-from-rest transform puts
    its mesh where it belongs. The head hangs below the mounted segment's body.
    """
    rng = np.random.default_rng(seed)
    if n_objects is None:
        # About 8 objects per square metre of bench, so a long bench is as cluttered as a short one.
        n_objects = max(6, int(round(8.0 * bench.size[0] * bench.size[1])))
    root = ET.Element("mujoco", model="wvr_twin")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", timestep=repr(TIMESTEP), gravity="0 0 -9.81", integrator="implicitfast")
    vis = ET.SubElement(root, "visual")
    ET.SubElement(vis, "global", offwidth=str(max(camera_render.width, 640)),
                  offheight=str(max(camera_render.height, 480)))
    ET.SubElement(vis, "quality", offsamples="4")
    ET.SubElement(vis, "headlight", ambient="0.25 0.25 0.25", diffuse="0.2 0.2 0.2", specular="0 0 0")
    asset = ET.SubElement(root, "asset")
    assets: dict[str, bytes] = {}
    ET.SubElement(asset, "texture", name="floor", type="2d", builtin="checker", rgb1="0.55 0.5 0.45",
                  rgb2="0.35 0.32 0.3", width="512", height="512", mark="edge", markrgb="0.2 0.2 0.2")
    ET.SubElement(asset, "material", name="floor", texture="floor", texrepeat="8 8", specular="0")
    for k in range(n_objects + 4):
        name = f"tex{k}.png"
        assets[name] = _texture(rng, 512 if k >= n_objects else 256)
        ET.SubElement(asset, "texture", name=f"tex{k}", type="2d", file=name)
        # Box faces each get the whole texture ("cube" mapping would need 6 images).
        ET.SubElement(asset, "material", name=f"mat{k}", texture=f"tex{k}", specular="0.05",
                      texrepeat="1 1", texuniform="false")
    ET.SubElement(asset, "material", name="white", rgba="0.95 0.95 0.95 1", specular="0")
    ET.SubElement(asset, "material", name="black", rgba="0.02 0.02 0.02 1", specular="0")
    ET.SubElement(asset, "material", name="wood", rgba="0.62 0.48 0.33 1", specular="0.05")
    # The bench top: wood strewn with sheets, notes and tools' outlines, so even its empty parts
    # offer corners.
    assets["benchtop.png"] = _bench_top_texture(rng, bench.size)
    ET.SubElement(asset, "texture", name="benchtop", type="2d", file="benchtop.png")
    ET.SubElement(asset, "material", name="benchtop", texture="benchtop", specular="0.05", texrepeat="1 1")
    ET.SubElement(asset, "material", name="skin", rgba="0.78 0.62 0.52 1", specular="0.1")
    for s, name in enumerate(wearer.segments):
        v, f = wearer.segment_mesh(s)
        ET.SubElement(asset, "mesh", name=f"{WEARER_PREFIX}{name}", vertex=_fmt(v), face=" ".join(map(str, f.ravel())))

    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", name="key", pos="1.5 1.0 3.0", dir="-0.4 -0.6 -1", directional="true",
                  diffuse="0.75 0.75 0.72", specular="0.1 0.1 0.1", castshadow="false")
    ET.SubElement(world, "light", name="fill", pos="-2 -1 2.5", dir="0.5 0.2 -1", directional="true",
                  diffuse="0.3 0.3 0.32", specular="0 0 0", castshadow="false")
    ET.SubElement(world, "geom", name="floor", type="plane", size="6 6 0.1", material="floor", contype="0", conaffinity="0")
    # Walls with posters, 2.5 to 3 m away: far features for SLAM.
    nt = n_objects
    for k, (pos, euler, size) in enumerate([((0, -2.6, 1.4), (math.pi / 2, 0, 0), (2.0, 1.2)),
                                            ((-2.8, -0.8, 1.4), (math.pi / 2, 0, math.pi / 2), (1.6, 1.0)),
                                            ((2.8, -0.8, 1.4), (math.pi / 2, 0, -math.pi / 2), (1.6, 1.0)),
                                            ((0, 2.6, 1.4), (math.pi / 2, 0, math.pi), (2.0, 1.2))]):
        ET.SubElement(world, "geom", name=f"poster{k}", type="box", size=_fmt([size[0], size[1], 0.01]),
                      pos=_fmt(pos), quat=_quat(Rotation.from_euler("xyz", euler).as_matrix()),
                      material=f"mat{nt + k}", contype="0", conaffinity="0")
    # The bench: a top and four legs.
    bx, by = bench.centre_xy
    sx, sy = bench.size
    top_t = 0.03
    b = ET.SubElement(world, "body", name="bench", pos=_fmt([bx, by, 0]))
    ET.SubElement(b, "geom", name="bench_top", type="box", size=_fmt([sx / 2, sy / 2, top_t / 2]),
                  pos=_fmt([0, 0, bench.height - top_t / 2]), material="benchtop", contype="0", conaffinity="0")
    for i, (lx, ly) in enumerate([(-1, -1), (1, -1), (1, 1), (-1, 1)]):
        ET.SubElement(b, "geom", name=f"bench_leg{i}", type="box", size="0.025 0.025 " + repr((bench.height - top_t) / 2),
                      pos=_fmt([lx * (sx / 2 - 0.05), ly * (sy / 2 - 0.05), (bench.height - top_t) / 2]),
                      material="wood", contype="0", conaffinity="0")
    # Objects on the bench, kept off the target card.
    tx, ty = bench.target_xy
    placed = 0
    tries = 0
    while placed < n_objects and tries < 500:
        tries += 1
        w, d, h = rng.uniform(0.05, 0.22), rng.uniform(0.05, 0.18), rng.uniform(0.04, 0.30)
        x = rng.uniform(bx - sx / 2 + w / 2 + 0.02, bx + sx / 2 - w / 2 - 0.02)
        y = rng.uniform(by - sy / 2 + d / 2 + 0.02, by + sy / 2 - d / 2 - 0.02)
        if abs(x - tx) < (bench.card_size[0] + w) / 2 + 0.03 and abs(y - ty) < (bench.card_size[1] + d) / 2 + 0.03:
            continue
        yaw = rng.uniform(-0.6, 0.6)
        ET.SubElement(world, "geom", name=f"object{placed}", type="box", size=_fmt([w / 2, d / 2, h / 2]),
                      pos=_fmt([x, y, bench.height + h / 2]), quat=_quat(Rotation.from_euler("z", yaw).as_matrix()),
                      material=f"mat{placed}", contype="0", conaffinity="0")
        placed += 1
    # The target: a white card and a black rectangle printed on it.
    q = _quat(Rotation.from_euler("z", bench.target_yaw).as_matrix())
    ET.SubElement(world, "geom", name="target_card", type="box",
                  size=_fmt([bench.card_size[0] / 2, bench.card_size[1] / 2, _CARD_T / 2]),
                  pos=_fmt([tx, ty, bench.height + _CARD_T / 2]), quat=q, material="white", contype="0", conaffinity="0")
    ET.SubElement(world, "geom", name="target_rect", type="box",
                  size=_fmt([bench.rect_size[0] / 2, bench.rect_size[1] / 2, _RECT_T / 2]),
                  pos=_fmt([tx, ty, bench.height + _CARD_T + _RECT_T / 2]), quat=q, material="black",
                  contype="0", conaffinity="0")
    if moving_card:
        # Mocap bodies the twin moves every frame (Scenario.T_world_card, T_world_occluder). Its
        # texture comes from its own generator, so the rest of the scene stays as it was.
        from .scenarios import MOVING_CARD_SIZE, MOVING_CARD_T, OCCLUDER_T

        assets["card.png"] = _texture(np.random.default_rng(seed + 7919), 256)
        ET.SubElement(asset, "texture", name="card", type="2d", file="card.png")
        ET.SubElement(asset, "material", name="card", texture="card", specular="0.05", texrepeat="1 1")
        body = ET.SubElement(world, "body", name=CARD_BODY, mocap="true")
        ET.SubElement(body, "geom", name="moving_card", type="box",
                      size=_fmt([MOVING_CARD_SIZE[0] / 2, MOVING_CARD_SIZE[1] / 2, MOVING_CARD_T / 2]),
                      material="card", contype="0", conaffinity="0", mass="0")
        body = ET.SubElement(world, "body", name=OCCLUDER_BODY, mocap="true")
        ET.SubElement(body, "geom", name="occluder", type="box",
                      size=_fmt([MOVING_CARD_SIZE[0] / 8, 0.6 * MOVING_CARD_SIZE[1], OCCLUDER_T / 2]),
                      material="skin", contype="0", conaffinity="0", mass="0")
    if stool is not None:   # (x, y, seat height): something to sit on
        x, y, h = stool
        ET.SubElement(world, "geom", name="stool", type="box", size=_fmt([0.2, 0.2, h / 2]), pos=_fmt([x, y, h / 2]),
                      material="wood", contype="0", conaffinity="0")
    # The wearer: one mocap body per segment, frames = the rest-pose body frame.
    ms = wearer.index(mount.segment)
    for s, name in enumerate(wearer.segments):
        body = ET.SubElement(world, "body", name=f"{WEARER_PREFIX}{name}", mocap="true")
        ET.SubElement(body, "geom", name=f"{WEARER_PREFIX}{name}", type="mesh", mesh=f"{WEARER_PREFIX}{name}",
                      material="skin", contype="0", conaffinity="0", mass="0")
        if s == ms:
            T = mount.T_rest_mount(wearer.joints[ms])
            x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
            body.append(head_body(head, camera_render, prefix=HEAD_PREFIX, pos=T[:3, 3], quat_wxyz=(w, x, y, z)))
    head_actuators_and_sensors(head, root, prefix=HEAD_PREFIX)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode"), assets
