"""Working volume by hierarchical voxel sweeping, against shapes whose swept volume is known.

The estimate counts every voxel the swept set touches, so it exceeds the true volume by about
half a voxel layer over the surface: (estimate - true) / (voxel * surface area) is about 0.5,
and always in (0, 1) here. The 5 % checks use voxels fine enough for that layer to be small.
"""

import math

import numpy as np
import pytest

from design.volume import swept_volume_cm3, swept_volume_m3
from kinematics import forward_kinematics, reference_head
from kinematics.geometry import HeadGeometry

#: A joint range that is as good as fixed (validate() wants lo < hi).
FIXED = (-1e-4, 1e-4)
MARKER = (0.001, 0.001, 0.001)


def _head(parts, ranges_deg) -> HeadGeometry:
    """The reference chain (origins, axes) with other joint ranges and other parts (name, link, centre, size)."""
    d = reference_head().to_dict()
    for name, r in zip(("elevation", "pan", "cyclotorsion"), ranges_deg):
        d["joints"][name]["range_deg"] = list(r)
    d["parts"] = [dict(name=n, link=link, kind="bracket", center_m=list(c), size_m=list(s), mass_kg=0.001)
                  for n, link, c, s in parts]
    return HeadGeometry.from_dict(d)


def _markers(at_elevation_frame):
    """1 mm boxes on the pan and cyclotorsion links (every link needs a mass), placed at a point of the
    elevation frame, inside the shape under test so that they add nothing. With the pan and
    cyclotorsion joints fixed near 0, the pan frame is the elevation frame shifted by the pan origin
    (0, 0, 25) mm, the cyclotorsion frame by a further (15, 0, 20) mm."""
    x, y, z = at_elevation_frame
    return [("pan_marker", "pan", (x, y, z - 0.025), MARKER),
            ("cyclotorsion_marker", "cyclotorsion", (x - 0.015, y, z - 0.045), MARKER)]


def _turned_square_prism(a: float, c: float):
    """An a x c x a box centred on the elevation axis (y), turned through 90 degrees: its square section
    sweeps the full disc of radius a / sqrt(2). Returns the head, true volume and surface area."""
    head = _head([("prism", "elevation", (0.0, 0.0, 0.0), (a, c, a))] + _markers((0.0, 0.0, 0.0)),
                 [(-45.0, 45.0), FIXED, FIXED])
    r = a / math.sqrt(2.0)
    return head, math.pi * r * r * c, 2.0 * math.pi * r * (r + c)


def _rel_excess_per_layer(estimate, volume, area, voxel):
    """(estimate - true) in units of one voxel layer over the surface."""
    return (estimate - volume) / (voxel * area)


def test_turned_square_prism_sweeps_a_cylinder():
    """(a) pi a^2 / 2 * c within 5 % at a 0.4 mm voxel (1/75 of the edge)."""
    head, volume, area = _turned_square_prism(0.030, 0.030)
    estimate = swept_volume_m3(head, voxel_m=0.0004)
    assert estimate == pytest.approx(volume, rel=0.05)
    assert 0.0 < _rel_excess_per_layer(estimate, volume, area, 0.0004) < 1.0


@pytest.mark.parametrize("voxel", [0.003, 0.002, 0.001])
def test_coarse_voxels_overestimate_by_less_than_one_voxel_layer(voxel):
    head, volume, area = _turned_square_prism(0.030, 0.030)
    assert 0.0 < _rel_excess_per_layer(swept_volume_m3(head, voxel), volume, area, voxel) < 1.0


def test_static_box_gives_its_own_volume():
    """(b) Every joint fixed: a box on the mount (the links' 1 mm markers inside it) is its own volume."""
    size = (0.0203, 0.0307, 0.0401)
    at = (0.005, 0.0, 0.04)  # mount frame; the elevation frame is the mount frame raised 20 mm
    head = _head([("block", "mount", at, size), ("elevation_marker", "elevation", (0.005, 0.0, 0.02), MARKER)]
                 + _markers((0.005, 0.0, 0.02)), [FIXED, FIXED, FIXED])
    estimate = swept_volume_m3(head, voxel_m=0.0003)
    assert estimate == pytest.approx(np.prod(size), rel=0.05)
    area = 2.0 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
    assert 0.0 < _rel_excess_per_layer(estimate, np.prod(size), area, 0.0003) < 1.0


@pytest.mark.parametrize("voxel", [0.001, 0.0005])
def test_thin_blade_sweeps_an_annular_sector(voxel):
    """(c) A blade from radius R1 to R2 (height h along the axis, 1 mm thick) turned through theta:
    the annular sector theta / 2 (R2^2 - R1^2) h, plus half the blade's own thickness at each end."""
    r1, r2, h, t, theta = 0.020, 0.040, 0.020, 0.001, math.radians(90.0)
    head = _head([("blade", "elevation", ((r1 + r2) / 2, 0.0, 0.0), (r2 - r1, h, t))] + _markers((0.03, 0.0, 0.0)),
                 [(0.0, 90.0), FIXED, FIXED])
    volume = theta / 2 * (r2 ** 2 - r1 ** 2) * h + t * (r2 - r1) * h
    area = theta * (r2 ** 2 - r1 ** 2) + theta * (r1 + r2) * h + 2 * (r2 - r1) * h
    estimate = swept_volume_m3(head, voxel)
    assert 0.0 < _rel_excess_per_layer(estimate, volume, area, voxel) < 1.0
    assert estimate == pytest.approx(volume, rel=0.15 if voxel > 0.0007 else 0.08)


@pytest.mark.parametrize("joint", [0, 1, 2])
def test_widening_a_joint_range_never_shrinks_the_volume(joint):
    """(d) On the reference head, widening one joint's range symmetrically, then only at one end.

    Where the true volume barely grows (cyclotorsion past +-45 degrees turns the nearly square
    camera onto itself) the estimate's jitter can lower it by a few per cent (design.volume,
    "Bias, jitter and convergence"); elevation and pan add volume at every step.
    """
    head = reference_head()
    for ends in ([(-h, h) for h in (5, 20, 40, 60, 80)], [(-80, top) for top in (-60, -30, 0, 30, 60, 80)]):
        volumes = []
        for lo, hi in ends:
            lower, upper = head.lower.copy(), head.upper.copy()
            lower[joint], upper[joint] = math.radians(lo), math.radians(hi)
            volumes.append(swept_volume_m3(head.with_joint_ranges(lower, upper)))
        steps = np.diff(volumes)
        if joint < 2:
            assert np.all(steps > 0), volumes
        else:
            assert np.all(steps >= -0.05 * volumes[-1]), volumes
        assert volumes[-1] > volumes[0]


def test_reference_head_volume_between_its_parts_and_its_bounding_sphere():
    """(e) More than the parts' own volumes, less than a sphere holding every part at every posture."""
    head = reference_head()
    volume = swept_volume_m3(head)
    print(f"\nreference head working volume: {volume * 1e6:.1f} cm^3 at the default 3 mm voxel")
    assert swept_volume_cm3(head) == pytest.approx(volume * 1e6)
    # Sphere about the elevation joint's origin (fixed in the mount) through the farthest box corner
    # over a 10-degree posture grid, plus 1 mm for what the grid can miss (a 60 mm arm moves
    # 0.25 mm within 5 degrees of a grid posture).
    centre = np.asarray(head.joints[0].origin_m)
    q = np.stack(np.meshgrid(*[np.linspace(lo, hi, 17) for lo, hi in zip(head.lower, head.upper)], indexing="ij"), -1)
    T = forward_kinematics(head, q.reshape(-1, 3)).T_mount_link
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    radius = 0.0
    for p in head.parts:
        corners = np.asarray(p.center_m) + signs * np.asarray(p.size_m) / 2           # (8, 3) link frame
        if p.link == "mount":
            points = corners
        else:
            Tl = T[:, ["elevation", "pan", "cyclotorsion"].index(p.link)]
            points = np.einsum("nij,kj->nki", Tl[:, :3, :3], corners) + Tl[:, None, :3, 3]
        radius = max(radius, float(np.linalg.norm(points - centre, axis=-1).max()))
    sphere = 4.0 / 3.0 * math.pi * (radius + 0.001) ** 3
    parts = sum(p.volume_m3 for p in head.parts)
    assert parts < volume < sphere
    print(f"parts {parts * 1e6:.1f} cm^3, bounding sphere (r = {radius * 1e3:.1f} mm) {sphere * 1e6:.1f} cm^3")


def test_rejects_a_non_positive_voxel():
    with pytest.raises(ValueError, match="voxel_m"):
        swept_volume_m3(reference_head(), voxel_m=0.0)
