"""An MJCF document under construction: the ``<mujoco>`` root with its ``<visual>``, ``<asset>``
and ``<worldbody>`` sections, and the PNG bytes the assets name. Scene builders (one per kind
of place, the props, the wearer) each add their part to one :class:`SceneDoc`.

The helpers write attributes in a fixed order, so a document built twice is the same string.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.mjcf import fmt  # the scene builders import it from here too


def quat(R: np.ndarray) -> str:
    """A rotation matrix (3, 3) as MJCF's quaternion, w x y z."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return fmt([w, x, y, z])


def rot_z(yaw: float) -> np.ndarray:
    """(3, 3) rotation about world z by ``yaw`` rad."""
    return Rotation.from_euler("z", yaw).as_matrix()


def facing(normal, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(3, 3) axes of a panel whose front faces ``normal``: z along it, y as near ``up`` as it
    can be, x to the right of someone looking at the front. MuJoCo maps a 2D texture onto a box
    in its local x-y plane, so a box turned this way shows its texture upright, unmirrored, on
    its front (+z) face; its other faces get the texture smeared along one axis."""
    z = np.asarray(normal, float) / np.linalg.norm(normal)
    y = np.asarray(up, float) - z * (z @ np.asarray(up, float))
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


#: A geom that neither collides nor is collided with: scenery only (the wearer is kinematic).
NO_CONTACT = {"contype": "0", "conaffinity": "0"}


@dataclass
class SceneDoc:
    """The sections of one MJCF document and the PNG assets its textures name (file -> bytes)."""

    root: ET.Element
    visual: ET.Element
    asset: ET.Element
    world: ET.Element
    assets: dict[str, bytes] = field(default_factory=dict)

    def png_texture(self, name: str, png: bytes) -> None:
        """A 2D texture ``name`` from PNG bytes (stored as asset file ``<name>.png``)."""
        self.assets[f"{name}.png"] = png
        ET.SubElement(self.asset, "texture", name=name, type="2d", file=f"{name}.png")

    def textured_material(self, name: str, png: bytes, specular: float = 0.05, repeat=(1, 1),
                          uniform: bool = False, shininess: float | None = None, emission: float | None = None) -> str:
        """A texture and a material of the same name; each box face gets the whole texture
        (``repeat`` times) unless ``uniform``, which repeats it per metre instead. ``emission``
        makes it shine by itself (a window's daylight)."""
        self.png_texture(name, png)
        attrs = {"name": name, "texture": name, "specular": repr(float(specular)), "texrepeat": fmt(repeat),
                 "texuniform": "true" if uniform else "false"}
        if shininess is not None:
            attrs["shininess"] = repr(float(shininess))
        if emission is not None:
            attrs["emission"] = repr(float(emission))
        ET.SubElement(self.asset, "material", **attrs)
        return name

    def colour_material(self, name: str, rgb, specular: float = 0.0, emission: float | None = None,
                        shininess: float | None = None, reflectance: float | None = None) -> str:
        """A plain material: ``rgb`` (3,) albedo 0..1."""
        attrs = {"name": name, "rgba": fmt([*rgb, 1.0]), "specular": repr(float(specular))}
        if emission is not None:
            attrs["emission"] = repr(float(emission))
        if shininess is not None:
            attrs["shininess"] = repr(float(shininess))
        if reflectance is not None:
            attrs["reflectance"] = repr(float(reflectance))
        ET.SubElement(self.asset, "material", **attrs)
        return name

    def box(self, name: str, size, pos, material: str, R: np.ndarray | None = None,
            parent: ET.Element | None = None) -> ET.Element:
        """A box geom: ``size`` (3,) full extents along its axes, m; ``pos`` its centre; ``R`` its axes."""
        attrs = {"name": name, "type": "box", "size": fmt(np.asarray(size, float) / 2), "pos": fmt(pos)}
        if R is not None:
            attrs["quat"] = quat(R)
        return ET.SubElement(self.world if parent is None else parent, "geom", **attrs, material=material, **NO_CONTACT)

    def panel(self, name: str, width: float, height: float, thickness: float, front_centre, normal, material: str,
              up=(0.0, 0.0, 1.0)) -> ET.Element:
        """A box showing a texture on its front: ``width`` x ``height`` (m) facing ``normal``,
        ``thickness`` behind its front face, whose centre is ``front_centre``."""
        R = facing(normal, up)
        centre = np.asarray(front_centre, float) - R[:, 2] * thickness / 2
        return self.box(name, [width, height, thickness], centre, material, R)

    def cylinder(self, name: str, radius: float, height: float, pos, material: str,
                 R: np.ndarray | None = None) -> ET.Element:
        """An upright cylinder geom (axis along its z): ``pos`` its centre, m."""
        attrs = {"name": name, "type": "cylinder", "size": fmt([radius, height / 2]), "pos": fmt(pos)}
        if R is not None:
            attrs["quat"] = quat(R)
        return ET.SubElement(self.world, "geom", **attrs, material=material, **NO_CONTACT)

    def light(self, name: str, pos, direction, diffuse, specular=(0.0, 0.0, 0.0), directional: bool = True,
              ambient=None, attenuation=None, cutoff: float | None = None) -> ET.Element:
        attrs = {"name": name, "pos": fmt(pos), "dir": fmt(direction), "directional": "true" if directional else "false",
                 "diffuse": fmt(diffuse), "specular": fmt(specular), "castshadow": "false"}
        if ambient is not None:
            attrs["ambient"] = fmt(ambient)
        if attenuation is not None:
            attrs["attenuation"] = fmt(attenuation)
        if cutoff is not None:
            attrs["cutoff"] = repr(float(cutoff))
        return ET.SubElement(self.world, "light", **attrs)

    def headlight(self, ambient, diffuse) -> None:
        """The light that moves with the rendering camera (a fill light; no specular)."""
        ET.SubElement(self.visual, "headlight", ambient=fmt(ambient), diffuse=fmt(diffuse), specular="0 0 0")
