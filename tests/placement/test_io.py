"""Bodies and motions from files: OBJ/PLY/JSON round trips, refused inputs, BVH retargeting.

Every file is written by the tests themselves (no fetched data): the body by the writers
under test, the BVH files by a small writer below that builds CMU- or Mixamo-style skeletons
from make_body()'s own joint centres (T-pose, Y-up, centimetres unless told otherwise).
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from placement.body import SEGMENT_INDEX, SEGMENTS, Body, BodyError, Motion, Pose, make_body
from placement.bvh import read_bvh
from placement.io import load_body, save_body_obj, save_body_ply, save_joints_json
from placement.retarget import load_bvh

H = 1.75


@pytest.fixture(scope="module")
def body():
    return make_body(H)


def _write_body(tmp_path, body, kind="obj", **kw):
    mesh = tmp_path / f"body.{kind}"
    (save_body_obj if kind == "obj" else save_body_ply)(body, mesh, **kw)
    joints = tmp_path / "joints.json"
    save_joints_json(body, joints)
    return mesh, joints


def _assert_same_body(a: Body, b: Body):
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-9, rtol=0)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.face_segment, b.face_segment)
    np.testing.assert_allclose(a.joints, b.joints, atol=1e-9, rtol=0)
    pose = Pose(np.random.default_rng(0).normal(scale=0.4, size=(len(SEGMENTS), 3)), np.array([0.1, -0.2, 0.05]))
    np.testing.assert_allclose(a.posed_vertices(pose), b.posed_vertices(pose), atol=1e-9, rtol=0)


def _canonical(faces):
    """Each triangle rotated to start at its smallest index: equal rows are the same triangle with
    the same winding (trimesh splits a quad (a b c d) as (a b c)(c d a), a fan as (a b c)(a c d))."""
    f = np.asarray(faces)
    k = np.argmin(f, axis=1)
    return np.stack([f[np.arange(len(f)), (k + i) % 3] for i in range(3)], axis=1)


def _one_line_error(excinfo, *words):
    msg = str(excinfo.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)
    return msg


# ----------------------------------------------------------------------------------------------
# Bodies.
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind, kw", [("obj", {}), ("ply", {}), ("ply", {"binary": True})])
def test_round_trip(tmp_path, body, kind, kw):
    loaded = load_body(*_write_body(tmp_path, body, kind, **kw))
    _assert_same_body(loaded, body)


def test_ply_is_standard_and_label_synonym(tmp_path, body):
    import trimesh

    mesh, joints = _write_body(tmp_path, body, "ply")
    # Another reader agrees on the geometry, so the writer's PLY is the standard format.
    tm = trimesh.load(mesh, process=False)
    np.testing.assert_allclose(tm.vertices, body.vertices, atol=1e-12)
    np.testing.assert_array_equal(tm.faces, body.faces)
    mesh.write_text(mesh.read_text().replace("property uchar segment", "property uchar label"))
    _assert_same_body(load_body(mesh, joints), body)


def test_ply_errors(tmp_path, body):
    mesh, joints = _write_body(tmp_path, body, "ply")
    text = mesh.read_text()
    mesh.write_text(text.replace("property uchar segment", "property uchar part"))
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, "no 'segment' property", "'label'")
    mesh.write_text("\n".join(text.splitlines()[:-20]))                   # the last faces lost
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, "truncated", "'face'")


def test_ply_polygons_and_binary_limits(tmp_path, body):
    """ASCII PLY polygons are fan-triangulated keeping their labels; a binary PLY whose faces
    have different corner counts (trimesh cannot read those) is refused saying what to do."""
    mesh, joints = _write_body(tmp_path, body, "ply")
    header, rest = mesh.read_text().split("end_header\n")
    lines = rest.splitlines()
    V = len(body.vertices)
    rows = lines[V:]
    # Merge the first two faces of each segment into one polygon where they share an edge (a, c).
    out, i, quads = [], 0, 0
    F, S = body.faces.tolist(), body.face_segment.tolist()
    while i < len(F):
        a, b, c = F[i]
        if i + 1 < len(F) and S[i + 1] == S[i] and F[i + 1][0] == a and F[i + 1][1] == c:
            out.append(f"4 {a} {b} {c} {F[i + 1][2]} {S[i]}")
            i, quads = i + 2, quads + 1
        else:
            out.append(rows[i])
            i += 1
    assert quads > 100
    header = header.replace(f"element face {len(F)}", f"element face {len(out)}")
    mesh.write_text(header + "end_header\n" + "\n".join(lines[:V] + out) + "\n")
    _assert_same_body(load_body(mesh, joints), body)        # fan (a b c)(a c d): the original faces
    import struct
    bad = tmp_path / "mixed.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty double x\nproperty double y\n"
                    b"property double z\nelement face 2\nproperty list uchar int vertex_indices\nproperty uchar segment\n"
                    b"end_header\n" + np.zeros((4, 3)).tobytes() + struct.pack("<B4iB", 4, 0, 1, 2, 3, 0)
                    + struct.pack("<B3iB", 3, 0, 1, 2, 1))
    with pytest.raises(BodyError) as e:
        load_body(bad, joints)
    _one_line_error(e, "corner counts", "triangulate on export")


def test_obj_polygons_corner_forms_objects_and_shared_vertices(tmp_path, body):
    """Quads, v/vt/vn forms, negative indices and `o` groups; a vertex shared by two segments is duplicated."""
    F, S = body.faces.tolist(), body.face_segment.tolist()
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in body.vertices.tolist()] + ["vt 0 0", "vn 0 0 1"]
    V = len(body.vertices)
    forms = [lambda k: f"{k + 1}", lambda k: f"{k + 1}/1", lambda k: f"{k + 1}/1/1", lambda k: f"{k - V}//1"]
    last, i, quads = None, 0, 0
    while i < len(F):
        if S[i] != last:
            lines.append(f"o {SEGMENTS[S[i]]}")
            last = S[i]
        a, b, c = F[i]
        nxt = F[i + 1] if i + 1 < len(F) and S[i + 1] == S[i] else None
        if nxt is not None and nxt[0] == a and nxt[1] == c:   # (a b c)(a c d) = fan of the quad (a b c d)
            poly, i, quads = (a, b, c, nxt[2]), i + 2, quads + 1
        else:
            poly, i = (a, b, c), i + 1
        lines.append("f " + " ".join(forms[(i + j) % 4](k) for j, k in enumerate(poly)))
    # One extra chest face reusing three abdomen vertices: the chest needs its own copies.
    abd = F[S.index(SEGMENT_INDEX["abdomen"])]
    lines += ["o chest", "f " + " ".join(str(k + 1) for k in abd)]
    mesh = tmp_path / "poly.obj"
    mesh.write_text("\n".join(lines) + "\n")
    joints = tmp_path / "joints.json"
    save_joints_json(body, joints)
    loaded = load_body(mesh, joints)
    assert quads > 100
    np.testing.assert_array_equal(_canonical(loaded.faces[:-1]), _canonical(body.faces))
    assert len(loaded.vertices) == V + 3 and loaded.face_segment[-1] == SEGMENT_INDEX["chest"]
    np.testing.assert_array_equal(loaded.vertices[loaded.faces[-1]], body.vertices[abd])
    # Each vertex belongs to exactly one segment: every corner carries its face's label.
    np.testing.assert_array_equal(loaded.vertex_segment[loaded.faces], np.repeat(loaded.face_segment[:, None], 3, 1))


def test_unknown_group_is_refused(tmp_path, body):
    mesh, joints = _write_body(tmp_path, body)
    mesh.write_text(mesh.read_text().replace("g head\n", "g skull\n"))
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, "'skull'", "'pelvis'", "'upper_arm_l'")


def test_missing_segment_is_refused(tmp_path, body):
    mesh, joints = _write_body(tmp_path, body)
    out, skip = [], False
    for line in mesh.read_text().splitlines():
        if line.startswith("g "):
            skip = line == "g hand_r"
        if not skip:
            out.append(line)
    mesh.write_text("\n".join(out) + "\n")
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, "'hand_r'", "expected one group per segment")


def _transformed(body, f):
    return Body(vertices=f(body.vertices), faces=body.faces, face_segment=body.face_segment, joints=f(body.joints))


@pytest.mark.parametrize("transform, words", [
    (lambda p: p * 10.0, ("17.5", "metres")),                              # 17 m tall
    (lambda p: p * 1000.0, ("1.75e+03", "millimetres")),                   # millimetres
    (lambda p: p @ Rotation.from_euler("x", 90, degrees=True).as_matrix().T, ("lying down", "+Z up")),
])
def test_wrong_units_and_orientation_are_refused(tmp_path, body, transform, words):
    mesh, joints = _write_body(tmp_path, _transformed(body, transform))
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, *words)


@pytest.mark.parametrize("vertex, words", [
    ([1e30, 0.0, 0.0], ("far off the body", "1e+30")),
    ([np.nan, 0.0, 1.0], ("not finite", "nan")),
])
def test_a_stray_or_non_finite_vertex_is_named_not_taken_for_a_body_lying_down(tmp_path, body, vertex, words):
    v = body.vertices.copy()
    v[0] = vertex
    mesh, joints = _write_body(tmp_path, Body(vertices=v, faces=body.faces, face_segment=body.face_segment,
                                              joints=body.joints))
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    assert "lying down" not in _one_line_error(e, "body.obj", *words)


def test_joints_json_errors(tmp_path, body):
    import json

    mesh, joints = _write_body(tmp_path, body)
    data = json.loads(joints.read_text())
    del data["hand_r"]
    joints.write_text(json.dumps(data))
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, "missing joints ['hand_r']", "16 segments")
    data["hand_r"], data["tail"] = [0, 0, 1], [0, 0, 1]
    joints.write_text(json.dumps(data))
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, "unknown names ['tail']")
    # Joints in millimetres next to a mesh in metres.
    save_joints_json(_transformed(body, lambda p: p * 1000.0), joints)
    with pytest.raises(BodyError) as e:
        load_body(mesh, joints)
    _one_line_error(e, "outside the mesh's bounds", "metres")


# ----------------------------------------------------------------------------------------------
# BVH: a writer of synthetic skeletons built from the body's own joint centres.
# ----------------------------------------------------------------------------------------------

def _skeleton(body, style="cmu"):
    """[(name, parent, position in our frame (m), channel order)] and end sites [(parent, position)].

    T-pose: the arms straight out along +-X from the shoulders; everything else at the body's
    joint centres, so the fitted scale is exactly the file's unit.
    """
    J = {s: body.joints[i] for i, s in enumerate(SEGMENTS)}
    up = np.array([0.0, 0.0, 1.0])
    pts, ends = [], []
    pre = "mixamorig:" if style == "mixamo" else ""
    rot = "Zrotation Yrotation Xrotation" if style == "cmu" else "Zrotation Xrotation Yrotation"

    def add(name, parent, p):
        pts.append((pre + name, None if parent is None else pre + parent, np.asarray(p, float), rot))

    add("Hips", None, J["pelvis"])
    if style == "cmu":
        add("LowerBack", "Hips", J["pelvis"])          # CMU's LowerBack sits on the hips (zero offset)
        add("Spine", "LowerBack", J["abdomen"])
        add("Spine1", "Spine", J["chest"])
        add("Neck", "Spine1", J["head"])
        add("Neck1", "Neck", J["head"] + 0.03 * H * up)
        add("Head", "Neck1", J["head"] + 0.06 * H * up)
    else:
        add("Spine", "Hips", J["abdomen"])
        add("Spine1", "Spine", (J["abdomen"] + J["chest"]) / 2)
        add("Spine2", "Spine1", J["chest"])
        add("Neck", "Spine2", J["head"])
        add("Head", "Neck", J["head"] + 0.06 * H * up)
        add("HeadTop_End", "Head", (0, 0, H))
    ends.append((pre + "HeadTop_End", (0, 0, H + 0.01)) if style == "mixamo" else ("Head", (0, 0, H)))
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        c = side[0].lower()
        sh = J[f"upper_arm_{c}"]
        ex = np.array([sign, 0.0, 0.0])
        l_ua = np.linalg.norm(J[f"forearm_{c}"] - sh)
        l_fa = np.linalg.norm(J[f"hand_{c}"] - J[f"forearm_{c}"])
        wr = sh + (l_ua + l_fa) * ex
        add(f"{side}Shoulder", "Spine1" if style == "cmu" else "Spine2", (sign * 0.03 * H, sh[1], sh[2]))
        add(f"{side}Arm", f"{side}Shoulder", sh)
        add(f"{side}ForeArm", f"{side}Arm", sh + l_ua * ex)
        add(f"{side}Hand", f"{side}ForeArm", wr)
        if style == "cmu":
            add(f"{side}FingerBase", f"{side}Hand", wr + 0.04 * H * ex)
            add(f"{side}HandIndex1", f"{side}FingerBase", wr + 0.07 * H * ex)
            ends.append((f"{side}HandIndex1", wr + 0.1 * H * ex))
            add(f"{c.upper()}Thumb", f"{side}Hand", wr + 0.02 * H * ex + (0, -0.02 * H, 0))
            ends.append((f"{c.upper()}Thumb", wr + 0.04 * H * ex + (0, -0.03 * H, 0)))
            add(f"{c.upper()}HipJoint", "Hips", J["pelvis"])
            leg_parent = f"{c.upper()}HipJoint"
        else:
            add(f"{side}HandIndex1", f"{side}Hand", wr + 0.05 * H * ex)
            add(f"{side}HandIndex2", f"{side}HandIndex1", wr + 0.08 * H * ex)
            ends.append((pre + f"{side}HandIndex2", wr + 0.1 * H * ex))
            leg_parent = "Hips"
        ankle = J[f"foot_{c}"]
        add(f"{side}UpLeg", leg_parent, J[f"thigh_{c}"])
        add(f"{side}Leg", f"{side}UpLeg", J[f"shank_{c}"])
        add(f"{side}Foot", f"{side}Leg", ankle)
        add(f"{side}ToeBase", f"{side}Foot", (ankle[0], -0.09 * H, 0.01 * H))
        if style == "cmu":
            ends.append((f"{side}ToeBase", (ankle[0], -0.12 * H, 0.01 * H)))
        else:
            add(f"{side}Toe_End", f"{side}ToeBase", (ankle[0], -0.12 * H, 0.01 * H))
    return pts, ends


def _write_bvh(path, body, frames, style="cmu", up="y", unit=0.01, frame_time=1 / 30, rename=None):
    """Write a BVH: frames is a list of {joint name (unprefixed): {channel: value}} (file axes, degrees, units)."""
    pts, ends = _skeleton(body, style)
    rename = rename or {}
    to_file = {"y": lambda p: np.array([p[0], p[2], -p[1]]) / unit,          # Y-up, facing +Z, left +X
               "y_back": lambda p: np.array([-p[0], p[2], p[1]]) / unit,     # Y-up, facing -Z, left -X
               "z": lambda p: np.asarray(p) / unit}[up]                       # Z-up, facing -Y, left +X
    pos = {n: to_file(p) for n, _, p, _ in pts}
    kids = {}
    for n, parent, _, _ in pts:
        kids.setdefault(parent, []).append(n)
    pre = "mixamorig:" if style == "mixamo" else ""
    out, columns = ["HIERARCHY"], []

    def write(n, depth):
        ind = "  " * depth
        parent = next(p for m, p, _, _ in pts if m == n)
        off = pos[n] - (pos[parent] if parent else 0)
        rot = next(r for m, _, _, r in pts if m == n).split()
        chans = (["Xposition", "Yposition", "Zposition"] if parent is None else []) + rot
        out.append(f"{ind}{'ROOT' if parent is None else 'JOINT'} {rename.get(n, n)}")
        out.append(f"{ind}{{")
        out.append(f"{ind}  OFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        out.append(f"{ind}  CHANNELS {len(chans)} {' '.join(chans)}")
        columns.extend((n, c) for c in chans)
        for k in kids.get(n, []):
            write(k, depth + 1)
        for parent_name, p in ends:
            if parent_name == n:
                e = to_file(p) - pos[n]
                out.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET {e[0]:.6f} {e[1]:.6f} {e[2]:.6f}",
                            f"{ind}  }}"])
        out.append(f"{ind}}}")

    write(pts[0][0], 0)
    out += ["MOTION", f"Frames: {len(frames)}", f"Frame Time: {frame_time:.8f}"]
    root = pos[pts[0][0]]
    for fr in frames:
        row = []
        for n, c in columns:
            v = fr.get(n[len(pre):], {}).get(c, 0.0)
            if c.endswith("position"):
                v += root["XYZ".index(c[0])]
            row.append(f"{v:.6f}")
        out.append(" ".join(row))
    path.write_text("\n".join(out) + "\n")
    return path


def _standing(up="y", **extra):
    """Arms brought down from the T-pose: the left arm's +X onto -up, the right arm's -X too."""
    arms = {"y": {"LeftArm": {"Zrotation": -90.0}, "RightArm": {"Zrotation": 90.0}},
            "y_back": {"LeftArm": {"Zrotation": 90.0}, "RightArm": {"Zrotation": -90.0}},
            "z": {"LeftArm": {"Yrotation": 90.0}, "RightArm": {"Yrotation": -90.0}}}[up]
    for k, v in extra.items():
        arms[k] = {**arms.get(k, {}), **v}
    return arms


def _check_standing(body, motion):
    assert np.abs(motion.rotvec).max() < 0.15                 # within ~8 degrees of our rest everywhere
    np.testing.assert_allclose(motion.root_m, 0.0, atol=1e-9)
    G = body.segment_transforms(motion)
    posed = body.posed_vertices(motion)
    head = G[:, SEGMENT_INDEX["head"], :3, 3] + body.joints[SEGMENT_INDEX["head"]]
    pelvis = G[:, SEGMENT_INDEX["pelvis"], :3, 3] + body.joints[SEGMENT_INDEX["pelvis"]]
    assert np.all(head[:, 2] > pelvis[:, 2] + 0.3)
    ext = posed.max(axis=1) - posed.min(axis=1)
    assert np.all(np.abs(ext[:, 2] - body.stature_m) < 0.03)  # upright, the body's height (not 100x)
    assert np.all(ext[:, 0] < 0.7)                            # arms hanging, not spread
    assert np.abs(posed - body.vertices).max() < 0.08


@pytest.mark.parametrize("style", ["cmu", "mixamo"])
def test_bvh_standing_still_is_our_rest_pose(tmp_path, body, style):
    path = _write_bvh(tmp_path / "stand.bvh", body, [_standing()] * 5, style=style)
    m = load_bvh(path, body)
    assert len(m) == 5 and m.name == "stand"
    np.testing.assert_allclose(m.t, np.arange(5) / 30, atol=1e-8)
    _check_standing(body, m)
    # Joints that drive no segment are reported, drivers are not.
    pre = "mixamorig:" if style == "mixamo" else ""
    expected = {"LeftShoulder", "RightShoulder", "Neck", "LeftHandIndex1", "LeftToeBase"}
    expected.add("Spine1" if style == "mixamo" else "Spine")
    expected |= {"LThumb", "LHipJoint", "Neck1", "LeftFingerBase"} if style == "cmu" else {"HeadTop_End", "LeftToe_End"}
    assert {pre + n for n in expected} <= set(m.unmapped)
    drivers = {"Hips", "Head", "LeftArm", "LeftForeArm", "LeftHand", "LeftUpLeg", "LeftLeg", "LeftFoot", "RightFoot"}
    drivers |= {"LowerBack", "Spine1"} if style == "cmu" else {"Spine", "Spine2"}
    assert not {pre + n for n in drivers} & set(m.unmapped)
    assert len(m.unmapped) == len(read_bvh(path).names) - 16


@pytest.mark.parametrize("style", ["cmu", "mixamo"])
def test_bvh_elbow_flexion_moves_only_the_left_forearm_and_hand(tmp_path, body, style):
    angles = np.linspace(0.0, 90.0, 7)
    # The upper arm hangs along the parent's -Y; its local +X points down, local +Z forward (+Z
    # in the file), so -Y rotation bends the forearm forward.
    frames = [_standing(LeftForeArm={"Yrotation": -a}) for a in angles]
    m = load_bvh(_write_bvh(tmp_path / "elbow.bvh", body, frames, style=style), body)
    fa, hand = SEGMENT_INDEX["forearm_l"], SEGMENT_INDEX["hand_l"]
    R = Rotation.from_rotvec(m.rotvec[:, fa])
    np.testing.assert_allclose((R[0].inv() * R).magnitude(), np.radians(angles), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(m.rotvec[:, fa], axis=1), np.radians(angles), atol=0.15)
    others = [i for i in range(len(SEGMENTS)) if i != fa]
    np.testing.assert_allclose(m.rotvec[:, others], np.broadcast_to(m.rotvec[:1, others], m.rotvec[:, others].shape),
                               atol=1e-9)
    posed = body.posed_vertices(m)
    moved = np.abs(posed - posed[:1]).max(axis=(0, 2)) > 1e-9
    vs = body.vertex_segment
    assert set(np.unique(vs[moved]).tolist()) == {fa, hand}
    tip = posed[:, vs == hand].mean(axis=1)
    assert tip[-1, 1] < tip[0, 1] - 0.15 and tip[-1, 2] > tip[0, 2] + 0.1   # forward (-Y) and up


@pytest.mark.parametrize("unit", [0.01, 0.0254])          # centimetres, inches
def test_bvh_walking_forward_moves_the_root_along_minus_y(tmp_path, body, unit):
    n = 11
    frames = [_standing(Hips={"Zposition": 1.0 / unit * k / (n - 1)}) for k in range(n)]
    path = _write_bvh(tmp_path / "walk.bvh", body, frames, unit=unit)
    m = load_bvh(path, body)                                  # scale fitted from the skeleton
    expected = np.zeros((n, 3))
    expected[:, 1] = -np.linspace(0.0, 1.0, n)
    np.testing.assert_allclose(m.root_m, expected, atol=1e-5)
    posed = body.posed_vertices(m)
    np.testing.assert_allclose(posed.max(axis=1)[:, 2] - posed.min(axis=1)[:, 2], body.stature_m, atol=0.03)
    np.testing.assert_allclose(load_bvh(path, body, scale=unit).root_m, expected, atol=1e-5)
    # File units taken for metres: a 175 m skeleton is refused.
    with pytest.raises(BodyError) as e:
        load_bvh(path, body, scale=1.0)
    _one_line_error(e, "m tall", "scale=0.01")


def test_bvh_channel_order_is_intrinsic(tmp_path, body):
    a, b, c = 30.0, -50.0, 70.0            # CMU order Zrotation Yrotation Xrotation: R = Rz(a) Ry(b) Rx(c)
    frames = [_standing(LeftArm={"Zrotation": a, "Yrotation": b, "Xrotation": c})]
    m = load_bvh(_write_bvh(tmp_path / "euler.bvh", body, frames), body)
    G = body.segment_transforms(m.pose(0))[SEGMENT_INDEX["upper_arm_l"]]
    sh, el = body.joints[SEGMENT_INDEX["upper_arm_l"]], body.joints[SEGMENT_INDEX["forearm_l"]]
    d = G[:3, :3] @ (el - sh)
    R = Rotation.from_euler("ZYX", [a, b, c], degrees=True).as_matrix()
    C = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_allclose(d / np.linalg.norm(d), C @ R @ [1.0, 0, 0], atol=1e-6)


def test_bvh_z_up(tmp_path, body):
    path = _write_bvh(tmp_path / "zup.bvh", body, [_standing("z")] * 3, up="z")
    with pytest.raises(BodyError) as e:
        load_bvh(path, body, up="y")
    _one_line_error(e, "+Z", "up='z'")
    _check_standing(body, load_bvh(path, body, up="z"))


def test_bvh_facing_minus_z_is_turned_not_mirrored(tmp_path, body):
    """A Y-up skeleton with its left towards -X faces -Z: walking forward (-Z) still moves our root along -Y."""
    n = 5
    frames = [_standing("y_back", Hips={"Zposition": -100.0 * k / (n - 1)}) for k in range(n)]
    m = load_bvh(_write_bvh(tmp_path / "back.bvh", body, frames, up="y_back"), body)
    np.testing.assert_allclose(m.root_m[-1], [0.0, -1.0, 0.0], atol=1e-5)
    _check_standing(body, Motion(m.name, m.t, m.rotvec, 0 * m.root_m))


def test_bvh_biovision_names(tmp_path, body):
    """LeftCollar > LeftShoulder > LeftElbow > LeftWrist, LeftHip > LeftKnee > LeftAnkle."""
    rename = {}
    for side in ("Left", "Right"):
        rename |= {f"{side}Shoulder": f"{side}Collar", f"{side}Arm": f"{side}Shoulder",
                   f"{side}ForeArm": f"{side}Elbow", f"{side}Hand": f"{side}Wrist", f"{side}UpLeg": f"{side}Hip",
                   f"{side}Leg": f"{side}Knee", f"{side}Foot": f"{side}Ankle"}
    m = load_bvh(_write_bvh(tmp_path / "bio.bvh", body, [_standing()] * 2, rename=rename), body)
    _check_standing(body, m)
    assert {"LeftCollar", "RightCollar"} <= set(m.unmapped) and "LeftShoulder" not in m.unmapped


def test_bvh_missing_driver(tmp_path, body):
    path = _write_bvh(tmp_path / "nofoot.bvh", body, [_standing()] * 2, rename={"LeftFoot": "LeftPaw"})
    with pytest.raises(BodyError) as e:
        load_bvh(path, body)
    _one_line_error(e, "['foot_l']", "allow_missing=True", "--allow-missing-joints")
    m = load_bvh(path, body, allow_missing=True)
    assert "LeftPaw" in m.unmapped
    np.testing.assert_allclose(m.rotvec[:, SEGMENT_INDEX["foot_l"]], 0.0, atol=1e-12)


def test_bvh_bad_files_name_the_line(tmp_path, body):
    path = _write_bvh(tmp_path / "ok.bvh", body, [_standing()] * 3)
    lines = path.read_text().splitlines()
    n_motion = lines.index("MOTION") + 1

    def refused(text, *words):
        bad = tmp_path / "bad.bvh"
        bad.write_text(text)
        with pytest.raises(BodyError) as e:
            load_bvh(bad, body)
        return _one_line_error(e, *words)

    refused("\n".join(lines[:-1]) + "\n", "truncated", "'Frames: 3'", f"line {n_motion + 1}")
    row = lines[-1].split()
    refused("\n".join(lines[:-1] + [" ".join(row[:-1])]) + "\n", f"line {len(lines)}", f"expected {len(row)}")
    refused("\n".join(lines[:-1] + [" ".join(row[:-1] + ["abc"])]) + "\n", f"line {len(lines)}", "'abc'")
    k = next(i for i, l in enumerate(lines) if "CHANNELS 3" in l)
    refused("\n".join(lines[:k] + [lines[k].replace("Xrotation", "Wrotation")] + lines[k + 1:]),
            f"line {k + 1}", "'Wrotation'")
    refused("\n".join(lines[:k - 4]) + "\n", "no MOTION")
    refused("\n".join(lines[:k - 4] + ["MOTION", "Frames: 1", "Frame Time: 0.1", "0"]), "ends", "HIERARCHY")
    for missing, words in ((tmp_path / "missing.bvh", ("missing.bvh", "no such file", "BVH")),
                           (tmp_path, ("is a folder", "BVH"))):
        with pytest.raises(BodyError) as e:
            load_bvh(missing, body)
        assert "Errno" not in _one_line_error(e, *words)


# ----------------------------------------------------------------------------------------------
# An imported walk in the placement study: its own travel is not camera motion.
# ----------------------------------------------------------------------------------------------

_TO_FILE = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])   # C^T: our axes -> the file's (Y up, facing +Z)
# Our segment -> the CMU-style joint carrying its local rotation (the joints between carry none).
_CARRIER = {"pelvis": "Hips", "abdomen": "LowerBack", "chest": "Spine1", "head": "Head",
            "thigh_l": "LeftUpLeg", "shank_l": "LeftLeg", "foot_l": "LeftFoot",
            "thigh_r": "RightUpLeg", "shank_r": "RightLeg", "foot_r": "RightFoot"}


def _walk_frames(body, t, travel_m, unit=0.01):
    """BVH frames of the procedural walk's gait along a given travel (distance along -Y, metres,
    per frame): the gait's phase advances with the distance, its amplitude with the speed."""
    from placement.motions import walk

    speed = np.gradient(travel_m, t)
    steady = walk(body, seconds=10.0, rate_hz=1 / (t[1] - t[0]))
    # The gait at the phase reached by walking this far at 1.3 m/s.
    k = np.clip(np.round(travel_m / 1.3 * 30).astype(int), 0, len(steady) - 1)
    amp = np.clip(speed / 1.3, 0.0, 1.0)
    frames = []
    for i in range(len(t)):
        fr = _standing()
        for seg, joint in _CARRIER.items():
            rv = amp[i] * steady.rotvec[k[i], SEGMENT_INDEX[seg]]
            R = _TO_FILE @ Rotation.from_rotvec(rv).as_matrix() @ _TO_FILE.T
            z, y, x = Rotation.from_matrix(R).as_euler("ZYX", degrees=True)
            fr[joint] = {**fr.get(joint, {}), "Zrotation": z, "Yrotation": y, "Xrotation": x}
        root = steady.root_m[k[i]] * [amp[i], 0.0, amp[i]] + [0.0, -travel_m[i], 0.0]   # sway, bounce, travel
        p = _TO_FILE @ root / unit
        fr["Hips"].update({"Xposition": p[0], "Yposition": p[1], "Zposition": p[2]})
        frames.append(fr)
    return frames


def _zone_motion_mm(body, motion):
    from placement.scores import ScoreSettings, ScoreTable, motion_scores
    from placement.zones import zone_masks

    c, n = body.face_frames()
    table = ScoreTable(np.arange(body.face_count), np.array([SEGMENTS[i] for i in body.face_segment]), c, n, {},
                       ScoreSettings(), (), ())
    mm = motion_scores(body, [motion])["motion_mm"]
    return {z: float(mm[m].mean()) for z, m in zone_masks(body, table).items()}


def test_an_imported_walk_that_starts_and_stops_has_its_travel_removed(tmp_path, body):
    """A captured walk starts from standing, speeds up, walks and stops: a straight-line fit of its
    path leaves the travel in as ~hundreds of mm for every zone. With the progression removed the
    figures are those of the same gait walked steadily, and the head moves most, as in the paper."""
    from placement.motions import walk

    dt = 1 / 30
    t = np.arange(0.0, 4.5, dt)
    # Speed: 0 for 0.5 s, up to 1.3 m/s by 1.5 s (smooth), steady, down to 0 by 4.2 s.
    up = np.clip((t - 0.5) / 1.0, 0, 1)
    down = np.clip((4.2 - t) / 1.0, 0, 1)
    speed = 1.3 * np.minimum(up * up * (3 - 2 * up), down * down * (3 - 2 * down))
    travel = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt)])
    m = load_bvh(_write_bvh(tmp_path / "walk.bvh", body, _walk_frames(body, t, travel)), body)
    np.testing.assert_allclose(-m.root_m[:, 1], travel, atol=0.03)           # the travel came through
    imported = _zone_motion_mm(body, m)
    steady_bvh = load_bvh(_write_bvh(tmp_path / "steady.bvh", body, _walk_frames(body, t, 1.3 * t)), body)
    steady = _zone_motion_mm(body, steady_bvh)
    procedural = _zone_motion_mm(body, walk(body))
    for z in ("head", "shoulder", "chest"):
        # The steady imported walk is the procedural one (an independent check of the retargeting) ...
        assert abs(steady[z] - procedural[z]) < 0.15 * procedural[z], (z, steady, procedural)
        # ... and the start-stop walk is on its scale, not hundreds of mm of travel.
        assert imported[z] < 1.5 * steady[z] + 10, (z, imported, steady)
    assert max(imported, key=imported.get) == "head", imported
