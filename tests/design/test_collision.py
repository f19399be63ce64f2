"""Self-collision: the oriented-box SAT test against geometry and against MuJoCo's collider."""

import dataclasses
import math
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from design.collision import (
    collision_grid, collision_pairs, obb_penetration, posed_boxes, posture_grid, rest_penetration, same_link_overlap,
    self_collision_fraction,
)
from kinematics import forward_kinematics, reference_head
from kinematics.mjcf import head_body

I3 = np.eye(3)
HALF = np.full(3, 0.5)  # a unit cube


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


# -- obb_penetration on cases worked out by hand --

@pytest.mark.parametrize("d", [0.0, 0.3, 0.99, 1.0, 1.5, 3.0])
def test_unit_cubes_along_x(d):
    """Two axis-aligned unit cubes d apart: overlap 1 - d (penetration depth, or minus the gap)."""
    assert obb_penetration([0, 0, 0], I3, HALF, [d, 0, 0], I3, HALF) == pytest.approx(1.0 - d)


@pytest.mark.parametrize("d", [0.5, 1.0, 1.2, 1.3, 2.0])
def test_cube_turned_45_degrees_about_z(d):
    """B's vertical edge points at A's face: B reaches sqrt(2)/2 along x, so overlap 1/2 + sqrt(2)/2 - d.

    Beyond contact the gap is exactly the vertex-face distance, so -penetration is the distance.
    """
    pen = obb_penetration([0, 0, 0], I3, HALF, [d, 0, 0], rot("z", 45), HALF)
    assert pen == pytest.approx(0.5 + math.sqrt(0.5) - d)


@pytest.mark.parametrize("d", [1.2, 1.4, 1.5, 2.0])
def test_crossed_ridges_need_the_edge_edge_axis(d):
    """A turned 45 deg about x has a ridge along x on top (at z = sqrt(2)/2); B turned 45 deg about y,
    d above it, a ridge along y below. The ridges cross, and the only axis that sees the gap
    is x cross y = z, which is neither box's face normal: overlap sqrt(2) - d."""
    pen = obb_penetration([0, 0, 0], rot("x", 45), HALF, [0, 0, d], rot("y", 45), HALF)
    assert pen == pytest.approx(math.sqrt(2.0) - d)


def test_parallel_and_nearly_parallel_edges_are_not_spurious_axes():
    """Equal orientations (and within 1e-12 rad of it) give the face-axis answer, with no NaN."""
    for R in (I3, rot("z", 1e-10), rot("xyz", [1e-12, -1e-12, 1e-12])):
        for d in (0.2, 0.9, 1.7):
            assert obb_penetration([0, 0, 0], I3, HALF, [d, 0.1, 0], R, HALF) == pytest.approx(1.0 - d, abs=1e-9)
    # Rotations by exact multiples of 90 degrees carry 6e-17 noise in their entries.
    pen = obb_penetration([0, 0, 0], I3, HALF, [0.6, 0, 0], rot("z", 90) @ rot("x", 180), HALF)
    assert pen == pytest.approx(0.4)


def _distance(cA, RA, hA, cB, RB, hB) -> float:
    """Euclidean distance between two boxes by convex minimisation over points of both."""
    def f(x):
        d = cA + RA @ x[:3] - cB - RB @ x[3:]
        return d @ d, np.concatenate([2 * RA.T @ d, -2 * RB.T @ d])
    bounds = [(-h, h) for h in np.concatenate([hA, hB])]
    res = minimize(f, np.zeros(6), jac=True, bounds=bounds, method="L-BFGS-B", options={"ftol": 1e-15, "gtol": 1e-12})
    return math.sqrt(max(res.fun, 0.0))


def test_random_boxes_against_exact_distance_and_symmetry():
    """Vectorised over a batch: separated boxes have -penetration <= distance (a lower bound), and
    the sign says intersect / apart exactly as the distance does; swapping A and B changes nothing."""
    rng = np.random.default_rng(3)
    n = 300
    cA, cB = rng.normal(size=(n, 3)) * 0.3, rng.normal(size=(n, 3)) * 0.3
    RA, RB = Rotation.random(n, random_state=4).as_matrix(), Rotation.random(n, random_state=5).as_matrix()
    hA, hB = rng.uniform(0.05, 0.5, (n, 3)), rng.uniform(0.05, 0.5, (n, 3))
    pen = obb_penetration(cA, RA, hA, cB, RB, hB)
    assert pen.shape == (n,)
    np.testing.assert_allclose(obb_penetration(cB, RB, hB, cA, RA, hA), pen, atol=1e-12)
    apart = 0
    for k in range(n):
        dist = _distance(cA[k], RA[k], hA[k], cB[k], RB[k], hB[k])
        if abs(pen[k]) < 1e-6:
            continue
        if pen[k] > 0:
            assert dist < 1e-6
        else:
            apart += 1
            assert dist > 1e-6 and -pen[k] <= dist + 1e-6
    assert 50 < apart < n - 50


def test_broadcasting_over_leading_dimensions():
    rng = np.random.default_rng(0)
    cA = rng.normal(size=(4, 5, 3))
    RB = Rotation.random(5, random_state=1).as_matrix()            # (5, 3, 3), broadcasts against (4, 5)
    pen = obb_penetration(cA, I3, HALF, np.zeros(3), RB, np.full(3, 0.3))
    assert pen.shape == (4, 5)
    assert pen[2, 3] == pytest.approx(obb_penetration(cA[2, 3], I3, HALF, np.zeros(3), RB[3], np.full(3, 0.3)))


# -- the head --

def test_posed_boxes_follow_forward_kinematics():
    head = reference_head()
    q = np.array([[0.3, -0.5, 0.9], [0.0, 0.0, 0.0]])
    c, R, half = posed_boxes(head, q)
    assert c.shape == (2, len(head.parts), 3) and R.shape == (2, len(head.parts), 3, 3)
    T = forward_kinematics(head, q[0]).T_mount_link
    for k, p in enumerate(head.parts):
        T_link = np.eye(4) if p.link == "mount" else T[["elevation", "pan", "cyclotorsion"].index(p.link)]
        np.testing.assert_allclose(c[0, k], T_link[:3, :3] @ p.center_m + T_link[:3, 3], atol=1e-15)
        np.testing.assert_allclose(R[0, k], T_link[:3, :3], atol=1e-15)
        np.testing.assert_allclose(half[k], np.array(p.size_m) / 2)
    # At q = 0 every link frame is the mount frame shifted by the joint origins up to it.
    shift = dict(zip(["mount", "elevation", "pan", "cyclotorsion"], np.cumsum([np.zeros(3), *head.origins], axis=0)))
    np.testing.assert_allclose(c[1], [np.add(p.center_m, shift[p.link]) for p in head.parts], atol=1e-15)


def test_collision_pairs_skip_brackets_and_same_link():
    head = reference_head()
    pairs = collision_pairs(head)
    names = [(head.parts[i].name, head.parts[j].name) for i, j in pairs]
    assert all(head.parts[i].kind != "bracket" and head.parts[j].kind != "bracket" for i, j in pairs)
    assert all(head.parts[i].link != head.parts[j].link for i, j in pairs)
    assert ("elevation_servo", "camera_body") in names and len(pairs) == 6  # 4 solid parts on 4 links


def test_reference_head_is_collision_free_at_rest_and_has_no_overlapping_parts():
    head = reference_head()
    assert rest_penetration(head) < 0
    assert same_link_overlap(head) < 0 or same_link_overlap(head) == -math.inf


def test_same_link_overlap_sees_two_parts_on_one_link():
    head = reference_head()
    extra = dataclasses.replace(head.parts[2], name="second_servo", center_m=(-0.006, 0.005, 0.0125))
    overlapping = dataclasses.replace(head, parts=head.parts + (extra,))
    # pan_servo spans y in [-6, 6] mm, the copy [-1, 11] mm: 7 mm of overlap along y.
    assert same_link_overlap(overlapping) == pytest.approx(0.007)
    apart = dataclasses.replace(extra, center_m=(-0.006, 0.015, 0.0125))
    assert same_link_overlap(dataclasses.replace(head, parts=head.parts + (apart,))) == pytest.approx(-0.003)
    assert same_link_overlap(head) == -math.inf  # no link carries two non-bracket parts


def _plain_loop_grid(head, steps):
    """The collision grid the slow way: posture by posture, pair by pair."""
    grid = posture_grid(head, steps)
    out = np.zeros((steps,) * 3, bool)
    for idx in np.ndindex(*out.shape):
        c, R, h = posed_boxes(head, grid[idx])
        out[idx] = any(obb_penetration(c[i], R[i], h[i], c[j], R[j], h[j]) > 0 for i, j in collision_pairs(head))
    return out


def test_posture_grid_spans_the_ranges_with_endpoints():
    head = reference_head()
    g = posture_grid(head, 5)
    assert g.shape == (5, 5, 5, 3)
    np.testing.assert_allclose(g[0, 0, 0], head.lower)
    np.testing.assert_allclose(g[-1, -1, -1], head.upper)
    np.testing.assert_allclose(g[:, 0, 0, 0], np.linspace(head.lower[0], head.upper[0], 5))


def test_reference_fraction_matches_a_plain_loop():
    head = reference_head()
    f = self_collision_fraction(head)
    assert 0.0 <= f <= 1.0
    assert f == _plain_loop_grid(head, 9).mean()


def _camera_hits_a_servo_for_part_of_the_elevation_range():
    """The reference head with its elevation servo moved forward onto the mount's x axis, in front of
    and below the camera: looking down (the lowest elevations on the grid, -80 and -60 deg) drives
    the camera into it at some pan angles."""
    head = reference_head()
    parts = tuple(dataclasses.replace(p, center_m=(0.045, 0.0, -0.005)) if p.name == "elevation_servo" else p
                  for p in head.parts)
    return dataclasses.replace(head, parts=parts).validate()


def test_constructed_collision_fraction_is_partial_and_matches_brute_force():
    head = _camera_hits_a_servo_for_part_of_the_elevation_range()
    grid = collision_grid(head, 9)
    f = self_collision_fraction(head, 9)
    assert 0.0 < f < 1.0
    assert f == _plain_loop_grid(head, 9).mean() == grid.mean()
    # Lowest elevations collide at some pan/cyclotorsion angles, the highest never.
    assert grid[0].any() and not grid[-1].any()
    # An odd step count and a different grid agree with the loop as well.
    assert self_collision_fraction(head, 6) == _plain_loop_grid(head, 6).mean()


# -- against MuJoCo's own collision detection --

def _collision_model(head) -> mujoco.MjModel:
    """The head's MJCF with every non-bracket part geom colliding, parent-child filtering off, no margins."""
    root = ET.Element("mujoco", model="collision_check")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(ET.SubElement(root, "option"), "flag", filterparent="disable")
    ET.SubElement(root, "worldbody").append(head_body(head))
    solid = {p.name for p in head.parts if p.kind != "bracket"}
    for geom in root.iter("geom"):
        if geom.get("name") in solid:
            geom.set("contype", "1")
            geom.set("conaffinity", "1")
            geom.set("margin", "0")
            geom.set("gap", "0")
    return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))


def test_agrees_with_mujoco_on_random_designs_and_postures():
    base = reference_head()
    rng = np.random.default_rng(11)
    hits = misses = 0
    for design in range(25):
        # Part centres moved by a few millimetres: some designs collide at some postures.
        parts = tuple(dataclasses.replace(p, center_m=tuple(np.add(p.center_m, rng.normal(0, 0.004, 3))))
                      for p in base.parts)
        head = dataclasses.replace(base, parts=parts)
        model = _collision_model(head)
        data = mujoco.MjData(model)
        assert [model.joint(i).name for i in range(3)] == ["elevation", "pan", "cyclotorsion"]
        geom_part = {model.geom(g).name: g for g in range(model.ngeom)}
        pairs = collision_pairs(head)
        q = rng.uniform(head.lower, head.upper, (40, 3))
        c, R, h = posed_boxes(head, q)
        for k in range(len(q)):
            data.qpos[:] = q[k]
            mujoco.mj_forward(model, data)
            touching = {frozenset((int(data.contact.geom1[n]), int(data.contact.geom2[n]))) for n in range(data.ncon)}
            for i, j in pairs:
                pen = obb_penetration(c[k, i], R[k, i], h[i], c[k, j], R[k, j], h[j])
                if abs(pen) < 1e-5:
                    continue  # grazing: either answer is right to within rounding
                in_mujoco = frozenset((geom_part[head.parts[i].name], geom_part[head.parts[j].name])) in touching
                assert in_mujoco == (pen > 0), (design, q[k], head.parts[i].name, head.parts[j].name, pen)
                hits += pen > 0
                misses += pen <= 0
    assert hits > 50 and misses > 50  # both answers were exercised
