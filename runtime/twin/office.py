"""The office: a desk against a wall with posters, a bookcase of titled spines, a dark monitor.

Large plain areas (painted wall, desk top, carpet), a switched-off monitor (dark and nearly
featureless), a keyboard (a repeated pattern), posters with titles and text, books on shelves
with their titles on the spines. Two printed targets: a sheet lying on the desk and a sheet
pinned to the wall, 21 x 15 cm, at eye height; ``known`` says which one is target.toml's (the
wall one, seen nearly frontally from 1 to 1.5 m, is the planar pose-ambiguity case). Both are
always built, so every office scenario with one scene seed shows the same place.

World frame: metres, z up; the wall's face is the plane y = ``wall_y``, the desk runs along x.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import textures
from .mjcf_doc import SceneDoc, rot_z
from .printed_target import PrintedTarget


@dataclass(frozen=True)
class OfficeDesk:
    """Where the desk, shelves and targets are (world frame, metres)."""

    wall_y: float = -1.35
    desk_x: tuple[float, float] = (-0.8, 0.8)
    desk_depth: float = 0.75
    desk_height: float = 0.74
    shelf_x: tuple[float, float] = (-1.85, -1.05)   # the bookcase, to the desk's right (facing the wall)
    desk_target: PrintedTarget = field(default_factory=lambda: PrintedTarget((-0.3, -0.86, 0.74), yaw=-0.05))
    wall_target: PrintedTarget = field(default_factory=lambda: PrintedTarget(
        (-0.42, -1.35, 1.40), upright=True, rect_size=(0.21, 0.15)))
    known: str = "desk"    # which target is target.toml's: "desk" or "wall"

    kind = "office"

    def __post_init__(self):
        if self.known not in ("desk", "wall"):
            raise ValueError(f"OfficeDesk.known = {self.known!r}: use 'desk' or 'wall'")

    @property
    def target(self) -> PrintedTarget:
        return self.desk_target if self.known == "desk" else self.wall_target

    def target_corners(self) -> np.ndarray:
        return self.target.corners()

    def look_point(self) -> np.ndarray:
        return np.asarray(self.target.centre, float)

    def sweep_axes(self) -> tuple[np.ndarray, np.ndarray]:
        if self.known == "wall":   # small, so the wall target stays in view, nearly frontal
            return np.array([0.12, 0.0, 0.0]), np.array([0.0, 0.0, 0.08])
        return np.array([0.35, 0.0, 0.0]), np.array([0.0, -0.12, 0.0])

    def follow_point(self, x: float) -> np.ndarray:
        x = float(np.clip(x, self.desk_x[0] + 0.1, self.desk_x[1] - 0.1))
        return np.array([x, self.target.centre[1], self.target.centre[2]])

    def away_point(self) -> np.ndarray:
        """The bookcase's middle shelves."""
        return np.array([0.5 * (self.shelf_x[0] + self.shelf_x[1]), self.wall_y + 0.3, 1.2])


ROOM = (2.3, 2.0, 2.6)          # x half-width, y of the opposite wall, ceiling height
SHELF = (0.3, 1.9, 5)           # bookcase depth, height, number of shelves


def build_office(doc: SceneDoc, o: OfficeDesk, rng: np.random.Generator) -> None:
    """Add the office's lights, room, posters, desk and what is on it, bookcase and both targets."""
    doc.headlight(ambient=(0.16, 0.16, 0.16), diffuse=(0.11, 0.11, 0.11))
    _office_materials(doc, rng)
    doc.light("ceiling0", (0.0, -0.4, 2.55), (0.05, -0.1, -1.0), (0.34, 0.34, 0.33), specular=(0.05, 0.05, 0.05))
    doc.light("ceiling1", (-1.5, 0.5, 2.55), (0.3, -0.4, -1.0), (0.15, 0.15, 0.15))
    _room(doc, o)
    _posters(doc, o, rng)
    _desk(doc, o, rng)
    _bookcase(doc, o, rng)
    o.desk_target.add_to(doc, "target_desk", "paper", "ink")
    o.wall_target.add_to(doc, "target_wall", "paper", "ink")


def _office_materials(doc: SceneDoc, rng: np.random.Generator) -> None:
    wall = tuple(int(c) for c in rng.choice([(214, 212, 204), (206, 210, 212), (218, 210, 196)]))
    doc.textured_material("wall", textures.paint(rng, wall), specular=0.0, repeat=(1, 1), uniform=True)
    carpet = tuple(int(c) for c in rng.choice([(88, 92, 100), (70, 72, 74), (120, 110, 96), (84, 96, 92)]))
    doc.textured_material("carpet", textures.paint(rng, carpet, mottle=0.06, grain=0.05), specular=0.0,
                          repeat=(2, 2), uniform=True)
    desk = tuple(int(c) for c in rng.choice([(178, 140, 100), (212, 208, 200), (150, 150, 146), (118, 86, 62)]))
    doc.textured_material("desk_top", textures.wood(rng, desk, (1024, 512), grain=0.04, period_px=4.0), specular=0.1)
    doc.textured_material("screen", textures.screen(rng), specular=0.5, shininess=0.8)
    doc.textured_material("keyboard", textures.keyboard(rng), specular=0.1)
    doc.colour_material("wood", (0.5, 0.38, 0.27), specular=0.05)
    doc.colour_material("shelf", tuple(float(c) for c in rng.choice([(0.85, 0.84, 0.8), (0.52, 0.4, 0.3)])),
                        specular=0.05)
    doc.colour_material("paper", (0.93, 0.93, 0.91))
    doc.colour_material("ink", (0.03, 0.03, 0.03))
    doc.colour_material("bezel", (0.05, 0.05, 0.055), specular=0.2)
    doc.colour_material("metal", (0.35, 0.36, 0.38), specular=0.3)
    doc.colour_material("ceiling", (0.9, 0.9, 0.88))
    doc.colour_material("mug", tuple(c / 255 for c in textures.muted_colour(rng, 80, 220, 0.5)), specular=0.3)
    doc.colour_material("notebook", tuple(c / 255 for c in textures.muted_colour(rng, 40, 140, 0.5)), specular=0.05)


def _room(doc: SceneDoc, o: OfficeDesk) -> None:
    """Carpet, ceiling and four walls, every painted face towards the room."""
    xh, ymax, h = ROOM
    yc, d = 0.5 * (o.wall_y + ymax), ymax - o.wall_y
    doc.panel("floor", 2 * xh, d, 0.02, [0, yc, 0.0], (0, 0, 1), "carpet", up=(0, 1, 0))
    doc.panel("ceiling", 2 * xh, d, 0.02, [0, yc, h], (0, 0, -1), "ceiling", up=(0, 1, 0))
    doc.panel("wall_back", 2 * xh, h, 0.1, [0, o.wall_y, h / 2], (0, 1, 0), "wall")
    doc.panel("wall_left", d, h, 0.1, [xh, yc, h / 2], (-1, 0, 0), "wall")
    doc.panel("wall_right", d, h, 0.1, [-xh, yc, h / 2], (1, 0, 0), "wall")
    doc.panel("wall_behind", 2 * xh, h, 0.1, [0, ymax, h / 2], (0, -1, 0), "wall")


def _posters(doc: SceneDoc, o: OfficeDesk, rng: np.random.Generator) -> None:
    """A tall poster left of the desk (facing the wall), a landscape one above the monitor, a
    small one on the side wall; plain wall in between."""
    y = o.wall_y + 0.003
    for i, (cx, cz, w, h) in enumerate(((1.35, 1.45, 0.59, 0.84), (0.3, 1.75, 0.6, 0.42))):
        name = f"poster{i}"
        px = (256, int(256 * h / w)) if h > w else (int(256 * w / h), 256)
        doc.textured_material(name, textures.poster(rng, px), specular=0.05)
        doc.panel(name, w, h, 0.003, [cx, y, cz], (0, 1, 0), name)
    doc.textured_material("poster2", textures.poster(rng, (256, 360)), specular=0.05)
    doc.panel("poster2", 0.42, 0.59, 0.003, [ROOM[0] - 0.003, -0.2, 1.5], (-1, 0, 0), "poster2")


def _desk(doc: SceneDoc, o: OfficeDesk, rng: np.random.Generator) -> None:
    x0, x1 = o.desk_x
    top = o.desk_height
    cy = o.wall_y + o.desk_depth / 2
    doc.box("desk_top", [x1 - x0, o.desk_depth, 0.03], [0.5 * (x0 + x1), cy, top - 0.015], "desk_top")
    for i, (lx, ly) in enumerate(((x0 + 0.03, o.wall_y + 0.03), (x1 - 0.03, o.wall_y + 0.03),
                                  (x0 + 0.03, o.wall_y + o.desk_depth - 0.03), (x1 - 0.03, o.wall_y + o.desk_depth - 0.03))):
        doc.box(f"desk_leg{i}", [0.04, 0.04, top - 0.03], [lx, ly, (top - 0.03) / 2], "metal")
    # A drawer unit under the desk's left end.
    doc.box("drawers", [0.4, 0.55, 0.6], [x1 - 0.25, cy + 0.05, 0.3], "metal")
    for k in range(3):
        doc.box(f"drawer_handle{k}", [0.12, 0.015, 0.012], [x1 - 0.25, cy + 0.33, 0.12 + 0.19 * k], "bezel")
    # The monitor: dark screen in a thin bezel on a stand.
    mx, my = 0.3 + float(rng.uniform(-0.05, 0.05)), o.wall_y + 0.22
    doc.box("monitor_stand", [0.22, 0.18, 0.012], [mx, my, top + 0.006], "bezel")
    doc.box("monitor_neck", [0.05, 0.03, 0.15], [mx, my, top + 0.085], "bezel")
    doc.box("monitor_bezel", [0.62, 0.03, 0.38], [mx, my + 0.02, top + 0.32], "bezel")
    doc.panel("monitor_screen", 0.59, 0.34, 0.004, [mx, my + 0.037, top + 0.325], (0, 1, 0), "screen")
    doc.box("keyboard", [0.44, 0.14, 0.02], [mx, o.wall_y + 0.55, top + 0.01], "keyboard")
    doc.box("mouse", [0.06, 0.1, 0.03], [mx + 0.32, o.wall_y + 0.55, top + 0.015], "bezel")
    doc.cylinder("mug", 0.04, 0.095, [x0 + 0.12, o.wall_y + 0.2 + float(rng.uniform(0, 0.15)), top + 0.0475], "mug")
    doc.cylinder("pens", 0.035, 0.1, [x0 + 0.25, o.wall_y + 0.12, top + 0.05], "metal")
    doc.box("notebook", [0.21, 0.29, 0.015], [x1 - 0.2, o.wall_y + 0.45, top + 0.0075], "notebook",
            rot_z(float(rng.uniform(-0.4, 0.4))))


def _bookcase(doc: SceneDoc, o: OfficeDesk, rng: np.random.Generator) -> None:
    """A bookcase against the wall: sides, shelves, and books with titled spines facing the room
    (gaps and a leaning book here and there)."""
    x0, x1 = o.shelf_x
    depth, height, n = SHELF
    y0 = o.wall_y
    cx = 0.5 * (x0 + x1)
    doc.box("shelf_back", [x1 - x0, 0.01, height], [cx, y0 + 0.005, height / 2], "shelf")
    for s, x in enumerate((x0, x1)):
        doc.box(f"shelf_side{s}", [0.02, depth, height], [x, y0 + depth / 2, height / 2], "shelf")
    pitch = (height - 0.1) / n
    for i in range(n + 1):
        doc.box(f"shelf{i}", [x1 - x0, depth, 0.02], [cx, y0 + depth / 2, 0.05 + i * pitch], "shelf")
    k = 0
    for i in range(n):
        z = 0.06 + i * pitch
        x = x0 + 0.02
        while True:
            w, h = float(rng.uniform(0.018, 0.05)), float(rng.uniform(0.6, 0.92) * (pitch - 0.03))
            if rng.uniform() < 0.06:   # a gap
                x += float(rng.uniform(0.05, 0.15))
            if x + w > x1 - 0.02:
                break
            d = float(rng.uniform(0.15, 0.24))
            name = f"book{k}"
            doc.textured_material(name, textures.book_spine(rng, (max(16, int(w * 800)), int(h * 800))), specular=0.05)
            # The spine faces the room.
            doc.panel(name, w, h, d, [x + w / 2, y0 + depth - 0.02, z + h / 2], (0, 1, 0), name)
            x += w + 0.002
            k += 1
