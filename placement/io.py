"""Bodies and motions from files: labelled meshes (OBJ, PLY), joint centres (JSON), BVH motions.

Everything returned is in the body frame of :mod:`placement.body`: metres, +Z up, the body
facing -Y with its left side towards +X, feet on z = 0. Every reader refuses what it cannot
use with a :class:`~placement.body.BodyError` whose one-line message says what was expected and
how to fix it; nothing is guessed silently.

Body meshes
    * OBJ: one ``g`` group per segment, named exactly as :data:`~placement.body.SEGMENTS`
      (``o`` objects are used instead when the file has no ``g`` line). Polygons are
      fan-triangulated; ``f`` corners may be ``v``, ``v/vt``, ``v/vt/vn`` or ``v//vn``, with
      negative (relative) indices.
    * PLY (ASCII, binary little- or big-endian): a per-face integer property ``segment`` (or,
      as a synonym, ``label``) holding the index into SEGMENTS; the face list property is
      ``vertex_indices`` (or ``vertex_index``).
    * Joint centres: a JSON object ``{"head": [x, y, z], ...}`` naming all 16 segments, metres.

    A vertex used by faces of several segments is duplicated, so each vertex belongs to
    exactly one segment (the body moves its segments rigidly); unused vertices are dropped;
    face order is kept.

Motions
    :func:`load_bvh` reads a BVH file and retargets it onto a :class:`~placement.body.Body`
    (see its docstring for the conventions: axes, scale, the T-pose rest, the root).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .body import PARENT, SEGMENT_INDEX, SEGMENTS, Body, BodyError, Motion

__all__ = [
    "load_body", "load_body_obj", "load_body_ply", "load_joints_json",
    "save_body_obj", "save_body_ply", "save_joints_json",
    "BvhData", "read_bvh", "load_bvh",
]

_AXES = "XYZ"


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


def load_joints_json(path) -> np.ndarray:
    """(16, 3) joint centres, metres, rows in SEGMENTS order, from ``{segment: [x, y, z]}`` JSON."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
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


def load_body_obj(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse a segment-grouped OBJ: (vertices (V, 3) m, faces (F, 3), face_segment (F,)).

    Group names must be segment names; every segment needs a group. Shared vertices are
    duplicated per segment (see the module docstring). :func:`load_body` adds the joints.
    """
    path = Path(path)
    lines = path.read_text().splitlines()
    # Exporters often write one "o" per object and "g" per group; the groups are the labels when
    # present, else the objects.
    use_g = any(line.split()[:1] == ["g"] for line in lines)
    group_kw = "g" if use_g else "o"
    verts: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    face_group: list[str] = []
    group: str | None = None
    for n, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        kw = parts[0]
        if kw == "v":
            try:
                verts.append((float(parts[1]), float(parts[2]), float(parts[3])))
            except (IndexError, ValueError):
                raise BodyError(f"{path.name} line {n}: expected 'v x y z', found {raw.strip()!r}") from None
        elif kw == group_kw:
            if len(parts) > 2:
                raise BodyError(f"{path.name} line {n}: group {' '.join(parts[1:])!r} has several names; "
                                "expected one segment name per group")
            group = parts[1] if len(parts) == 2 else None
        elif kw == "f":
            if group is None:
                raise BodyError(f"{path.name} line {n}: a face outside any group; expected every face under "
                                f"a '{group_kw} <segment>' line naming one of {list(SEGMENTS)}")
            idx = []
            for corner in parts[1:]:
                try:
                    k = int(corner.split("/", 1)[0])
                except ValueError:
                    raise BodyError(f"{path.name} line {n}: cannot read face corner {corner!r}; expected "
                                    "v, v/vt, v/vt/vn or v//vn with integer indices") from None
                # OBJ indices are 1-based; negative ones count back from the last vertex read.
                k = k - 1 if k > 0 else len(verts) + k
                if not 0 <= k < len(verts):
                    raise BodyError(f"{path.name} line {n}: face corner {corner!r} refers to no vertex "
                                    f"({len(verts)} read so far); expected indices 1..{len(verts)} or negative")
                idx.append(k)
            if len(idx) < 3:
                raise BodyError(f"{path.name} line {n}: a face needs at least 3 corners, found {len(idx)}")
            for i in range(1, len(idx) - 1):   # fan triangulation keeps convex polygons' winding
                faces.append((idx[0], idx[i], idx[i + 1]))
                face_group.append(group)
    if not faces:
        raise BodyError(f"{path.name}: no faces; expected a triangle mesh grouped by segment")
    names = list(dict.fromkeys(face_group))
    unknown = [g for g in names if g not in SEGMENT_INDEX]
    if unknown:
        raise BodyError(f"{path.name}: unknown group names {unknown}; expected groups named exactly as the "
                        f"segments {list(SEGMENTS)}")
    missing = [s for s in SEGMENTS if s not in names]
    if missing:
        raise BodyError(f"{path.name}: no group for segments {missing}; expected one group per segment, "
                        f"all of {list(SEGMENTS)}")
    seg = np.array([SEGMENT_INDEX[g] for g in face_group])
    return _labelled_body(np.array(verts, float), np.array(faces, int), seg)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _read_ply(path: Path) -> dict[str, dict[str, object]]:
    """All elements of a PLY file: {element: {property: (N,) array, or list of arrays for lists}}."""
    blob = path.read_bytes()
    end = blob.find(b"end_header")
    if not blob.startswith(b"ply") or end < 0:
        raise BodyError(f"{path.name}: not a PLY file (no 'ply' ... 'end_header' header); expected a PLY mesh")
    header = blob[:end].decode("ascii", errors="replace").splitlines()
    body_start = blob.index(b"\n", end) + 1
    fmt = None
    # (element name, row count, [(property, dtype, dtype of the list count or None)])
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]] = []
    for n, line in enumerate(header, 1):
        p = line.split()
        if not p or p[0] in ("ply", "comment", "obj_info"):
            continue
        try:
            if p[0] == "format":
                fmt = p[1]
            elif p[0] == "element":
                elements.append((p[1], int(p[2]), []))
            elif p[0] == "property" and p[1] == "list":
                elements[-1][2].append((p[4], _PLY_TYPES[p[3]], _PLY_TYPES[p[2]]))
            elif p[0] == "property":
                elements[-1][2].append((p[2], _PLY_TYPES[p[1]], None))
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError):
            raise BodyError(f"{path.name} header line {n}: cannot read {line.strip()!r}; expected PLY 'format', "
                            "'element' or 'property' lines with standard types") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise BodyError(f"{path.name}: PLY format {fmt!r}; expected ascii, binary_little_endian or binary_big_endian")
    out: dict[str, dict[str, object]] = {}
    if fmt == "ascii":
        tokens = blob[body_start:].split()
        pos = 0
        for name, count, props in elements:
            cols: dict[str, list] = {p[0]: [] for p in props}
            try:
                if all(p[2] is None for p in props):
                    # Fixed-width element (vertices): read it as one block.
                    k = len(props)
                    block = np.array(tokens[pos:pos + count * k], dtype=float).reshape(count, k)
                    out[name] = {p[0]: block[:, i].astype(p[1]) for i, p in enumerate(props)}
                    pos += count * k
                    continue
                for _ in range(count):
                    for prop, typ, ctyp in props:
                        if ctyp is None:
                            cols[prop].append(float(tokens[pos]))
                            pos += 1
                        else:
                            m = int(tokens[pos])
                            vals = tokens[pos + 1:pos + 1 + m]
                            if len(vals) != m:
                                raise IndexError
                            cols[prop].append(np.array(vals, dtype=float).astype(typ))
                            pos += 1 + m
            except (IndexError, ValueError):
                raise BodyError(f"{path.name}: the PLY data of element {name!r} is truncated or not numeric; "
                                f"expected {count} rows") from None
            out[name] = {p[0]: (np.array(cols[p[0]]).astype(p[1]) if p[2] is None else cols[p[0]]) for p in props}
        return out
    order = "<" if fmt == "binary_little_endian" else ">"
    data = memoryview(blob)[body_start:]
    pos = 0
    for name, count, props in elements:
        try:
            if all(p[2] is None for p in props):
                dt = np.dtype([(p[0], order + p[1]) for p in props])
                arr = np.frombuffer(data, dt, count, pos)
                pos += dt.itemsize * count
                out[name] = {p[0]: arr[p[0]].astype(p[1]) for p in props}
                continue
            # Lists (face corners): when every row has the first row's list lengths (all
            # triangles, say), the element is a fixed record and reads as one block.
            fixed = _fixed_ply_records(data, pos, count, props, order)
            if fixed is not None:
                out[name], pos = fixed
                continue
            cols = {p[0]: [] for p in props}
            for _ in range(count):
                for prop, typ, ctyp in props:
                    if ctyp is None:
                        dt = np.dtype(order + typ)
                        cols[prop].append(np.frombuffer(data, dt, 1, pos)[0])
                        pos += dt.itemsize
                    else:
                        cdt = np.dtype(order + ctyp)
                        m = int(np.frombuffer(data, cdt, 1, pos)[0])
                        pos += cdt.itemsize
                        dt = np.dtype(order + typ)
                        cols[prop].append(np.frombuffer(data, dt, m, pos).astype(typ))
                        pos += dt.itemsize * m
        except ValueError:
            raise BodyError(f"{path.name}: the binary PLY data ends inside element {name!r}; "
                            f"expected {count} rows") from None
        out[name] = {p[0]: (np.array(cols[p[0]]).astype(p[1]) if p[2] is None else cols[p[0]]) for p in props}
    return out


def _fixed_ply_records(data, pos: int, count: int, props, order: str):
    """A binary PLY element with list properties read as fixed-size records, or None.

    Returns ({property: values}, position after the element) when every row's lists have the
    lengths of the first row's; None when they vary (the caller then reads row by row).
    """
    if count == 0:
        return {prop: ([] if ctyp else np.zeros(0, typ)) for prop, typ, ctyp in props}, pos
    fields, p = [], pos
    for prop, typ, ctyp in props:
        if ctyp is None:
            fields.append((prop, order + typ))
            p += np.dtype(typ).itemsize
        else:
            m = int(np.frombuffer(data, np.dtype(order + ctyp), 1, p)[0])
            fields += [(prop + "#count", order + ctyp), (prop, order + typ, (m,))]
            p += np.dtype(ctyp).itemsize + m * np.dtype(typ).itemsize
    dt = np.dtype(fields)
    if pos + dt.itemsize * count > len(data):
        return None
    arr = np.frombuffer(data, dt, count, pos)
    for prop, typ, ctyp in props:
        if ctyp is not None and np.any(arr[prop + "#count"] != arr.dtype[prop].shape[0]):
            return None
    cols = {prop: (arr[prop].astype(typ) if ctyp is None else list(arr[prop].astype(typ))) for prop, typ, ctyp in props}
    return cols, pos + dt.itemsize * count


def load_body_ply(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse a segment-labelled PLY: (vertices (V, 3) m, faces (F, 3), face_segment (F,)).

    Faces need an integer property ``segment`` (or ``label``): the index into SEGMENTS.
    Polygons are fan-triangulated, each triangle keeping its polygon's label.
    """
    path = Path(path)
    el = _read_ply(path)
    if "vertex" not in el or not {"x", "y", "z"} <= set(el["vertex"]):
        raise BodyError(f"{path.name}: no vertex element with x, y, z; expected a PLY triangle mesh")
    if "face" not in el:
        raise BodyError(f"{path.name}: no face element; expected a PLY triangle mesh")
    vx = el["vertex"]
    vertices = np.column_stack([vx["x"], vx["y"], vx["z"]]).astype(float)
    fe = el["face"]
    key = next((k for k in ("vertex_indices", "vertex_index") if k in fe), None)
    if key is None:
        raise BodyError(f"{path.name}: faces have no 'vertex_indices' list; expected a PLY triangle mesh")
    label_key = next((k for k in ("segment", "label") if k in fe), None)
    if label_key is None:
        raise BodyError(f"{path.name}: faces have no 'segment' property; expected a per-face integer 'segment' "
                        f"(or 'label') indexing {list(SEGMENTS)}")
    labels = np.asarray(fe[label_key])
    if not np.all(labels == np.round(labels)) or labels.min() < 0 or labels.max() >= len(SEGMENTS):
        bad = sorted(set(labels[(labels < 0) | (labels >= len(SEGMENTS)) | (labels != np.round(labels))].tolist()))
        raise BodyError(f"{path.name}: face {label_key} values {bad[:10]} are not segment indices; expected "
                        f"integers 0..{len(SEGMENTS) - 1} indexing {list(SEGMENTS)}")
    labels = labels.astype(int)
    faces, seg = [], []
    for poly, s in zip(fe[key], labels):
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


# ----------------------------------------------------------------------------------------------
# BVH.
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class BvhData:
    """A BVH file as written, before retargeting.

    names : joint names (ROOT and JOINTs, file order: parents before children).
    parents : (J,) parent index, -1 for the root.
    offsets : (J, 3) OFFSET of each joint from its parent, file units and axes.
    channels : per joint, its channel names normalised to e.g. "Xposition", "Zrotation".
    channel_start : (J,) column of each joint's first channel in ``frames``.
    end_sites : (E,) parent joint index of each End Site; end_offsets (E, 3) their OFFSETs.
    frames : (T, C) channel values (positions in file units, angles in degrees).
    frame_time : seconds per frame.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    channel_start: np.ndarray
    end_sites: np.ndarray
    end_offsets: np.ndarray
    frames: np.ndarray
    frame_time: float

    def rest_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Rest-pose positions (all rotations zero, root at its OFFSET): joints (J, 3), end sites (E, 3)."""
        pos = np.zeros((len(self.names), 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        ends = pos[self.end_sites] + self.end_offsets if len(self.end_sites) else np.zeros((0, 3))
        return pos, ends

    def global_rotations(self) -> np.ndarray:
        """(T, J, 3, 3) rotation of every joint's frame relative to the rest pose, by FK.

        Each joint's local rotation is its Euler angles (degrees) applied in its channel order as
        intrinsic rotations, R = R_c1 @ R_c2 @ R_c3 (the BVH convention); rest is identity.
        """
        T = len(self.frames)
        Rg = np.zeros((T, len(self.names), 3, 3))
        for j, p in enumerate(self.parents):
            R = self._local_rotation(j)
            Rg[:, j] = R if p < 0 else Rg[:, p] @ R
        return Rg

    def _local_rotation(self, j: int) -> np.ndarray:
        T = len(self.frames)
        seq = "".join(c[0] for c in self.channels[j] if c.endswith("rotation"))
        if not seq:
            return np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
        cols = [self.channel_start[j] + k for k, c in enumerate(self.channels[j]) if c.endswith("rotation")]
        angles = self.frames[:, cols]
        # Upper-case axes are intrinsic in scipy: from_euler("ZXY", (a, b, c)) = Rz(a) @ Rx(b) @ Ry(c).
        return Rotation.from_euler(seq, angles if len(seq) > 1 else angles[:, 0], degrees=True).as_matrix()

    def positions(self, j: int, Rg: np.ndarray | None = None) -> np.ndarray:
        """(T, 3) world position of joint j over the frames (file units and axes).

        The root's position channels are added to its OFFSET; other joints sit at their OFFSET
        from their parent (position channels on non-root joints, i.e. bone stretch, are ignored:
        the body's segments are rigid).
        """
        Rg = self.global_rotations() if Rg is None else Rg
        chain = []
        k = j
        while k >= 0:
            chain.append(k)
            k = int(self.parents[k])
        root = chain[-1]
        p = np.tile(self.offsets[root], (len(self.frames), 1))
        for k, c in enumerate(self.channels[root]):
            if c.endswith("position"):
                p[:, _AXES.index(c[0])] += self.frames[:, self.channel_start[root] + k]
        for k in reversed(chain[:-1]):
            p = p + Rg[:, self.parents[k]] @ self.offsets[k]
        return p


class _Tokens:
    """Whitespace tokens of the HIERARCHY with their line numbers, for error messages."""

    def __init__(self, name: str, lines: list[str]):
        self.name = name
        self.items = [(tok, n) for n, line in enumerate(lines, 1)
                      for tok in line.replace("{", " { ").replace("}", " } ").split()]
        self.pos = 0

    def peek(self) -> str | None:
        return self.items[self.pos][0] if self.pos < len(self.items) else None

    def line(self) -> int:
        return self.items[min(self.pos, len(self.items) - 1)][1] if self.items else 0

    def next(self, what: str) -> str:
        if self.pos >= len(self.items):
            raise BodyError(f"{self.name}: the file ends after line {self.line()} inside the HIERARCHY; "
                            f"expected {what} (truncated file?)")
        tok = self.items[self.pos][0]
        self.pos += 1
        return tok

    def expect(self, word: str) -> None:
        n = self.line()
        tok = self.next(repr(word))
        if tok.lower() != word.lower():
            raise BodyError(f"{self.name} line {n}: expected {word!r}, found {tok!r}")

    def number(self, what: str) -> float:
        n = self.line()
        tok = self.next(what)
        try:
            return float(tok)
        except ValueError:
            raise BodyError(f"{self.name} line {n}: expected {what} (a number), found {tok!r}") from None


def read_bvh(path) -> BvhData:
    """Parse a BVH file (HIERARCHY and MOTION) without interpreting it; errors name the line."""
    path = Path(path)
    name = path.name
    lines = path.read_text(errors="replace").splitlines()
    motion_line = next((i for i, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise BodyError(f"{name}: no MOTION section; expected a BVH file with HIERARCHY then MOTION")
    tk = _Tokens(name, lines[:motion_line])
    tk.expect("HIERARCHY")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    starts: list[int] = []
    end_sites: list[int] = []
    end_offsets: list[list[float]] = []
    n_channels = 0

    def offset() -> list[float]:
        tk.expect("OFFSET")
        return [tk.number("an OFFSET coordinate") for _ in range(3)]

    def joint(parent: int) -> None:
        nonlocal n_channels
        n = tk.line()
        jname = tk.next("a joint name")
        if jname == "{":
            raise BodyError(f"{name} line {n}: a joint without a name; expected 'JOINT <name>'")
        if jname in names:
            raise BodyError(f"{name} line {n}: joint name {jname!r} used twice; expected unique joint names")
        tk.expect("{")
        j = len(names)
        names.append(jname)
        parents.append(parent)
        offsets.append(offset())
        chans: tuple[str, ...] = ()
        if (tk.peek() or "").upper() == "CHANNELS":
            tk.next("CHANNELS")
            n = tk.line()
            count = tk.number("the channel count")
            if count != int(count) or not 0 <= count <= 6:
                raise BodyError(f"{name} line {n}: {count:g} channels; expected 0 to 6")
            cl = []
            for _ in range(int(count)):
                n = tk.line()
                c = tk.next("a channel name")
                m = re.fullmatch(r"([XYZ])(position|rotation)", c, re.IGNORECASE)
                if not m:
                    raise BodyError(f"{name} line {n}: unknown channel {c!r}; expected Xposition, Yposition, "
                                    "Zposition, Xrotation, Yrotation or Zrotation")
                cl.append(m.group(1).upper() + m.group(2).lower())
            chans = tuple(cl)
        channels.append(chans)
        starts.append(n_channels)
        n_channels += len(chans)
        while True:
            n = tk.line()
            tok = tk.next("'JOINT', 'End Site' or '}'")
            if tok == "}":
                return
            if tok.upper() == "JOINT":
                joint(j)
            elif tok.upper() == "END":
                tk.expect("Site")
                tk.expect("{")
                end_sites.append(j)
                end_offsets.append(offset())
                tk.expect("}")
            else:
                raise BodyError(f"{name} line {n}: expected 'JOINT', 'End Site' or '}}', found {tok!r}")

    tk.expect("ROOT")
    joint(-1)
    if tk.peek() is not None:
        raise BodyError(f"{name} line {tk.line()}: {tk.peek()!r} after the ROOT joint closed; expected one ROOT "
                        "hierarchy then MOTION")

    # MOTION: "Frames: N", "Frame Time: dt", then one line of values per frame.
    rest = [(i + 1, line) for i, line in enumerate(lines) if i > motion_line and line.strip()]
    if len(rest) < 2:
        raise BodyError(f"{name}: the MOTION section ends early (line {len(lines)}); expected 'Frames: N' and "
                        "'Frame Time: seconds'")
    (n1, l1), (n2, l2) = rest[0], rest[1]
    m1 = re.fullmatch(r"\s*Frames\s*:\s*(\d+)\s*", l1, re.IGNORECASE)
    if not m1:
        raise BodyError(f"{name} line {n1}: expected 'Frames: N', found {l1.strip()!r}")
    m2 = re.fullmatch(r"\s*Frame\s+Time\s*:\s*(\S+)\s*", l2, re.IGNORECASE)
    try:
        dt = float(m2.group(1)) if m2 else math.nan
    except ValueError:
        dt = math.nan
    if not dt > 0:
        raise BodyError(f"{name} line {n2}: expected 'Frame Time: seconds' with a positive time, found {l2.strip()!r}")
    n_frames = int(m1.group(1))
    if n_frames == 0:
        raise BodyError(f"{name} line {n1}: 'Frames: 0'; expected at least one frame")
    rows = rest[2:]
    if len(rows) < n_frames:
        raise BodyError(f"{name}: truncated: 'Frames: {n_frames}' at line {n1} but only {len(rows)} frame lines "
                        f"(the file ends at line {len(lines)}); expected one line per frame")
    if len(rows) > n_frames:
        raise BodyError(f"{name} line {rows[n_frames][0]}: more frame lines than 'Frames: {n_frames}' "
                        f"(line {n1}) declares; expected exactly {n_frames}")
    frames = np.zeros((n_frames, n_channels))
    for k, (n, line) in enumerate(rows):
        vals = line.split()
        if len(vals) != n_channels:
            raise BodyError(f"{name} line {n}: frame {k} has {len(vals)} values; expected {n_channels} "
                            "(the total of the CHANNELS counts)")
        try:
            frames[k] = [float(v) for v in vals]
        except ValueError:
            bad = next(v for v in vals if not _is_float(v))
            raise BodyError(f"{name} line {n}: cannot read {bad!r} as a number; "
                            f"expected {n_channels} numbers") from None
    if not np.all(np.isfinite(frames)):
        raise BodyError(f"{name}: the frames contain NaN or infinite values; expected finite numbers")
    return BvhData(
        names=tuple(names), parents=np.array(parents, int), offsets=np.array(offsets, float),
        channels=tuple(channels), channel_start=np.array(starts, int),
        end_sites=np.array(end_sites, int), end_offsets=np.array(end_offsets, float).reshape(-1, 3),
        frames=frames, frame_time=dt,
    )


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


# Joint names of common skeletons, normalised (lower case, namespace and "mixamorig_" prefix
# removed). "{s}" is "left"/"right", "{c}" is "l"/"r". CMU (cgspeed BVH), CMU ASF names,
# Mixamo, and Unity-humanoid style names.
_HIPS = ("hips", "hip", "pelvis")
_SPINE = ("lowerback", "spine", "spine1", "spine2", "spine3", "upperback", "thorax", "chest", "upperchest")
_NECK = ("neck", "neck1", "neck2", "lowerneck", "upperneck")
_LIMBS = {
    "upper_arm": ("{s}arm", "{s}upperarm", "{c}humerus", "{c}upperarm", "{c}_upperarm"),
    "forearm": ("{s}forearm", "{s}lowerarm", "{c}radius", "{c}forearm", "{c}_forearm", "{s}elbow"),
    "hand": ("{s}hand", "{c}hand", "{c}_hand", "{s}wrist"),
    "thigh": ("{s}upleg", "{s}upperleg", "{c}femur", "{c}thigh", "{c}_thigh", "{s}hip"),
    "shank": ("{s}leg", "{s}lowerleg", "{c}tibia", "{c}shin", "{c}_calf", "{s}knee"),
    "foot": ("{s}foot", "{c}foot", "{c}_foot", "{s}ankle"),
}
# Older Biovision-style skeletons (LeftCollar > LeftShoulder > LeftElbow > LeftWrist) call the
# upper arm's joint "shoulder"; CMU and Mixamo use that name for the clavicle. So "{s}shoulder"
# is the upper arm only when a "{s}collar" joint exists.
_COLLAR_UPPER_ARM = ("{s}collar", "{s}shoulder")
#: The next segment down each chain (whose joint the bone points at); hand, foot, head are leaves.
_CHAIN_CHILD = {
    "abdomen": "chest", "chest": "head",
    "upper_arm_l": "forearm_l", "forearm_l": "hand_l", "upper_arm_r": "forearm_r", "forearm_r": "hand_r",
    "thigh_l": "shank_l", "shank_l": "foot_l", "thigh_r": "shank_r", "shank_r": "foot_r",
}


def _normalise(name: str) -> str:
    n = name.rsplit(":", 1)[-1]                      # "mixamorig:Hips", "Character1:Hips"
    n = re.sub(r"^mixamorig\d*_", "", n, flags=re.IGNORECASE)
    return n.lower()


def _find_drivers(bvh: BvhData) -> tuple[dict[str, int], int | None]:
    """Driver joint of each segment that has one, and the neck anchor (joint at our head joint).

    pelvis <- Hips (else the ROOT); abdomen <- the first spine joint above the hips (CMU
    LowerBack, Mixamo Spine); chest <- the last spine joint below the neck (CMU Spine1, Mixamo
    Spine2); head <- Head (else the last neck joint); limbs <- LeftArm, LeftForeArm, LeftHand,
    LeftUpLeg, LeftLeg, LeftFoot and Right* (or the aliases in _LIMBS: CMU ASF, Unity-humanoid
    and Biovision LeftShoulder/LeftElbow/LeftWrist/LeftHip/LeftKnee/LeftAnkle names).
    """
    norm = [_normalise(n) for n in bvh.names]
    find = lambda cands: next((j for c in cands for j, n in enumerate(norm) if n == c), None)  # noqa: E731
    drivers: dict[str, int] = {}
    hips = find(_HIPS)
    drivers["pelvis"] = 0 if hips is None else hips
    necks = [j for j, n in enumerate(norm) if n in _NECK]
    head = find(("head",))
    if head is None and necks:
        head = necks[-1]
    neck_anchor = necks[0] if necks else head
    if head is not None:
        drivers["head"] = head
        # The spine joints on the path from the hips up to the head, bottom first.
        path = _path_up(bvh, int(bvh.parents[head]), drivers["pelvis"])
        spine = [j for j in reversed(path) if norm[j] in _SPINE]
        if spine:
            drivers["abdomen"] = spine[0]
        if len(spine) > 1:
            drivers["chest"] = spine[-1]
    for side, s, c in (("l", "left", "l"), ("r", "right", "r")):
        for seg, templates in _LIMBS.items():
            j = find(tuple(t.format(s=s, c=c) for t in templates))
            if j is None and seg == "upper_arm" and find((_COLLAR_UPPER_ARM[0].format(s=s),)) is not None:
                j = find((_COLLAR_UPPER_ARM[1].format(s=s),))
            if j is not None:
                drivers[f"{seg}_{side}"] = j
    return drivers, neck_anchor


def _path_up(bvh: BvhData, j: int, stop: int) -> list[int]:
    """Joints from j up its parents to (excluding) stop, or to the root: [j, parent, ...]."""
    out = []
    while j >= 0 and j != stop:
        out.append(j)
        j = int(bvh.parents[j])
    return out


def _descendants(bvh: BvhData, j: int) -> list[int]:
    out, frontier = [], [j]
    while frontier:
        k = frontier.pop()
        kids = [c for c, p in enumerate(bvh.parents) if p == k]
        out += kids
        frontier += kids
    return out


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The minimal rotation (3, 3) taking direction a onto direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Opposite directions: half a turn about any axis perpendicular to a.
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(math.pi * perp / np.linalg.norm(perp)).as_matrix()
    return Rotation.from_rotvec(axis / s * math.atan2(s, c)).as_matrix()


def load_bvh(path, body: Body, scale: float | None = None, up: str = "y", allow_missing: bool = False) -> Motion:
    """Read a BVH file and retarget it onto ``body``: a :class:`Motion` (T frames, 16 segments).

    path : a BVH file (any channel orders; Euler angles in degrees, intrinsic in channel order).
    body : the body to drive (its rest pose: standing, arms hanging).
    scale : metres per BVH unit; None fits it to the body: (our neck-joint height minus our
        mean ankle height) / (the BVH Neck height (Head if none) minus its mean LeftFoot/RightFoot
        height), rest poses. Only the root translation uses it (rotations have no units). A
        scale that makes the rest skeleton shorter than 0.5 m or taller than 2.5 m is refused.
    up : "y" (usual BVH: Y up, facing +Z, left towards +X; our = C @ bvh with x = bx,
        y = -bz, z = by) or "z" (Z up, assumed facing -Y with left towards +X already, C = I).
        If the rest skeleton's head is not above its feet along the declared axis, it is refused.
        If its left hip and shoulder are towards -X (the character faces the other way), C also
        turns it half a turn about up, so that the character's forward is our -Y.
    allow_missing : False: a segment with no driver joint in the file is an error naming it.
        True: such segments stay at rest relative to their parents.

    Returns Motion(name = file stem, t (T,) s from Frame Time, rotvec (T, 16, 3) rad,
    root_m (T, 3) m, unmapped = every BVH joint (file spelling, file order) that drives no
    segment: clavicles, extra spine and neck joints, fingers, toes... End Sites carry no
    motion and are not listed. Intermediate joints' rotations still reach the segments below
    them (global rotations are retargeted), so only leaf joints' motion is actually lost.

    Retargeting: BVH rest is usually a T-pose, ours has the arms down, so each segment s with
    driver j is aligned once at rest by A_s, the minimal rotation taking our rest bone
    direction (joint centre to the next joint down the chain; for head, hands and feet, to the
    segment's farthest vertex; pelvis: up) onto C times the driver's rest bone direction (to
    the next driver's joint; for leaves, to its farthest descendant; root: up). Then our global
    rotation is G_s(t) = C Rg_j(t) C^T A_s, and the local rotation G_parent^T G_s. A BVH frame
    in its own rest pose therefore poses our body in that (T-)pose; a BVH of a person standing
    with the arms down gives our rest pose (up to small differences of bone directions).

    Root: the pelvis driver's world position p(t) gives root_m(t) = scale * C (p(t) - p(0)):
    frame 0 puts our pelvis at its rest position (rest height, origin), and later frames move
    it as the BVH root moves. A BVH whose first frame is not standing (e.g. crouched) therefore
    leaves the body's height offset by that difference.
    """
    path = Path(path)
    bvh = read_bvh(path)
    up = up.lower()
    if up not in ("y", "z"):
        raise BodyError(f"up={up!r}; expected 'y' (usual BVH) or 'z'")
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]) if up == "y" else np.eye(3)
    u = np.array([0.0, 1.0, 0.0]) if up == "y" else np.array([0.0, 0.0, 1.0])

    drivers, neck_anchor = _find_drivers(bvh)
    missing = [s for s in SEGMENTS if s not in drivers]
    if missing and not allow_missing:
        raise BodyError(f"{path.name}: no joint drives segments {missing}; expected CMU or Mixamo names (Hips, Spine, "
                        f"Spine1, Neck, Head, LeftArm, LeftForeArm, LeftHand, LeftUpLeg, LeftLeg, LeftFoot, Right...); "
                        f"the file has {list(bvh.names)}; rename them or pass allow_missing=True to keep those at rest")

    rest, ends = bvh.rest_positions()
    points = np.vstack([rest, ends])

    # Up axis: the head must be above the feet along the declared axis (a T-pose's arm span can
    # exceed its height, so the largest extent alone would misjudge).
    feet = [drivers[f] for f in ("foot_l", "foot_r") if f in drivers]
    top = drivers.get("head", neck_anchor)
    if top is not None and feet:
        d = rest[top] - rest[feet].mean(axis=0)
    else:
        d = np.zeros(3)
        k = int(np.argmax(np.ptp(points, axis=0)))
        d[k] = np.ptp(points, axis=0)[k]
    axis = int(np.argmax(np.abs(d)))
    declared = _AXES.index(up.upper())
    if axis != declared or d[axis] <= 0:
        found = ("-" if d[axis] < 0 else "+") + _AXES[axis]
        hint = f"pass up='{_AXES[axis].lower()}'" if d[axis] > 0 and _AXES[axis] in "YZ" else \
            "re-export it Y-up or Z-up"
        raise BodyError(f"{path.name}: the rest skeleton's head is above its feet along {found}, not +{up.upper()} "
                        f"as up={up!r} declares; {hint}")

    # Facing: left towards +X (the BVH convention for both axes). A skeleton with its left side
    # towards -X faces the other way; turn it half a turn about up rather than mirror it.
    lr = [(drivers[f"{s}_l"], drivers[f"{s}_r"]) for s in ("thigh", "upper_arm")
          if f"{s}_l" in drivers and f"{s}_r" in drivers]
    if lr and sum(rest[a, 0] - rest[b, 0] for a, b in lr) < 0:
        C = C @ Rotation.from_rotvec(math.pi * u).as_matrix()

    # Scale: metres per file unit.
    span = np.nan
    if neck_anchor is not None and feet:
        span = float(rest[neck_anchor] @ u - np.mean(rest[feet] @ u))
    if scale is None:
        if not span > 0:
            raise BodyError(f"{path.name}: cannot fit the scale without Neck/Head and LeftFoot/RightFoot joints "
                            "above one another; pass scale= (metres per file unit, e.g. 0.01 for centimetres)")
        ankles = body.joints[[SEGMENT_INDEX["foot_l"], SEGMENT_INDEX["foot_r"]], 2].mean()
        ours = body.joints[SEGMENT_INDEX["head"], 2] - ankles
        scale = float(ours / span)
    height = float(scale * np.ptp(points @ u))
    if not (np.isfinite(height) and 0.5 <= height <= 2.5):
        raise BodyError(f"{path.name}: at scale={scale:g} m per unit the rest skeleton is {height:.3g} m tall; "
                        "expected a person 0.5 to 2.5 m tall: pass scale=0.01 for centimetres, 0.0254 for inches, "
                        "1 for metres, or scale=None to fit the body")

    # Rest alignment A_s of each driven segment (see the docstring).
    vs = body.vertex_segment
    A: dict[str, np.ndarray] = {}
    for s in SEGMENTS:
        if s not in drivers:
            continue
        j = drivers[s]
        i = SEGMENT_INDEX[s]
        if s == "pelvis":
            A[s] = np.eye(3)   # both bones point up
            continue
        child = _CHAIN_CHILD.get(s)
        while child is not None and child not in drivers:   # skip undriven segments (allow_missing)
            child = _CHAIN_CHILD.get(child)
        if child is not None:
            # The bone points at the joint matching our child's joint centre: the next driver, or
            # for the chest the neck. CMU puts Neck on Spine1 (zero offset): then take the next
            # joint up the neck that is apart from it.
            targets = [drivers[child]]
            up_chain = _path_up(bvh, drivers[child], j)
            if child == "head" and bvh.parents[up_chain[-1]] == j:
                targets = up_chain[::-1]
                if neck_anchor in targets:
                    targets = targets[targets.index(neck_anchor):]
            apart = [k for k in targets if np.linalg.norm(rest[k] - rest[j]) > 1e-6 * np.ptp(points)]
            target = apart[0] if apart else targets[-1]
            b_bvh = rest[target] - rest[j]
            b_ours = body.joints[SEGMENT_INDEX[child]] - body.joints[i]
        else:
            # Leaves: towards the farthest point below (fingertip, toe tip, top of the head).
            desc = _descendants(bvh, j)
            below = [rest[k] for k in desc] + [ends[e] for e, p in enumerate(bvh.end_sites) if p == j or p in desc]
            b_bvh = max(below, key=lambda p: np.linalg.norm(p - rest[j])) - rest[j] if below else np.zeros(3)
            v = body.vertices[vs == i]
            b_ours = v[np.argmax(np.linalg.norm(v - body.joints[i], axis=1))] - body.joints[i]
        if np.linalg.norm(b_bvh) < 1e-9 * max(1.0, np.ptp(points)) or np.linalg.norm(b_ours) < 1e-9:
            # No bone to align (a leaf without end site): keep the parent's alignment.
            parent = PARENT[s]
            A[s] = A.get(parent, np.eye(3)) if parent else np.eye(3)
        else:
            A[s] = _rotation_between(b_ours, C @ b_bvh)

    Rg = bvh.global_rotations()
    T = len(bvh.frames)
    G = np.zeros((T, len(SEGMENTS), 3, 3))
    local = np.zeros_like(G)
    for i, s in enumerate(SEGMENTS):
        p = PARENT[s]
        if s in drivers:
            G[:, i] = C @ Rg[:, drivers[s]] @ C.T @ A[s]
        else:
            G[:, i] = G[:, SEGMENT_INDEX[p]] if p else np.eye(3)   # at rest relative to the parent
        local[:, i] = G[:, i] if p is None else np.swapaxes(G[:, SEGMENT_INDEX[p]], -1, -2) @ G[:, i]
    rotvec = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_rotvec().reshape(T, len(SEGMENTS), 3)

    p_root = bvh.positions(drivers.get("pelvis", 0), Rg)
    root_m = scale * (p_root - p_root[0]) @ C.T

    used = set(drivers.values())
    unmapped = tuple(n for j, n in enumerate(bvh.names) if j not in used)
    return Motion(name=path.stem, t=np.arange(T) * bvh.frame_time, rotvec=rotvec, root_m=root_m, unmapped=unmapped)
