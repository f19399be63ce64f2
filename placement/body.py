"""The human body model: 16 rigid segments on a joint tree, posed by forward kinematics.

Body frame: metres, +Z up, the body facing -Y with its left side towards +X, feet on z = 0
(in the rest pose: standing upright, arms hanging, palms facing the thighs).

A :class:`Body` holds a triangle mesh in the rest pose whose every face belongs to one
segment, and each segment's joint centre (the point it rotates about) and parent. A
:class:`Pose` gives each segment a rotation about its joint centre, relative to its parent and
expressed in the rest-pose axes, plus a translation of the root (pelvis); the posed mesh comes
from forward kinematics of the tree: every segment moves rigidly.

:func:`make_body` generates a body in code from stature and a few proportions (segment lengths
and breadths as fractions of stature, after Drillis and Contini's anthropometric table), each
segment a closed, tapered elliptical tube, about 1800 triangles in all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

#: The 16 segments, parents before children.
SEGMENTS: tuple[str, ...] = (
    "pelvis", "abdomen", "chest", "head",
    "upper_arm_l", "forearm_l", "hand_l", "upper_arm_r", "forearm_r", "hand_r",
    "thigh_l", "shank_l", "foot_l", "thigh_r", "shank_r", "foot_r",
)
PARENT: dict[str, str | None] = {
    "pelvis": None, "abdomen": "pelvis", "chest": "abdomen", "head": "chest",
    "upper_arm_l": "chest", "forearm_l": "upper_arm_l", "hand_l": "forearm_l",
    "upper_arm_r": "chest", "forearm_r": "upper_arm_r", "hand_r": "forearm_r",
    "thigh_l": "pelvis", "shank_l": "thigh_l", "foot_l": "shank_l",
    "thigh_r": "pelvis", "shank_r": "thigh_r", "foot_r": "shank_r",
}
#: What each segment's joint centre is, anatomically.
JOINT_OF: dict[str, str] = {
    "head": "neck", "chest": "mid-spine", "abdomen": "lower spine", "pelvis": "root (between the hips)",
    "upper_arm_l": "left shoulder", "forearm_l": "left elbow", "hand_l": "left wrist",
    "upper_arm_r": "right shoulder", "forearm_r": "right elbow", "hand_r": "right wrist",
    "thigh_l": "left hip", "shank_l": "left knee", "foot_l": "left ankle",
    "thigh_r": "right hip", "shank_r": "right knee", "foot_r": "right ankle",
}
SEGMENT_INDEX = {s: i for i, s in enumerate(SEGMENTS)}
PARENT_INDEX = np.array([-1 if PARENT[s] is None else SEGMENT_INDEX[PARENT[s]] for s in SEGMENTS])
#: A face whose height is below this fraction of its longest edge is degenerate (zero area up to
#: rounding): its own cross product gives no reliable normal (:meth:`Body.face_frames`).
DEGENERATE_FACE = 1e-9


class BodyError(ValueError):
    """A body, pose or motion that cannot be used; the message says what was expected."""


@dataclass(frozen=True)
class Pose:
    """Joint rotations of the 16 segments and the root's translation.

    rotvec : (16, 3) rotation vectors (radians) of each segment about its joint centre,
        relative to its parent, axes of the rest pose; row order :data:`SEGMENTS`.
    root_m : (3,) translation of the pelvis from its rest position, body frame, metres.
    """

    rotvec: np.ndarray
    root_m: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def rest(cls) -> "Pose":
        return cls(np.zeros((len(SEGMENTS), 3)), np.zeros(3))

    @classmethod
    def from_dict(cls, rotations: dict[str, tuple[float, float, float]], root_m=(0.0, 0.0, 0.0)) -> "Pose":
        """A pose from ``{segment: rotation vector (rad)}``; unnamed segments stay at rest."""
        rv = np.zeros((len(SEGMENTS), 3))
        for s, v in rotations.items():
            if s not in SEGMENT_INDEX:
                raise BodyError(f"unknown segment {s!r}; segments are {list(SEGMENTS)}")
            rv[SEGMENT_INDEX[s]] = v
        return cls(rv, np.asarray(root_m, float))


@dataclass(frozen=True)
class Motion:
    """Poses over time: the common form of procedural motions and imported BVH files.

    t : (T,) seconds. rotvec : (T, 16, 3). root_m : (T, 3). unmapped : joints of a source
    file that had no segment to drive (reported, never silently dropped).
    """

    name: str
    t: np.ndarray
    rotvec: np.ndarray
    root_m: np.ndarray
    unmapped: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.t)

    def pose(self, i: int) -> Pose:
        return Pose(self.rotvec[i], self.root_m[i])

    def subsample_indices(self, n: int) -> np.ndarray:
        """The frames :meth:`subsample` keeps: at most n, evenly spaced."""
        return np.unique(np.linspace(0, len(self.t) - 1, min(n, len(self.t))).round().astype(int))

    def subsample(self, n: int) -> "Motion":
        """At most n frames, evenly spaced (for scoring over a motion cheaply)."""
        idx = self.subsample_indices(n)
        return Motion(self.name, self.t[idx], self.rotvec[idx], self.root_m[idx], self.unmapped)


@dataclass(frozen=True)
class Body:
    """A segmented body in its rest pose.

    vertices : (V, 3) rest-pose vertices, body frame, metres; each belongs to one segment.
    faces : (F, 3) vertex indices, counter-clockwise seen from outside.
    face_segment : (F,) segment index of each face (into :data:`SEGMENTS`).
    joints : (16, 3) joint centre of each segment, rest pose, metres.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_segment: np.ndarray
    joints: np.ndarray

    @property
    def vertex_segment(self) -> np.ndarray:
        vs = np.full(len(self.vertices), -1)
        vs[self.faces.ravel()] = np.repeat(self.face_segment, 3)
        return vs

    @property
    def stature_m(self) -> float:
        return float(self.vertices[:, 2].max() - self.vertices[:, 2].min())

    @property
    def arm_length_m(self) -> float:
        """Shoulder to fingertip, rest pose (the reach that bounds the handling space)."""
        vs = self.vertex_segment
        hand = self.vertices[vs == SEGMENT_INDEX["hand_l"]]
        sh = self.joints[SEGMENT_INDEX["upper_arm_l"]]
        return float(np.linalg.norm(hand - sh, axis=1).max())

    def segment_transforms(self, pose: Pose | Motion) -> np.ndarray:
        """World-from-rest transforms of every segment: (16, 4, 4), or (T, 16, 4, 4) for a Motion."""
        rotvec = np.asarray(pose.rotvec, float)
        root = np.asarray(pose.root_m, float)
        batch = rotvec.shape[:-2]
        R_local = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(batch + (len(SEGMENTS), 3, 3))
        G = np.zeros(batch + (len(SEGMENTS), 4, 4))
        for i, s in enumerate(SEGMENTS):
            c = self.joints[i]
            L = np.zeros(batch + (4, 4))
            L[..., :3, :3] = R_local[..., i, :, :]
            # Rotation about the joint centre: x -> c + R (x - c).
            L[..., :3, 3] = c - np.einsum("...ij,j->...i", R_local[..., i, :, :], c)
            L[..., 3, 3] = 1.0
            p = PARENT_INDEX[i]
            if p < 0:
                L[..., :3, 3] += root
                G[..., i, :, :] = L
            else:
                G[..., i, :, :] = G[..., p, :, :] @ L
        return G

    def posed_vertices(self, pose: Pose | Motion) -> np.ndarray:
        """(V, 3) vertices in a pose, or (T, V, 3) over a motion."""
        G = self.segment_transforms(pose)
        vs = self.vertex_segment
        Gv = G[..., vs, :, :]
        return np.einsum("...vij,vj->...vi", Gv[..., :3, :3], self.vertices) + Gv[..., :3, 3]

    def mesh(self, pose: Pose | None = None):
        """A trimesh.Trimesh of the body (rest pose, or posed)."""
        import trimesh

        v = self.vertices if pose is None else self.posed_vertices(pose)
        return trimesh.Trimesh(v, self.faces, process=False)

    def face_frames(self, pose: Pose | Motion | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(centroids, unit normals) of every face: (F, 3) each, or (T, F, 3) over a motion.

        A degenerate face (zero area: coincident or collinear vertices, as mesh exports leave)
        has no normal of its own; it takes the area-weighted mean normal of the faces sharing
        a vertex with it, so its camera still sits on the surface. A BodyError names a
        degenerate face whose neighbours give no direction either.
        """
        v = self.vertices if pose is None else self.posed_vertices(pose)
        tri = v[..., self.faces, :]
        n = np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
        norm = np.linalg.norm(n, axis=-1)
        edges2 = np.stack([np.sum((tri[..., k, :] - tri[..., (k + 1) % 3, :]) ** 2, axis=-1) for k in range(3)])
        flat = norm <= DEGENERATE_FACE * edges2.max(axis=0)   # |cross| = twice the area
        if flat.any():
            n, norm = n.copy(), norm.copy()
            for f in np.flatnonzero(flat.reshape(-1, len(self.faces)).any(axis=0)):
                # Unnormalised cross products weight each neighbour by its area.
                shared = np.isin(self.faces, self.faces[f]).any(axis=1)
                m = n[..., shared, :].sum(axis=-2)
                m_norm = np.linalg.norm(m, axis=-1)
                here = flat[..., f]
                if np.any(here & ~(m_norm > 0)):
                    raise BodyError(f"face {f} (vertices {self.faces[f].tolist()}) has zero area and its neighbours "
                                    "give no normal either; remove the degenerate faces from the mesh")
                n[..., f, :] = np.where(here[..., None], m, n[..., f, :])
                norm[..., f] = np.where(here, m_norm, norm[..., f])
        return tri.mean(axis=-2), n / norm[..., None]

    def check(self) -> "Body":
        """Refuse bodies in the wrong units or orientation, with a message saying what was expected."""
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise BodyError("the body mesh must have triangular faces")
        if len(self.face_segment) != len(self.faces):
            raise BodyError("every face needs a segment label")
        missing = sorted(set(range(len(SEGMENTS))) - set(np.unique(self.face_segment).tolist()))
        if missing:
            raise BodyError(f"segments without faces: {[SEGMENTS[i] for i in missing]}; all 16 are needed")
        ext = self.vertices.max(axis=0) - self.vertices.min(axis=0)
        h = ext[2]
        if not 0.5 <= h <= 2.5:
            raise BodyError(f"the body is {h:.3g} units tall along +Z; expected a person 0.5 to 2.5 m tall in metres "
                            "(convert from millimetres or centimetres, or check the scale)")
        if ext[2] < max(ext[0], ext[1]):
            raise BodyError(f"the body extends {ext.round(2).tolist()} m along X, Y, Z: it is lying down or not Z-up; "
                            "expected +Z up, facing -Y, left towards +X")
        zmin = self.vertices[:, 2].min()
        if abs(zmin) > 0.05:
            raise BodyError(f"the feet are at z = {zmin:.3f} m; expected the soles on z = 0")
        head_z = self.joints[SEGMENT_INDEX["head"], 2]
        pelvis_z = self.joints[SEGMENT_INDEX["pelvis"], 2]
        if head_z <= pelvis_z:
            raise BodyError("the neck joint is below the root: the body is upside down; expected +Z up")
        lx = self.joints[SEGMENT_INDEX["upper_arm_l"], 0]
        rx = self.joints[SEGMENT_INDEX["upper_arm_r"], 0]
        if lx <= rx:
            raise BodyError("the left shoulder is not towards +X of the right one: expected the body facing -Y "
                            "with its left side towards +X (turn it 180 degrees about Z, or swap _l and _r)")
        return self

    @property
    def face_count(self) -> int:
        return len(self.faces)


# ----------------------------------------------------------------------------------------------
# The parametric body.
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Proportions:
    """Heights and breadths as fractions of stature (Drillis and Contini; Winter, 2009, Fig. 4.1)."""

    shoulder_height: float = 0.818
    chest_height: float = 0.720
    waist_height: float = 0.600
    hip_height: float = 0.530
    knee_height: float = 0.285
    ankle_height: float = 0.039
    elbow_height: float = 0.630
    wrist_height: float = 0.485
    hand_length: float = 0.108
    shoulder_breadth: float = 0.259
    hip_breadth: float = 0.191
    foot_length: float = 0.152
    chest_depth: float = 0.125
    girth: float = 1.0   # scales every limb and trunk radius (thinner < 1 < stouter)


def _tube(p0, p1, radii_x, radii_y, rings: int, sectors: int, x_hint=(1.0, 0.0, 0.0)):
    """A closed tube from p0 to p1 with elliptical sections: (vertices (n, 3), faces (m, 3)).

    radii_x, radii_y : callables of s in [0, 1] giving the section's semi-axes along the
    x_hint direction (projected off the axis) and the other perpendicular. Poles at both ends
    close it; faces wind counter-clockwise seen from outside. 2 * sectors * rings faces.
    """
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    e1 = np.asarray(x_hint, float) - u * (u @ x_hint)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    s = (np.arange(rings) + 0.5) / rings
    # Rounded ends: the section shrinks like an ellipsoid's towards the poles.
    round_ = np.sqrt(np.clip(1 - (2 * s - 1) ** 2, 0, 1)) ** 0.5
    phi = 2 * math.pi * np.arange(sectors) / sectors
    rx = np.array([radii_x(si) for si in s]) * round_
    ry = np.array([radii_y(si) for si in s]) * round_
    ring_pts = (p0 + np.outer(s, p1 - p0))[:, None, :] + rx[:, None, None] * np.cos(phi)[None, :, None] * e1 \
        + ry[:, None, None] * np.sin(phi)[None, :, None] * e2
    verts = np.vstack([p0[None], ring_pts.reshape(-1, 3), p1[None]])
    faces = []
    idx = lambda r, k: 1 + r * sectors + (k % sectors)  # noqa: E731
    for k in range(sectors):
        faces.append((0, idx(0, k + 1), idx(0, k)))
    for r in range(rings - 1):
        for k in range(sectors):
            a, b, c, d = idx(r, k), idx(r, k + 1), idx(r + 1, k + 1), idx(r + 1, k)
            faces += [(a, b, c), (a, c, d)]
    top = len(verts) - 1
    for k in range(sectors):
        faces.append((top, idx(rings - 1, k), idx(rings - 1, k + 1)))
    faces = np.array(faces)
    # Orient outwards: the pole-to-first-ring fan must point away from the axis.
    tri = verts[faces[0]]
    n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    if n @ (tri.mean(axis=0) - (p0 + 0.5 * (p1 - p0))) < 0:
        faces = faces[:, ::-1]
    return verts, faces


def _lerp(*knots):
    """Piecewise-linear profile through (s, value) knots."""
    s = np.array([k[0] for k in knots])
    v = np.array([k[1] for k in knots])
    return lambda x: float(np.interp(x, s, v))


def make_body(stature_m: float = 1.75, proportions: Proportions | None = None) -> Body:
    """The parametric body (rest pose, body frame), 1700 to 1900 triangles in 16 segments."""
    if not 0.5 <= stature_m <= 2.5:
        raise BodyError(f"stature {stature_m} m is not a person's; give metres, e.g. 1.75")
    P = proportions or Proportions()
    H = stature_m
    g = P.girth
    z = lambda f: f * H  # noqa: E731
    sx = P.shoulder_breadth / 2 * H - 0.02 * H      # shoulder joint, inside the deltoid
    hx = P.hip_breadth / 2 * H * 0.52               # hip joint
    arm_x = sx + 0.005 * H
    leg_x = hx + 0.004 * H
    joints = {
        "pelvis": (0.0, 0.0, z(P.hip_height)),
        "abdomen": (0.0, 0.01 * H, z(P.waist_height)),
        "chest": (0.0, 0.015 * H, z((P.waist_height + P.chest_height) / 2 + 0.02)),
        "head": (0.0, 0.01 * H, z(P.shoulder_height + 0.012)),
        "upper_arm_l": (sx, 0.005 * H, z(P.shoulder_height - 0.01)),
        "forearm_l": (arm_x, 0.01 * H, z(P.elbow_height)),
        "hand_l": (arm_x, 0.0, z(P.wrist_height)),
        "thigh_l": (hx, 0.0, z(P.hip_height)),
        "shank_l": (leg_x, 0.0, z(P.knee_height)),
        "foot_l": (leg_x, 0.0, z(P.ankle_height)),
    }
    for s in ("upper_arm", "forearm", "hand", "thigh", "shank", "foot"):
        x, y, zz = joints[f"{s}_l"]
        joints[f"{s}_r"] = (-x, y, zz)
    # Each segment's tube: (start, end, rx(s), ry(s), rings, sectors, x_hint).
    tubes = {
        "head": ((0, 0.012 * H, z(P.shoulder_height) - 0.01 * H), (0, 0.0, H),
                 _lerp((0, 0.036), (0.35, 0.034), (0.5, 0.050), (0.8, 0.052), (1, 0.045)),
                 _lerp((0, 0.038), (0.35, 0.036), (0.5, 0.058), (0.8, 0.060), (1, 0.050)), 9, 11),
        "chest": ((0, 0.012 * H, z(P.chest_height - 0.06)), (0, 0.015 * H, z(P.shoulder_height + 0.01)),
                  _lerp((0, 0.092), (0.6, 0.100), (0.85, 0.112), (1, 0.108)),
                  _lerp((0, 0.060), (0.5, P.chest_depth / 2), (1, 0.050)), 9, 14),
        "abdomen": ((0, 0.01 * H, z(P.waist_height - 0.04)), (0, 0.012 * H, z(P.chest_height - 0.03)),
                    _lerp((0, 0.088), (1, 0.090)), _lerp((0, 0.060), (1, 0.060)), 4, 12),
        "pelvis": ((0, 0.005 * H, z(P.hip_height - 0.045)), (0, 0.01 * H, z(P.waist_height + 0.015)),
                   _lerp((0, 0.092), (0.5, P.hip_breadth / 2 + 0.004), (1, 0.090)), _lerp((0, 0.062), (1, 0.060)), 5, 12),
    }
    limb = {
        "upper_arm": ("upper_arm", "forearm", 0.026, 0.022, 7, 8),
        "forearm": ("forearm", "hand", 0.021, 0.016, 6, 8),
        "thigh": ("thigh", "shank", 0.046, 0.032, 7, 9),
        "shank": ("shank", "foot", 0.032, 0.020, 7, 8),
    }
    for side, sign in (("l", 1.0), ("r", -1.0)):
        for name, (a, b, r0, r1, rings, sectors) in limb.items():
            p0 = np.array(joints[f"{a}_{side}"])
            p1 = np.array(joints[f"{b}_{side}"])
            # Limb tubes run a little past their joints so neighbours overlap, as flesh does.
            ext = 0.015 * H if name in ("upper_arm", "thigh") else 0.008 * H
            u = (p1 - p0) / np.linalg.norm(p1 - p0)
            tubes[f"{name}_{side}"] = (p0 - u * ext, p1 + u * 0.004 * H, _lerp((0, r0), (1, r1)), _lerp((0, r0), (1, r1)),
                                       rings, sectors)
        w = np.array(joints[f"hand_{side}"])
        tubes[f"hand_{side}"] = (w, w + (0, -0.01 * H, -P.hand_length * H), _lerp((0, 0.012), (0.5, 0.013), (1, 0.010)),
                                 _lerp((0, 0.026), (0.5, 0.030), (1, 0.020)), 5, 6)
        a = np.array(joints[f"foot_{side}"])
        heel = (a[0], 0.03 * H, 0.022 * H)
        toe = (a[0] + sign * 0.01 * H, -(P.foot_length - 0.03) * H, 0.022 * H)
        tubes[f"foot_{side}"] = (heel, toe, _lerp((0, 0.026), (0.6, 0.033), (1, 0.028)),
                                 _lerp((0, 0.022), (1, 0.014)), 6, 7, (0.0, 0.0, 1.0))
    verts, faces, labels = [], [], []
    n = 0
    for seg in SEGMENTS:
        spec = tubes[seg]
        p0, p1, rx, ry, rings, sectors = spec[:6]
        hint = spec[6] if len(spec) > 6 else (1.0, 0.0, 0.0)
        # Radii are fractions of stature, scaled by girth.
        v, f = _tube(p0, p1, lambda s, rx=rx: rx(s) * H * g, lambda s, ry=ry: ry(s) * H * g, rings, sectors, hint)
        if seg.startswith("foot"):
            v[:, 2] = np.maximum(v[:, 2], 0.0)  # flat soles on the floor
        verts.append(v)
        faces.append(f + n)
        labels.append(np.full(len(f), SEGMENT_INDEX[seg]))
        n += len(v)
    V = np.vstack(verts)
    body = Body(vertices=V, faces=np.vstack(faces), face_segment=np.concatenate(labels),
                joints=np.array([joints[s] for s in SEGMENTS], float))
    return body.check()
