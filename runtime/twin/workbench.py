"""The workbench: a bench strewn with randomly textured boxes in a room of posters, and its known
target, a black rectangle printed on a white card lying on the bench (its four outer corners are
the known points of target.toml).

World frame: metres, z up, origin on the floor. The bench stands in front of the origin along
-y. Textures are saturated and corner-rich (:func:`runtime.twin.textures.clutter`): every
object offers plenty of corners at 0.5 to 2 m, more than a real bench would.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from . import textures
from .mjcf_doc import SceneDoc, fmt, quat

_CARD_T = 0.0005   # card thickness above the bench top, m
_RECT_T = 0.0002   # the printed rectangle's thickness above the card


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

    kind = "workbench"

    def target_corners(self) -> np.ndarray:
        """(4, 3) world corners of the black rectangle: the known points (counter-clockwise from above)."""
        w, h = self.rect_size
        local = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
        c, s = math.cos(self.target_yaw), math.sin(self.target_yaw)
        xy = local @ np.array([[c, s], [-s, c]]) + np.asarray(self.target_xy)
        return np.column_stack([xy, np.full(4, self.height + _CARD_T + _RECT_T)])

    # What the scripted gazes look at (runtime.twin.scenarios): world points, m.
    def look_point(self) -> np.ndarray:
        """The target's centre on the bench top."""
        return np.r_[self.target_xy, self.height]

    def sweep_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The two amplitude vectors of the sweeping gaze about the target: along the bench and
        towards the wearer."""
        return np.array([0.35, 0.0, 0.0]), np.array([0.0, -0.12, 0.0])

    def follow_point(self, x: float) -> np.ndarray:
        """The point of the bench's target line at x (clipped to the bench, 10 cm from its ends)."""
        x = float(np.clip(x, self.centre_xy[0] - self.size[0] / 2 + 0.1, self.centre_xy[0] + self.size[0] / 2 - 0.1))
        return np.array([x, self.target_xy[1], self.height])

    def away_point(self) -> np.ndarray:
        """Where a gaze that leaves the target goes: up and to the left, to the far wall's poster
        and the bench's left end (natural features only, the target out of view)."""
        return np.array([-0.9, -2.6, 1.45])


def build_workbench(doc: SceneDoc, bench: Workbench, rng: np.random.Generator, n_objects: int | None = None) -> None:
    """Add the workbench's lights, floor, posters, bench, objects and target to ``doc``."""
    if n_objects is None:
        # About 8 objects per square metre of bench, so a long bench is as cluttered as a short one.
        n_objects = max(6, int(round(8.0 * bench.size[0] * bench.size[1])))
    ET.SubElement(doc.visual, "headlight", ambient="0.25 0.25 0.25", diffuse="0.2 0.2 0.2", specular="0 0 0")
    _workbench_materials(doc, bench, rng, n_objects)
    world = doc.world
    ET.SubElement(world, "light", name="key", pos="1.5 1.0 3.0", dir="-0.4 -0.6 -1", directional="true",
                  diffuse="0.75 0.75 0.72", specular="0.1 0.1 0.1", castshadow="false")
    ET.SubElement(world, "light", name="fill", pos="-2 -1 2.5", dir="0.5 0.2 -1", directional="true",
                  diffuse="0.3 0.3 0.32", specular="0 0 0", castshadow="false")
    ET.SubElement(world, "geom", name="floor", type="plane", size="6 6 0.1", material="floor", contype="0", conaffinity="0")
    _posters(world, n_objects)
    _bench_body(world, bench)
    _bench_objects(world, bench, rng, n_objects)
    _bench_target(world, bench)


def _workbench_materials(doc: SceneDoc, bench: Workbench, rng: np.random.Generator, n_objects: int) -> None:
    asset = doc.asset
    ET.SubElement(asset, "texture", name="floor", type="2d", builtin="checker", rgb1="0.55 0.5 0.45",
                  rgb2="0.35 0.32 0.3", width="512", height="512", mark="edge", markrgb="0.2 0.2 0.2")
    ET.SubElement(asset, "material", name="floor", texture="floor", texrepeat="8 8", specular="0")
    for k in range(n_objects + 4):
        name = f"tex{k}.png"
        doc.assets[name] = textures.clutter(rng, 512 if k >= n_objects else 256)
        ET.SubElement(asset, "texture", name=f"tex{k}", type="2d", file=name)
        # Box faces each get the whole texture ("cube" mapping would need 6 images).
        ET.SubElement(asset, "material", name=f"mat{k}", texture=f"tex{k}", specular="0.05",
                      texrepeat="1 1", texuniform="false")
    ET.SubElement(asset, "material", name="white", rgba="0.95 0.95 0.95 1", specular="0")
    ET.SubElement(asset, "material", name="black", rgba="0.02 0.02 0.02 1", specular="0")
    ET.SubElement(asset, "material", name="wood", rgba="0.62 0.48 0.33 1", specular="0.05")
    # The bench top: wood strewn with sheets, notes and tools' outlines, so even its empty parts
    # offer corners.
    doc.assets["benchtop.png"] = textures.bench_top(rng, bench.size)
    ET.SubElement(asset, "texture", name="benchtop", type="2d", file="benchtop.png")
    ET.SubElement(asset, "material", name="benchtop", texture="benchtop", specular="0.05", texrepeat="1 1")


def _posters(world: ET.Element, first_material: int) -> None:
    """Walls' posters 2.5 to 3 m away: far features for SLAM."""
    for k, (pos, euler, size) in enumerate([((0, -2.6, 1.4), (math.pi / 2, 0, 0), (2.0, 1.2)),
                                            ((-2.8, -0.8, 1.4), (math.pi / 2, 0, math.pi / 2), (1.6, 1.0)),
                                            ((2.8, -0.8, 1.4), (math.pi / 2, 0, -math.pi / 2), (1.6, 1.0)),
                                            ((0, 2.6, 1.4), (math.pi / 2, 0, math.pi), (2.0, 1.2))]):
        ET.SubElement(world, "geom", name=f"poster{k}", type="box", size=fmt([size[0], size[1], 0.01]),
                      pos=fmt(pos), quat=quat(Rotation.from_euler("xyz", euler).as_matrix()),
                      material=f"mat{first_material + k}", contype="0", conaffinity="0")


def _bench_body(world: ET.Element, bench: Workbench) -> None:
    """The bench: a top and four legs."""
    bx, by = bench.centre_xy
    sx, sy = bench.size
    top_t = 0.03
    b = ET.SubElement(world, "body", name="bench", pos=fmt([bx, by, 0]))
    ET.SubElement(b, "geom", name="bench_top", type="box", size=fmt([sx / 2, sy / 2, top_t / 2]),
                  pos=fmt([0, 0, bench.height - top_t / 2]), material="benchtop", contype="0", conaffinity="0")
    for i, (lx, ly) in enumerate([(-1, -1), (1, -1), (1, 1), (-1, 1)]):
        ET.SubElement(b, "geom", name=f"bench_leg{i}", type="box", size="0.025 0.025 " + repr((bench.height - top_t) / 2),
                      pos=fmt([lx * (sx / 2 - 0.05), ly * (sy / 2 - 0.05), (bench.height - top_t) / 2]),
                      material="wood", contype="0", conaffinity="0")


def _bench_objects(world: ET.Element, bench: Workbench, rng: np.random.Generator, n_objects: int) -> None:
    """Boxes on the bench, kept off the target card."""
    bx, by = bench.centre_xy
    sx, sy = bench.size
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
        ET.SubElement(world, "geom", name=f"object{placed}", type="box", size=fmt([w / 2, d / 2, h / 2]),
                      pos=fmt([x, y, bench.height + h / 2]), quat=quat(Rotation.from_euler("z", yaw).as_matrix()),
                      material=f"mat{placed}", contype="0", conaffinity="0")
        placed += 1


def _bench_target(world: ET.Element, bench: Workbench) -> None:
    """The target: a white card and a black rectangle printed on it."""
    tx, ty = bench.target_xy
    q = quat(Rotation.from_euler("z", bench.target_yaw).as_matrix())
    ET.SubElement(world, "geom", name="target_card", type="box",
                  size=fmt([bench.card_size[0] / 2, bench.card_size[1] / 2, _CARD_T / 2]),
                  pos=fmt([tx, ty, bench.height + _CARD_T / 2]), quat=q, material="white", contype="0", conaffinity="0")
    ET.SubElement(world, "geom", name="target_rect", type="box",
                  size=fmt([bench.rect_size[0] / 2, bench.rect_size[1] / 2, _RECT_T / 2]),
                  pos=fmt([tx, ty, bench.height + _CARD_T + _RECT_T / 2]), quat=q, material="black",
                  contype="0", conaffinity="0")
