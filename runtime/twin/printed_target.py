"""A printed target: a black rectangle on a white sheet, lying on a surface or pinned to a wall.
Its four outer corners are the known points of target.toml."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .mjcf_doc import SceneDoc

SHEET_T = 0.0005   # the sheet's thickness, m
PRINT_T = 0.00002  # the printed rectangle's thickness above the sheet, m (toner: its sides must not show)


@dataclass(frozen=True)
class PrintedTarget:
    """centre : (3,) the sheet's centre on the surface it lies on, world, m. yaw : rad about world
    z. upright : False lying face up; True standing on a wall facing +y rotated by ``yaw``.
    sheet_size, rect_size : (width, height) m; the target frame's x runs along the width, z out of
    the printed face."""

    centre: tuple[float, float, float]
    yaw: float = 0.0
    upright: bool = False
    sheet_size: tuple[float, float] = (0.297, 0.210)   # A4, landscape
    rect_size: tuple[float, float] = (0.200, 0.140)

    def R_world_target(self) -> np.ndarray:
        """(3, 3) the target frame's axes in the world (x along the width, z out of the face)."""
        R = Rotation.from_euler("z", self.yaw).as_matrix()
        if self.upright:
            R = R @ Rotation.from_euler("x", -math.pi / 2).as_matrix()   # face +y, x along world x
        return R

    def corners(self) -> np.ndarray:
        """(4, 3) world corners of the black rectangle's printed face, counter-clockwise about
        the face's normal: (-x, -y), (+x, -y), (+x, +y), (-x, +y) in the target frame."""
        w, h = self.rect_size
        local = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
        local = np.column_stack([local, np.full(4, SHEET_T + PRINT_T)])
        return local @ self.R_world_target().T + np.asarray(self.centre)

    def add_to(self, doc: SceneDoc, name: str, white: str, black: str) -> None:
        """The sheet and its rectangle as two thin boxes (materials ``white`` and ``black``)."""
        R = self.R_world_target()
        c, n = np.asarray(self.centre), R[:, 2]
        doc.box(f"{name}_sheet", [*self.sheet_size, SHEET_T], c + n * SHEET_T / 2, white, R)
        doc.box(f"{name}_rect", [*self.rect_size, PRINT_T], c + n * (SHEET_T + PRINT_T / 2), black, R)
