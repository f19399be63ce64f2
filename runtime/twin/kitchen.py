"""The kitchen: a counter run against a wall, as plain as a real one.

A worktop of faintly speckled stone on base cupboards (painted doors, an oven's dark glass),
a tiled splash-back (one block of tiles repeated along the wall: a periodic pattern, the trap
for matching by appearance), wall cupboards, a bright window over the counter's right-hand end
(to a wearer facing the wall), and a few things on the worktop: a kettle, a toaster, a
microwave, jars with printed labels, a packet, a chopping board. The known target is a printed
sheet lying on the worktop.

World frame: metres, z up; the wall's face is the plane y = ``wall_y``, the counter runs along x.
Layout and colours come from the scene seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import textures
from .mjcf_doc import SceneDoc, rot_z
from .printed_target import PrintedTarget


@dataclass(frozen=True)
class KitchenCounter:
    """Where the counter, its window and its target are (world frame, metres)."""

    x_range: tuple[float, float] = (-2.3, 2.1)     # the counter run along x
    wall_y: float = -1.05                          # the wall's face
    depth: float = 0.62                            # worktop depth from the wall
    height: float = 0.91                           # worktop surface
    window_x: tuple[float, float] = (-2.05, -1.2)  # the window over the counter
    window_z: tuple[float, float] = (1.12, 2.05)
    target: PrintedTarget = field(default_factory=lambda: PrintedTarget((-0.75, -0.70, 0.91), yaw=0.06))

    kind = "kitchen"

    @property
    def front_y(self) -> float:
        return self.wall_y + self.depth

    def target_corners(self) -> np.ndarray:
        return self.target.corners()

    def look_point(self) -> np.ndarray:
        return np.asarray(self.target.centre, float)

    def sweep_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Along the worktop, and up the splash-back and back down towards the front edge."""
        return np.array([0.35, 0.0, 0.0]), np.array([0.0, -0.10, 0.12])

    def follow_point(self, x: float) -> np.ndarray:
        x = float(np.clip(x, self.x_range[0] + 0.15, self.x_range[1] - 0.15))
        return np.array([x, self.target.centre[1], self.height])

    def away_point(self) -> np.ndarray:
        """The window's left edge and the wall cupboard beside it (bright: the exposure drops)."""
        return np.array([self.window_x[1] - 0.1, self.wall_y, 0.5 * (self.window_z[0] + self.window_z[1]) - 0.1])


TOP_T = 0.04          # worktop thickness, m
PLINTH = 0.10         # the base cupboards' plinth height, m
SPLASH = 0.55         # splash-back height above the worktop, m
WALL_CUPBOARD = (1.46, 2.16, 0.33)   # bottom, top, depth of the wall cupboards, m
ROOM = (2.5, 1.9, 2.5)  # x half-width beyond the counter, y of the opposite wall, ceiling height


def build_kitchen(doc: SceneDoc, k: KitchenCounter, rng: np.random.Generator) -> None:
    """Add the kitchen's lights, room, counter, splash-back, window, cupboards, things and target."""
    doc.headlight(ambient=(0.14, 0.14, 0.14), diffuse=(0.12, 0.12, 0.12))
    _kitchen_materials(doc, rng)
    _kitchen_lights(doc, k)   # dimmer than daylight: the camera's gain is about 1.5 indoors
    _room(doc, k)
    _base_cupboards(doc, k, rng)
    _splashback(doc, k)
    _window(doc, k)
    _wall_cupboards(doc, k)
    _things_on_the_worktop(doc, k, rng)
    k.target.add_to(doc, "target", "paper", "ink")


def _kitchen_materials(doc: SceneDoc, rng: np.random.Generator) -> None:
    wall = tuple(int(c) for c in rng.integers(205, 225, 3))
    doc.textured_material("wall", textures.paint(rng, wall), specular=0.0, repeat=(1, 1), uniform=True)
    doc.textured_material("floor", textures.tiles(rng, (2, 2), 120, (172, 166, 156), (128, 122, 114), 4, 0.03),
                          specular=0.05, repeat=(1.25, 1.25), uniform=True)
    door = tuple(int(c) for c in rng.choice([(206, 210, 196), (190, 200, 206), (222, 214, 196), (120, 132, 120)]))
    doc.textured_material("door", textures.cupboard_door(rng, door), specular=0.05)
    top = tuple(int(c) for c in rng.choice([(190, 188, 182), (200, 190, 170), (112, 112, 110), (216, 214, 208)]))
    doc.textured_material("worktop", textures.stone(rng, top), specular=0.1, repeat=(0.8, 0.8), uniform=True)
    # One 4 x 4 block of 10 cm tiles, 0.4 m square, repeated along the wall.
    doc.textured_material("tiles", textures.tiles(rng, (4, 4), 48), specular=0.15, repeat=(2.5, 2.5), uniform=True)
    # Daylight: brighter than anything lit in the room.
    doc.textured_material("window", textures.window_view(rng), specular=0.0, emission=1.6)
    doc.textured_material("board", textures.wood(rng, (176, 132, 90)), specular=0.05)
    doc.colour_material("wood", (0.55, 0.42, 0.3), specular=0.05)
    doc.colour_material("paper", (0.93, 0.93, 0.91))
    doc.colour_material("ink", (0.03, 0.03, 0.03))
    doc.colour_material("steel", (0.62, 0.63, 0.64), specular=0.5, shininess=0.6)
    doc.colour_material("dark_glass", (0.05, 0.05, 0.06), specular=0.4, shininess=0.8)
    doc.colour_material("black_plastic", (0.07, 0.07, 0.07), specular=0.2)
    doc.colour_material("frame", (0.9, 0.9, 0.88), specular=0.05)
    doc.colour_material("ceiling", (0.88, 0.88, 0.86))
    doc.colour_material("glass_jar", (0.74, 0.76, 0.72), specular=0.3)
    doc.colour_material("toaster", tuple(c / 255 for c in textures.muted_colour(rng, 90, 210, 0.5)), specular=0.3)
    doc.colour_material("appliance", (0.86, 0.86, 0.84), specular=0.2)


def _kitchen_lights(doc: SceneDoc, k: KitchenCounter) -> None:
    # Daylight in through the window, a ceiling lamp over the room.
    wx = 0.5 * (k.window_x[0] + k.window_x[1])
    doc.light("daylight", (wx, k.wall_y - 0.5, 2.2), (0.45, 0.8, -0.5), (0.34, 0.34, 0.33))
    doc.light("ceiling", (0.0, -0.2, 2.45), (0.1, -0.5, -1.0), (0.36, 0.35, 0.33), specular=(0.1, 0.1, 0.1))


def _room(doc: SceneDoc, k: KitchenCounter) -> None:
    """Floor, ceiling and four walls, the back one with a hole for the window (every wall's
    painted face towards the room)."""
    x0, x1 = k.x_range[0] - ROOM[0] + 2.0, k.x_range[1] + ROOM[0] - 2.0
    ymax, h = ROOM[1], ROOM[2]
    xc, yc, w, d = 0.5 * (x0 + x1), 0.5 * (k.wall_y + ymax), x1 - x0, ymax - k.wall_y
    doc.panel("floor", w, d, 0.02, [xc, yc, 0.0], (0, 0, 1), "floor", up=(0, 1, 0))
    doc.panel("ceiling", w, d, 0.02, [xc, yc, h], (0, 0, -1), "ceiling", up=(0, 1, 0))
    wx0, wx1 = k.window_x
    wz0, wz1 = k.window_z
    for name, xa, xb, za, zb in (("wall_left", x0, wx0, 0, h), ("wall_right", wx1, x1, 0, h),
                                 ("wall_below", wx0, wx1, 0, wz0), ("wall_above", wx0, wx1, wz1, h)):
        doc.panel(name, xb - xa, zb - za, 0.1, [0.5 * (xa + xb), k.wall_y, 0.5 * (za + zb)], (0, 1, 0), "wall")
    doc.panel("wall_side0", d, h, 0.1, [x0, yc, h / 2], (1, 0, 0), "wall")
    doc.panel("wall_side1", d, h, 0.1, [x1, yc, h / 2], (-1, 0, 0), "wall")
    doc.panel("wall_behind", w, h, 0.1, [xc, ymax, h / 2], (0, -1, 0), "wall")


def _base_cupboards(doc: SceneDoc, k: KitchenCounter, rng: np.random.Generator) -> None:
    """Cupboard doors 60 cm wide along the run (one of them an oven), plinth, worktop."""
    x0, x1 = k.x_range
    front = k.front_y - 0.02
    body_h = k.height - TOP_T - PLINTH
    doc.box("plinth", [x1 - x0, 0.02, PLINTH], [0.5 * (x0 + x1), front - 0.06, PLINTH / 2], "black_plastic")
    n = int((x1 - x0) // 0.6)
    oven = int(rng.integers(1, max(2, n - 1)))
    for i in range(n):
        xa = x0 + i * (x1 - x0) / n
        w = (x1 - x0) / n
        cx = xa + w / 2
        if i == oven:
            doc.panel(f"oven{i}", w - 0.006, body_h - 0.006, 0.02, [cx, front + 0.02, PLINTH + body_h / 2], (0, 1, 0),
                      "dark_glass")
            doc.box(f"oven{i}_handle", [w - 0.12, 0.025, 0.02], [cx, front + 0.035, PLINTH + body_h - 0.07], "steel")
            continue
        doc.panel(f"door{i}", w - 0.006, body_h - 0.006, 0.02, [cx, front + 0.02, PLINTH + body_h / 2], (0, 1, 0), "door")
        side = 1 if i % 2 else -1    # handles on the doors' meeting edges
        doc.box(f"door{i}_handle", [0.012, 0.02, 0.12], [cx + side * (w / 2 - 0.05), front + 0.03, PLINTH + body_h - 0.12],
                "steel")
    doc.box("worktop", [x1 - x0, k.depth + 0.02, TOP_T], [0.5 * (x0 + x1), k.wall_y + (k.depth + 0.02) / 2,
                                                           k.height - TOP_T / 2], "worktop")


def _splashback(doc: SceneDoc, k: KitchenCounter) -> None:
    """Tiles from the worktop to the wall cupboards, and up to the window's sill below it."""
    x0, x1 = k.x_range
    wx0, wx1 = k.window_x
    z0, z1 = k.height, k.height + SPLASH
    y = k.wall_y + 0.008
    for name, xa, xb, zb in (("tiles_left", x0, wx0, z1), ("tiles_window", wx0, wx1, k.window_z[0] - 0.04),
                             ("tiles_right", wx1, x1, z1)):
        if xb - xa > 0.01:
            doc.panel(name, xb - xa, zb - z0, 0.008, [0.5 * (xa + xb), y, 0.5 * (z0 + zb)], (0, 1, 0), "tiles")


def _window(doc: SceneDoc, k: KitchenCounter) -> None:
    """A bright view (emissive) set back in the wall, a frame, a mullion and a sill."""
    wx0, wx1 = k.window_x
    wz0, wz1 = k.window_z
    cx, cz, w, h = 0.5 * (wx0 + wx1), 0.5 * (wz0 + wz1), wx1 - wx0, wz1 - wz0
    doc.panel("window_view", w, h, 0.01, [cx, k.wall_y - 0.09, cz], (0, 1, 0), "window")
    f = 0.05
    for name, size, pos in (("frame_bottom", [w, 0.06, f], [cx, k.wall_y - 0.06, wz0 + f / 2]),
                            ("frame_top", [w, 0.06, f], [cx, k.wall_y - 0.06, wz1 - f / 2]),
                            ("frame_left", [f, 0.06, h], [wx0 + f / 2, k.wall_y - 0.06, cz]),
                            ("frame_right", [f, 0.06, h], [wx1 - f / 2, k.wall_y - 0.06, cz]),
                            ("mullion", [0.035, 0.05, h], [cx, k.wall_y - 0.06, cz]),
                            ("transom", [w, 0.05, 0.035], [cx, k.wall_y - 0.06, wz0 + 0.62 * h]),
                            ("sill", [w + 0.08, 0.12, 0.025], [cx, k.wall_y + 0.02, wz0 - 0.0125])):
        doc.box(name, size, pos, "frame")


def _wall_cupboards(doc: SceneDoc, k: KitchenCounter) -> None:
    """Plain doors 50 cm wide on both sides of the window (none in front of it)."""
    zb, zt, d = WALL_CUPBOARD
    for side, (xa, xb) in enumerate(((k.x_range[0], k.window_x[0] - 0.08), (k.window_x[1] + 0.08, k.x_range[1]))):
        if xb - xa < 0.3:
            continue
        doc.box(f"wall_cupboard{side}", [xb - xa, d - 0.02, zt - zb], [0.5 * (xa + xb), k.wall_y + (d - 0.02) / 2,
                                                                       0.5 * (zb + zt)], "frame")
        n = max(1, int(round((xb - xa) / 0.5)))
        for i in range(n):
            w = (xb - xa) / n
            cx = xa + (i + 0.5) * w
            doc.panel(f"wall_door{side}_{i}", w - 0.006, zt - zb - 0.006, 0.02, [cx, k.wall_y + d, 0.5 * (zb + zt)],
                      (0, 1, 0), "door")
            hx = cx + (w / 2 - 0.05) * (1 if i % 2 else -1)
            doc.box(f"wall_door{side}_{i}_handle", [0.012, 0.02, 0.1], [hx, k.wall_y + d + 0.01, zb + 0.1], "steel")


def _free_spots(k: KitchenCounter, rng: np.random.Generator, widths: list[float]) -> list[float]:
    """x positions for things of the given widths along the worktop, apart from each other and
    from the target sheet (a random order along the run)."""
    tx, half = k.target.centre[0], k.target.sheet_size[0] / 2 + 0.08
    spots: list[tuple[float, float]] = [(tx - half, tx + half)]
    xs = []
    for w in widths:
        for _ in range(200):
            x = float(rng.uniform(k.x_range[0] + w / 2 + 0.05, k.x_range[1] - w / 2 - 0.05))
            if all(x + w / 2 + 0.04 < a or x - w / 2 - 0.04 > b for a, b in spots):
                break
        else:
            x = math.nan
        spots.append((x - w / 2, x + w / 2))
        xs.append(x)
    return xs


def _things_on_the_worktop(doc: SceneDoc, k: KitchenCounter, rng: np.random.Generator) -> None:
    """Kettle, toaster, microwave, a row of labelled jars, a packet, a chopping board."""
    n_jars = int(rng.integers(3, 5))
    widths = [0.2, 0.3, 0.5, 0.13 * n_jars, 0.2, 0.42]
    kettle, toaster, microwave, jars, packet, board = _free_spots(k, rng, widths)
    top, back = k.height, k.wall_y
    if math.isfinite(kettle):
        y = back + 0.25
        doc.cylinder("kettle", 0.08, 0.2, [kettle, y, top + 0.11], "steel")
        doc.cylinder("kettle_base", 0.09, 0.02, [kettle, y, top + 0.01], "black_plastic")
        doc.box("kettle_handle", [0.03, 0.04, 0.16], [kettle, y + 0.1, top + 0.12], "black_plastic")
    if math.isfinite(toaster):
        y = back + 0.18
        doc.box("toaster", [0.28, 0.17, 0.19], [toaster, y, top + 0.095], "toaster", rot_z(rng.uniform(-0.1, 0.1)))
        for s in (-1, 1):
            doc.box(f"toaster_slot{s}", [0.2, 0.03, 0.003], [toaster, y + s * 0.04, top + 0.19], "black_plastic")
    if math.isfinite(microwave):
        y = back + 0.2
        doc.box("microwave", [0.48, 0.36, 0.28], [microwave, y, top + 0.14], "appliance")
        doc.box("microwave_door", [0.33, 0.01, 0.2], [microwave - 0.05, y + 0.185, top + 0.14], "dark_glass")
        doc.box("microwave_panel", [0.08, 0.01, 0.2], [microwave + 0.18, y + 0.185, top + 0.14], "black_plastic")
    if math.isfinite(jars):
        for i in range(n_jars):
            x = jars - 0.13 * (n_jars - 1) / 2 + 0.13 * i
            r, h = float(rng.uniform(0.045, 0.058)), float(rng.uniform(0.12, 0.2))
            y = back + 0.12
            doc.cylinder(f"jar{i}", r, h, [x, y, top + h / 2], "glass_jar")
            doc.cylinder(f"jar{i}_lid", r + 0.004, 0.025, [x, y, top + h + 0.0125], "black_plastic")
            name = f"label{i}"
            doc.textured_material(name, textures.label(rng, str(rng.choice(textures.PANTRY))), specular=0.02)
            doc.panel(name, 1.3 * r, 0.55 * h, 0.003, [x, y + r + 0.003, top + 0.45 * h], (0, 1, 0), name)
    if math.isfinite(packet):
        doc.textured_material("packet", textures.carton(rng, word=str(rng.choice(textures.PANTRY))), specular=0.05)
        yaw = float(rng.uniform(-0.15, 0.15))
        normal = rot_z(yaw) @ np.array([0.0, 1.0, 0.0])
        doc.panel("packet", 0.19, 0.28, 0.07, [packet, back + 0.135, top + 0.14], normal, "packet")
    if math.isfinite(board):
        # Leaning against the splash-back, its grain along its length.
        normal = (0.0, math.cos(0.25), math.sin(0.25))
        doc.panel("board", 0.42, 0.3, 0.02, [board, back + 0.07, top + 0.15], normal, "board")
