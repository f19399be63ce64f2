"""The twin's MJCF scene: a place (a workbench, a kitchen counter, an office desk, each with its
known target), the scenario's props, the wearer's segments (kinematically driven mocap bodies)
and the head mounted on one of them.

:func:`build_scene` assembles the document from one builder per part; the place's builder is
chosen by the place's type (:data:`PLACE_BUILDERS`). Every random choice of a place (textures,
object layout) comes from the scene seed, so one seed gives one place whatever the scenario.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics import HeadGeometry
from kinematics.camera import CameraIntrinsics
from kinematics.mjcf import head_actuators_and_sensors, head_body

from .kitchen import build_kitchen
from .mjcf_doc import SceneDoc, fmt
from .mount import Mount
from .office import build_office
from .places import KitchenCounter, OfficeDesk, Place, Workbench
from .props import CARD_BODY, OCCLUDER_BODY, add_moving_card, add_stool
from .wearer import Wearer
from .workbench import build_workbench

__all__ = ["CARD_BODY", "OCCLUDER_BODY", "HEAD_PREFIX", "WEARER_PREFIX", "TIMESTEP", "PLACE_BUILDERS", "build_scene"]

HEAD_PREFIX = "head/"
WEARER_PREFIX = "wearer/"
TIMESTEP = 0.001

#: One builder per kind of place: (doc, place, rng) adds its lights, materials and geoms.
PLACE_BUILDERS: dict[type, Callable[[SceneDoc, object, np.random.Generator], None]] = {
    Workbench: build_workbench,
    KitchenCounter: build_kitchen,
    OfficeDesk: build_office,
}


def build_scene(head: HeadGeometry, camera_render: CameraIntrinsics, wearer: Wearer, mount: Mount,
                place: Place = Workbench(), seed: int = 0, stool: tuple[float, float, float] | None = None,
                moving_card: bool = False) -> tuple[str, dict]:
    """(MJCF string, assets dict of PNG bytes) of the whole scene.

    ``camera_render`` is the pinhole camera MuJoCo renders (see :mod:`runtime.twin.render`).
    ``seed`` is the scene seed: the place's textures and layout. The wearer's segments are mocap
    bodies named ``wearer/<segment>``, whose frames are the rest-pose body frame: setting a
    mocap pose to a segment's world-from-rest transform puts its mesh where it belongs. The head
    hangs below the mounted segment's body.
    """
    try:
        build_place = PLACE_BUILDERS[type(place)]
    except KeyError:
        raise ValueError(f"no scene builder for a place of type {type(place).__name__}; "
                         f"use one of {[t.__name__ for t in PLACE_BUILDERS]}") from None
    doc = new_document(camera_render)
    build_place(doc, place, np.random.default_rng(seed))
    add_wearer_meshes(doc, wearer)
    if moving_card:
        add_moving_card(doc, seed)
    if stool is not None:
        add_stool(doc, stool)
    add_wearer_bodies(doc, wearer, mount, head, camera_render)
    head_actuators_and_sensors(head, doc.root, prefix=HEAD_PREFIX)
    ET.indent(doc.root)
    return ET.tostring(doc.root, encoding="unicode"), doc.assets


def new_document(camera_render: CameraIntrinsics) -> SceneDoc:
    """The document's root: compiler, physics options, offscreen buffer size, empty sections."""
    root = ET.Element("mujoco", model="wvr_twin")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", timestep=repr(TIMESTEP), gravity="0 0 -9.81", integrator="implicitfast")
    vis = ET.SubElement(root, "visual")
    ET.SubElement(vis, "global", offwidth=str(max(camera_render.width, 640)),
                  offheight=str(max(camera_render.height, 480)))
    ET.SubElement(vis, "quality", offsamples="4")
    asset = ET.SubElement(root, "asset")
    world = ET.SubElement(root, "worldbody")
    return SceneDoc(root, vis, asset, world)


def add_wearer_meshes(doc: SceneDoc, wearer: Wearer) -> None:
    """The skin material and one mesh asset per wearer segment (rest pose, body frame)."""
    ET.SubElement(doc.asset, "material", name="skin", rgba="0.78 0.62 0.52 1", specular="0.1")
    for s, name in enumerate(wearer.segments):
        v, f = wearer.segment_mesh(s)
        ET.SubElement(doc.asset, "mesh", name=f"{WEARER_PREFIX}{name}", vertex=fmt(v), face=" ".join(map(str, f.ravel())))


def add_wearer_bodies(doc: SceneDoc, wearer: Wearer, mount: Mount, head: HeadGeometry,
                      camera_render: CameraIntrinsics) -> None:
    """One mocap body per segment (frames = the rest-pose body frame); the head on the mount."""
    ms = wearer.index(mount.segment)
    for s, name in enumerate(wearer.segments):
        body = ET.SubElement(doc.world, "body", name=f"{WEARER_PREFIX}{name}", mocap="true")
        ET.SubElement(body, "geom", name=f"{WEARER_PREFIX}{name}", type="mesh", mesh=f"{WEARER_PREFIX}{name}",
                      material="skin", contype="0", conaffinity="0", mass="0")
        if s == ms:
            T = mount.T_rest_mount(wearer.joints[ms])
            x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
            body.append(head_body(head, camera_render, prefix=HEAD_PREFIX, pos=T[:3, 3], quat_wxyz=(w, x, y, z)))
