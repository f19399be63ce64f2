"""Things a scenario adds to a place: the hand-held card and the finger that occludes it (mocap
bodies the twin moves every frame), and a stool to sit on."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from . import textures
from .mjcf_doc import SceneDoc, fmt

CARD_BODY = "object/card"
OCCLUDER_BODY = "object/occluder"

#: The moving card (m): its face (length, width), its thickness, and the occluder's thickness.
MOVING_CARD_SIZE = (0.14, 0.10)
MOVING_CARD_T = 0.003
OCCLUDER_T = 0.012


def add_moving_card(doc: SceneDoc, seed: int) -> None:
    """The textured card and its occluder as mocap bodies (poses: Scenario.T_world_card,
    T_world_occluder). The card's texture has its own generator, so the place stays as it was."""
    doc.assets["card.png"] = textures.clutter(np.random.default_rng(seed + 7919), 256)
    ET.SubElement(doc.asset, "texture", name="card", type="2d", file="card.png")
    ET.SubElement(doc.asset, "material", name="card", texture="card", specular="0.05", texrepeat="1 1")
    body = ET.SubElement(doc.world, "body", name=CARD_BODY, mocap="true")
    ET.SubElement(body, "geom", name="moving_card", type="box",
                  size=fmt([MOVING_CARD_SIZE[0] / 2, MOVING_CARD_SIZE[1] / 2, MOVING_CARD_T / 2]),
                  material="card", contype="0", conaffinity="0", mass="0")
    body = ET.SubElement(doc.world, "body", name=OCCLUDER_BODY, mocap="true")
    ET.SubElement(body, "geom", name="occluder", type="box",
                  size=fmt([MOVING_CARD_SIZE[0] / 8, 0.6 * MOVING_CARD_SIZE[1], OCCLUDER_T / 2]),
                  material="skin", contype="0", conaffinity="0", mass="0")


def add_stool(doc: SceneDoc, stool: tuple[float, float, float], material: str = "wood") -> None:
    """A 40 cm square stool at (x, y) with its seat at height h (m), for sitting down."""
    x, y, h = stool
    ET.SubElement(doc.world, "geom", name="stool", type="box", size=fmt([0.2, 0.2, h / 2]), pos=fmt([x, y, h / 2]),
                  material=material, contype="0", conaffinity="0")
