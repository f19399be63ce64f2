"""Bodies from files: labelled meshes (OBJ, PLY, read by trimesh) and joint centres (JSON).

Everything returned is in the body frame of :mod:`placement.body`: metres, +Z up, the body
facing -Y with its left side towards +X, feet on z = 0. Every reader refuses what it cannot
use with a :class:`~placement.body.BodyError` whose one-line message says what was expected and
how to fix it; nothing is guessed silently.

Body meshes (trimesh parses the files; the labels, checks and messages are ours)
    * OBJ: one ``g`` group per segment, named exactly as :data:`~placement.body.SEGMENTS`
      (``o`` objects are used instead when the file has no ``g`` line). Polygons are
      triangulated as trimesh does (a fan, each triangle keeping the polygon's winding);
      ``f`` corners may be ``v``, ``v/vt``, ``v/vt/vn`` or ``v//vn``, with negative
      (relative) indices.
    * PLY (ASCII, binary little- or big-endian): a per-face integer property ``segment`` (or,
      as a synonym, ``label``) holding the index into SEGMENTS; the face list property is
      ``vertex_indices`` (or ``vertex_index``). Polygons are fan-triangulated, each triangle
      keeping its polygon's label. A binary PLY must give every face the same number of corners
      (trimesh's binary reader needs one record size; triangulate on export, or write ASCII).
    * Joint centres: a JSON object ``{"head": [x, y, z], ...}`` naming all 16 segments, metres.

    A vertex used by faces of several segments is duplicated, so each vertex belongs to
    exactly one segment (the body moves its segments rigidly); unused vertices are dropped;
    face order is kept.

Motions: BVH files are read by :mod:`placement.bvh` and retargeted by :mod:`placement.retarget`.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from kinematics.nesting import deeper_than, nesting_message

from .body import SEGMENT_INDEX, SEGMENTS, Body, BodyError

__all__ = [
    "load_body", "load_body_obj", "load_body_ply", "load_joints_json",
    "save_body_obj", "save_body_ply", "save_joints_json",
]

_AXES = "XYZ"   # for messages


# ----------------------------------------------------------------------------------------------
# Body meshes.
# ----------------------------------------------------------------------------------------------

def load_body(mesh_path, joints_path) -> Body:
    """A checked :class:`Body` from a segment-labelled mesh (.obj or .ply) and a joints JSON.

    mesh_path : OBJ with one group per segment, or PLY with a per-face ``segment`` property
        (see the module docstring). Vertices in metres, body frame.
    joints_path : JSON ``{segment: [x, y, z]}`` for all 16 segments, metres, body frame.
    Returns a Body with vertices (V, 3), faces (F, 3), face_segment (F,), joints (16, 3), after
    :meth:`Body.check` (which refuses wrong units, a body lying down, upside down or mirrored).
    """
    mesh_path = Path(mesh_path)
    suffix = mesh_path.suffix.lower()
    if suffix == ".obj":
        vertices, faces, face_segment = load_body_obj(mesh_path)
    elif suffix == ".ply":
        vertices, faces, face_segment = load_body_ply(mesh_path)
    else:
        raise BodyError(f"{mesh_path.name}: unknown mesh format {suffix!r}; expected a segment-labelled .obj or .ply")
    joints = load_joints_json(joints_path)
    _check_vertices(mesh_path.name, vertices)

    # Orientation first: Body.check() tests the height before the orientation, which would
    # report a body lying down as "0.3 m tall"; the longest extent says what is really wrong.
    ext = vertices.max(axis=0) - vertices.min(axis=0)
    longest = int(np.argmax(ext))
    if longest != 2:
        raise BodyError(f"{mesh_path.name}: the mesh is longest along {_AXES[longest]} (extents "
                        f"{np.round(ext, 3).tolist()} along X, Y, Z): the body is lying down or not Z-up; expected "
                        "+Z up, facing -Y, left towards +X (rotate the mesh and joints so the head points to +Z)")
    # Joint centres lie inside the body: outside its bounds means other units or another frame.
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    margin = 0.1 * (hi - lo)
    outside = [s for s, p in zip(SEGMENTS, joints) if np.any(p < lo - margin) or np.any(p > hi + margin)]
    if outside:
        raise BodyError(f"{Path(joints_path).name}: joints {outside} lie outside the mesh's bounds "
                        f"{np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()}; expected the joints in the "
                        "mesh's units (metres) and frame")
    return Body(vertices=vertices, faces=faces, face_segment=face_segment, joints=joints).check()


#: A vertex this many times farther from the mesh's median than the 99th percentile vertex is
#: not on the body (a stray point at 1e30 would otherwise pass for a body lying down).
STRAY_FACTOR = 10.0


def _check_vertices(name: str, vertices: np.ndarray) -> None:
    """Refuse non-finite vertices (V, 3) and stray ones far off the body, naming the first."""
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if bad.size:
        raise BodyError(f"{name}: {bad.size} vertices are not finite numbers (the first is "
                        f"{vertices[bad[0]].tolist()}); expected x, y, z in metres for every vertex")
    d = np.linalg.norm(vertices - np.median(vertices, axis=0), axis=1)
    reach = float(np.percentile(d, 99))
    stray = np.flatnonzero(d > STRAY_FACTOR * reach + 1e-9)
    if stray.size:
        raise BodyError(f"{name}: {stray.size} vertices lie far off the body (the first at "
                        f"{np.array2string(vertices[stray[0]], precision=4)}, {d[stray[0]]:.3g} m from its middle, "
                        f"where 99% lie within {reach:.3g} m); remove them, or give every vertex in metres")


def load_joints_json(path) -> np.ndarray:
    """(16, 3) joint centres, metres, rows in SEGMENTS order, from ``{segment: [x, y, z]}`` JSON."""
    path = Path(path)
    try:
        text = path.read_text()
        line = deeper_than(text, "json")
        if line is not None:
            raise BodyError(nesting_message(path.name, line))
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise BodyError(f"{path.name} line {e.lineno}: not valid JSON ({e.msg}); expected "
                        '{"pelvis": [x, y, z], ...} for the 16 segments') from None
    if not isinstance(data, dict):
        raise BodyError(f"{path.name}: expected a JSON object {{segment: [x, y, z]}}, found a {type(data).__name__}")
    missing = [s for s in SEGMENTS if s not in data]
    extra = sorted(k for k in data if k not in SEGMENT_INDEX)
    if missing or extra:
        parts = ([f"missing joints {missing}"] if missing else []) + ([f"unknown names {extra}"] if extra else [])
        raise BodyError(f"{path.name}: {'; '.join(parts)}; expected exactly the 16 segments {list(SEGMENTS)}")
    joints = np.zeros((len(SEGMENTS), 3))
    for i, s in enumerate(SEGMENTS):
        try:
            p = np.asarray(data[s], dtype=float)
        except (TypeError, ValueError):
            p = np.zeros(0)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise BodyError(f"{path.name}: joint {s!r} is {data[s]!r}; expected [x, y, z], three finite numbers "
                            "in metres")
        joints[i] = p
    return joints


def _labelled_body(vertices: np.ndarray, faces: np.ndarray, face_segment: np.ndarray):
    """Duplicate vertices shared between segments, drop unused ones; keep the face order.

    A vertex keeps its place for the segment of the first face using it; the corners of other
    segments' faces get copies appended after the originals, so a mesh that is already
    segmented comes back with its vertex order unchanged.
    """
    V = len(vertices)
    corner_v = faces.ravel()
    corner_s = np.repeat(face_segment, faces.shape[1])
    owner = np.full(V, -1)
    used, first = np.unique(corner_v, return_index=True)
    owner[used] = corner_s[first]
    # Compact the originals (unused vertices would have no segment to move with).
    keep = owner >= 0
    new_index = np.cumsum(keep) - 1
    n_kept = int(keep.sum())
    new_corner = new_index[corner_v]
    foreign = corner_s != owner[corner_v]
    extra_vertices = np.zeros((0, 3))
    if foreign.any():
        keys = corner_v[foreign].astype(np.int64) * len(SEGMENTS) + corner_s[foreign]
        uniq, first_pos, inverse = np.unique(keys, return_index=True, return_inverse=True)
        # Number the copies in order of first appearance, so the output is deterministic and readable.
        order = np.argsort(first_pos, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        new_corner[foreign] = n_kept + rank[inverse.ravel()]
        extra_vertices = vertices[(uniq // len(SEGMENTS))[order]]
    out_v = np.vstack([vertices[keep], extra_vertices])
    return out_v, new_corner.reshape(faces.shape), face_segment.copy()


def _trimesh_load(path: Path, file_type: str, **kwargs):
    """trimesh's reader of ``path``, its exceptions turned into one-line BodyErrors."""
    import trimesh

    try:
        with open(path, "rb") as f:
            data = f.read()
        return trimesh.load(io.BytesIO(data), file_type=file_type, process=False, **kwargs)
    except OSError as e:
        raise BodyError(f"{path.name}: cannot read ({e.strerror or e}); give a readable {file_type.upper()} file") \
            from None
    except Exception as e:    # trimesh raises whatever its parser meets (ValueError, IndexError, KeyError...)
        raise BodyError(f"{path.name}: not a readable {file_type.upper()} mesh ({type(e).__name__}: "
                        f"{str(e)[:80]}); expected a triangle or polygon mesh") from None


def _obj_labels(path: Path, lines: list[str]) -> tuple[list[str], list[int]]:
    """The group of every triangle, in file order: (group names per triangle, the file line of
    each triangle's face). ``g`` lines label the faces after them (``o`` when the file has none);
    a polygon of n corners gives n - 2 triangles."""
    use_g = any(line.split()[:1] == ["g"] for line in lines)
    group_kw = "g" if use_g else "o"
    labels: list[str] = []
    line_of: list[int] = []
    group: str | None = None
    for n, raw in enumerate(lines, 1):
        parts = raw.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == group_kw:
            if len(parts) > 2:
                raise BodyError(f"{path.name} line {n}: group {' '.join(parts[1:])!r} has several names; "
                                "expected one segment name per group")
            group = parts[1] if len(parts) == 2 else None
        elif parts[0] == "f":
            if group is None:
                raise BodyError(f"{path.name} line {n}: a face outside any group; expected every face under "
                                f"a '{group_kw} <segment>' line naming one of {list(SEGMENTS)}")
            if len(parts) < 4:
                raise BodyError(f"{path.name} line {n}: a face needs at least 3 corners, found {len(parts) - 1}")
            labels += [group] * (len(parts) - 3)
            line_of += [n] * (len(parts) - 3)
    return labels, line_of


def load_body_obj(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a segment-grouped OBJ: (vertices (V, 3) m, faces (F, 3), face_segment (F,)).

    Group names must be segment names; every segment needs a group. Shared vertices are
    duplicated per segment (see the module docstring). :func:`load_body` adds the joints.
    """
    path = Path(path)
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as e:
        raise BodyError(f"{path.name}: cannot read ({e.strerror or e}); give a readable OBJ file") from None
    labels, line_of = _obj_labels(path, lines)
    if not labels:
        raise BodyError(f"{path.name}: no faces; expected a triangle mesh grouped by segment")
    # maintain_order keeps the file's vertices and faces in order (no merging by texture).
    mesh = _trimesh_load(path, "obj", maintain_order=True, group_material=False, skip_materials=True,
                         force="mesh")
    vertices = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces, int).reshape(-1, 3)
    if len(faces) != len(labels):
        raise BodyError(f"{path.name}: trimesh read {len(faces)} triangles but the file's faces make {len(labels)}; "
                        "expected 'f' lines of vertex indices (v, v/vt, v/vt/vn or v//vn)")
    names = list(dict.fromkeys(labels))
    unknown = [g for g in names if g not in SEGMENT_INDEX]
    if unknown:
        raise BodyError(f"{path.name}: unknown group names {unknown}; expected groups named exactly as the "
                        f"segments {list(SEGMENTS)}")
    missing = [s for s in SEGMENTS if s not in names]
    if missing:
        raise BodyError(f"{path.name}: no group for segments {missing}; expected one group per segment, "
                        f"all of {list(SEGMENTS)}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        bad = int(np.flatnonzero((faces < 0).any(1) | (faces >= len(vertices)).any(1))[0])
        raise BodyError(f"{path.name} line {line_of[bad]}: a face corner refers to no vertex ({len(vertices)} "
                        f"vertices); expected indices 1..{len(vertices)} or negative")
    seg = np.array([SEGMENT_INDEX[g] for g in labels])
    return _labelled_body(vertices, faces, seg)


def _ply_column(data, key: str):
    """A PLY property from trimesh's raw element data: (N,) values, or the face lists as an
    (N, k) array (one corner count) or a list of arrays."""
    col = data[key]
    if getattr(col, "dtype", None) is not None and col.dtype.names and "f1" in col.dtype.names:
        return np.asarray(col["f1"])            # binary list records: (count, indices)
    if getattr(col, "dtype", None) is not None and col.dtype == object:
        return [np.asarray(v) for v in col]
    col = np.asarray(col)
    return col.reshape(len(col), -1)[:, 0] if col.ndim == 2 and col.shape[1] == 1 else col


def load_body_ply(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a segment-labelled PLY: (vertices (V, 3) m, faces (F, 3), face_segment (F,)).

    Faces need an integer property ``segment`` (or ``label``): the index into SEGMENTS.
    Polygons are fan-triangulated, each triangle keeping its polygon's label.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(400)
    except OSError as e:
        raise BodyError(f"{path.name}: cannot read ({e.strerror or e}); give a readable PLY file") from None
    if not head.startswith(b"ply") or b"end_header" not in open(path, "rb").read():
        raise BodyError(f"{path.name}: not a PLY file (no 'ply' ... 'end_header' header); expected a PLY mesh")
    binary = b"format binary" in head
    try:
        mesh = _trimesh_load(path, "ply")
    except BodyError as e:
        if binary and "unexpected length" in str(e):
            raise BodyError(f"{path.name}: the binary PLY data is truncated, or its faces have different corner "
                            "counts (the binary reader needs one per file); expected 'face' rows of one size: "
                            "triangulate on export, or write ASCII PLY") from None
        raise
    raw = getattr(mesh, "metadata", {}).get("_ply_raw", {})
    if "vertex" not in raw or not {"x", "y", "z"} <= set(_names(raw["vertex"]["data"])):
        raise BodyError(f"{path.name}: no vertex element with x, y, z; expected a PLY triangle mesh")
    if "face" not in raw:
        raise BodyError(f"{path.name}: no face element; expected a PLY triangle mesh")
    vx, fe = raw["vertex"]["data"], raw["face"]["data"]
    for name in ("vertex", "face"):
        got = len(_ply_column(raw[name]["data"], _names(raw[name]["data"])[0]))
        if got != raw[name]["length"]:
            raise BodyError(f"{path.name}: the PLY data of element {name!r} is truncated: {got} of the "
                            f"{raw[name]['length']} rows the header declares; expected {raw[name]['length']} rows")
    vertices = np.column_stack([_ply_column(vx, c) for c in "xyz"]).astype(float)
    key = next((k for k in ("vertex_indices", "vertex_index") if k in _names(fe)), None)
    if key is None:
        raise BodyError(f"{path.name}: faces have no 'vertex_indices' list; expected a PLY triangle mesh")
    label_key = next((k for k in ("segment", "label") if k in _names(fe)), None)
    if label_key is None:
        raise BodyError(f"{path.name}: faces have no 'segment' property; expected a per-face integer 'segment' "
                        f"(or 'label') indexing {list(SEGMENTS)}")
    labels = np.asarray(_ply_column(fe, label_key))
    if not np.all(labels == np.round(labels)) or labels.min() < 0 or labels.max() >= len(SEGMENTS):
        bad = sorted(set(labels[(labels < 0) | (labels >= len(SEGMENTS)) | (labels != np.round(labels))].tolist()))
        raise BodyError(f"{path.name}: face {label_key} values {bad[:10]} are not segment indices; expected "
                        f"integers 0..{len(SEGMENTS) - 1} indexing {list(SEGMENTS)}")
    labels = labels.astype(int)
    faces, seg = [], []
    for poly, s in zip(_ply_column(fe, key), labels):
        poly = np.asarray(poly, int)
        if len(poly) < 3 or poly.min() < 0 or poly.max() >= len(vertices):
            raise BodyError(f"{path.name}: face {len(faces)} has corners {poly.tolist()}; expected 3 or more "
                            f"indices into the {len(vertices)} vertices")
        for i in range(1, len(poly) - 1):
            faces.append((poly[0], poly[i], poly[i + 1]))
            seg.append(s)
    missing = [SEGMENTS[i] for i in range(len(SEGMENTS)) if i not in set(seg)]
    if missing:
        raise BodyError(f"{path.name}: no faces labelled for segments {missing}; expected faces of all of "
                        f"{list(SEGMENTS)}")
    return _labelled_body(vertices, np.array(faces, int), np.array(seg, int))


def _names(data) -> list[str]:
    return list(data.keys()) if isinstance(data, dict) else list(data.dtype.names or ())


def save_body_obj(body: Body, path) -> None:
    """Write the rest-pose mesh as an OBJ with one ``g`` group per run of same-segment faces.

    Vertices are written to full precision (round trips are exact); the face order is kept,
    so a segment whose faces are not contiguous gets several groups of the same name.
    """
    out = ["# wvr body: metres, +Z up, facing -Y, left towards +X; one group per segment"]
    out += [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(body.vertices, float).tolist()]
    last = None
    for (a, b, c), s in zip(np.asarray(body.faces).tolist(), np.asarray(body.face_segment).tolist()):
        if s != last:
            out.append(f"g {SEGMENTS[s]}")
            last = s
        out.append(f"f {a + 1} {b + 1} {c + 1}")
    Path(path).write_text("\n".join(out) + "\n")


def save_body_ply(body: Body, path, binary: bool = False) -> None:
    """Write the rest-pose mesh as PLY (ASCII, or binary little-endian) with a face ``segment`` property."""
    V = np.asarray(body.vertices, float)
    F = np.asarray(body.faces, int)
    S = np.asarray(body.face_segment, int)
    fmt = "binary_little_endian" if binary else "ascii"
    header = (f"ply\nformat {fmt} 1.0\ncomment wvr body: metres, +Z up, facing -Y; segment indexes "
              f"{' '.join(SEGMENTS)}\nelement vertex {len(V)}\nproperty double x\nproperty double y\n"
              f"property double z\nelement face {len(F)}\nproperty list uchar int vertex_indices\n"
              "property uchar segment\nend_header\n")
    if binary:
        vdt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
        fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("s", "u1")])
        va = np.zeros(len(V), vdt)
        va["x"], va["y"], va["z"] = V.T
        fa = np.zeros(len(F), fdt)
        fa["n"], fa["v"], fa["s"] = 3, F, S
        Path(path).write_bytes(header.encode("ascii") + va.tobytes() + fa.tobytes())
    else:
        lines = [f"{x!r} {y!r} {z!r}" for x, y, z in V.tolist()]
        lines += [f"3 {a} {b} {c} {s}" for (a, b, c), s in zip(F.tolist(), S.tolist())]
        Path(path).write_text(header + "\n".join(lines) + "\n")


def save_joints_json(body: Body, path) -> None:
    """Write the joint centres as ``{segment: [x, y, z]}`` (metres, full precision)."""
    data = {s: [float(c) for c in body.joints[i]] for i, s in enumerate(SEGMENTS)}
    Path(path).write_text(json.dumps(data, indent=1) + "\n")
