"""Retargeting a BVH motion onto the body: which joint drives which segment, axes, scale, the
rest alignment, and the root's path (:func:`load_bvh`).

Conventions (see :func:`load_bvh` for the whole contract): BVH files are usually Y up, facing
+Z, left towards +X; ours is +Z up, facing -Y, left towards +X, so ``our = C @ bvh`` with
x = bx, y = -bz, z = by. A BVH rest pose is usually a T-pose and ours has the arms down, so each
segment is aligned once at rest. Every refusal is a one-line BodyError naming the file, what
was expected and the fix (the ``wvr placement map`` flag and the Python argument).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.transforms import rotation_between

from .body import PARENT, SEGMENT_INDEX, SEGMENTS, Body, BodyError, Motion
from .bvh import AXES, BvhData, read_bvh

__all__ = ["load_bvh"]

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




@dataclass(frozen=True)
class _Frame:
    """The file's axes in ours: ``C`` (3, 3) with our = C @ file, and ``up`` (3,), the file's up."""

    C: np.ndarray
    up: np.ndarray
    name: str


def _axes(up: str) -> _Frame:
    up = up.lower()
    if up not in ("y", "z"):
        raise BodyError(f"up={up!r}; expected 'y' (usual BVH) or 'z'")
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]) if up == "y" else np.eye(3)
    u = np.array([0.0, 1.0, 0.0]) if up == "y" else np.array([0.0, 0.0, 1.0])
    return _Frame(C, u, up)


def _check_drivers(path: Path, bvh: BvhData, drivers: dict[str, int], allow_missing: bool) -> None:
    missing = [s for s in SEGMENTS if s not in drivers]
    if missing and not allow_missing:
        names = list(bvh.names[:12]) + (["..."] if len(bvh.names) > 12 else [])
        raise BodyError(f"{path.name}: no joint drives segments {missing}; rename the joints, or keep those segments "
                        f"at rest (--allow-missing-joints; allow_missing=True in Python); expected CMU or Mixamo names "
                        f"(Hips, Spine, Spine1, Neck, Head, LeftArm, LeftForeArm, LeftHand, LeftUpLeg, LeftLeg, "
                        f"LeftFoot, Right...), the file has {', '.join(names)}")


def _check_up(path: Path, frame: _Frame, drivers: dict[str, int], neck_anchor: int | None, rest: np.ndarray,
              points: np.ndarray) -> None:
    """The head must be above the feet along the declared axis (a T-pose's arm span can exceed its
    height, so the largest extent alone would misjudge)."""
    feet = [drivers[f] for f in ("foot_l", "foot_r") if f in drivers]
    top = drivers.get("head", neck_anchor)
    if top is not None and feet:
        d = rest[top] - rest[feet].mean(axis=0)
    else:
        d = np.zeros(3)
        k = int(np.argmax(np.ptp(points, axis=0)))
        d[k] = np.ptp(points, axis=0)[k]
    axis = int(np.argmax(np.abs(d)))
    declared = AXES.index(frame.name.upper())
    if axis != declared or d[axis] <= 0:
        found = ("-" if d[axis] < 0 else "+") + AXES[axis]
        hint = (f"declare it (--motion-up {AXES[axis].lower()}; up='{AXES[axis].lower()}' in Python)"
                if d[axis] > 0 and AXES[axis] in "YZ" else "re-export it Y-up or Z-up")
        raise BodyError(f"{path.name}: the rest skeleton's head is above its feet along {found}, not "
                        f"+{frame.name.upper()} as up={frame.name!r} declares; {hint}")


def _facing(frame: _Frame, drivers: dict[str, int], rest: np.ndarray) -> _Frame:
    """Left towards +X is the BVH convention for both axes; a skeleton with its left side towards
    -X faces the other way: turn it half a turn about up rather than mirror it."""
    lr = [(drivers[f"{s}_l"], drivers[f"{s}_r"]) for s in ("thigh", "upper_arm")
          if f"{s}_l" in drivers and f"{s}_r" in drivers]
    if lr and sum(rest[a, 0] - rest[b, 0] for a, b in lr) < 0:
        return _Frame(frame.C @ Rotation.from_rotvec(math.pi * frame.up).as_matrix(), frame.up, frame.name)
    return frame


def _scale(path: Path, body: Body, frame: _Frame, drivers: dict[str, int], neck_anchor: int | None,
           rest: np.ndarray, points: np.ndarray, scale: float | None) -> float:
    """Metres per file unit: given, or fitted from the neck-to-ankle height; checked either way."""
    feet = [drivers[f] for f in ("foot_l", "foot_r") if f in drivers]
    u = frame.up
    span = np.nan
    if neck_anchor is not None and feet:
        span = float(rest[neck_anchor] @ u - np.mean(rest[feet] @ u))
    if scale is None:
        if not span > 0:
            raise BodyError(f"{path.name}: cannot fit the scale without Neck/Head and LeftFoot/RightFoot joints "
                            "above one another; give it (--motion-scale 0.01 for centimetres; scale=0.01 in "
                            "Python: metres per file unit)")
        ankles = body.joints[[SEGMENT_INDEX["foot_l"], SEGMENT_INDEX["foot_r"]], 2].mean()
        ours = body.joints[SEGMENT_INDEX["head"], 2] - ankles
        scale = float(ours / span)
    height = float(scale * np.ptp(points @ u))
    if not (np.isfinite(height) and 0.5 <= height <= 2.5):
        raise BodyError(f"{path.name}: at scale={scale:g} m per unit the rest skeleton is {height:.3g} m tall; "
                        "expected a person 0.5 to 2.5 m tall: give --motion-scale 0.01 for centimetres, 0.0254 "
                        "for inches, 1 for metres (scale=0.01 etc. in Python), or leave it out to fit the body")
    return scale


def _bone_target(bvh: BvhData, drivers: dict[str, int], neck_anchor: int | None, j: int, child: str,
                 rest: np.ndarray, points: np.ndarray) -> int:
    """The joint a segment's bone points at: the next driver, or for the chest the neck. CMU puts
    Neck on Spine1 (zero offset): then the next joint up the neck that is apart from it."""
    targets = [drivers[child]]
    up_chain = _path_up(bvh, drivers[child], j)
    if child == "head" and bvh.parents[up_chain[-1]] == j:
        targets = up_chain[::-1]
        if neck_anchor in targets:
            targets = targets[targets.index(neck_anchor):]
    apart = [k for k in targets if np.linalg.norm(rest[k] - rest[j]) > 1e-6 * np.ptp(points)]
    return apart[0] if apart else targets[-1]


def _rest_alignments(bvh: BvhData, body: Body, frame: _Frame, drivers: dict[str, int], neck_anchor: int | None,
                     rest: np.ndarray, ends: np.ndarray, points: np.ndarray) -> dict[str, np.ndarray]:
    """A_s (3, 3) of each driven segment: the minimal rotation taking our rest bone onto the
    file's (in our axes); see :func:`load_bvh`."""
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
            b_bvh = rest[_bone_target(bvh, drivers, neck_anchor, j, child, rest, points)] - rest[j]
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
            A[s] = rotation_between(b_ours, frame.C @ b_bvh)
    return A


def _local_rotations(bvh: BvhData, Rg: np.ndarray, frame: _Frame, drivers: dict[str, int],
                     A: dict[str, np.ndarray]) -> np.ndarray:
    """(T, 16, 3) rotation vectors of every segment relative to its parent: G_s = C Rg_j C^T A_s,
    an undriven segment at rest relative to its parent."""
    C = frame.C
    T = len(bvh.frames)
    G = np.zeros((T, len(SEGMENTS), 3, 3))
    local = np.zeros_like(G)
    for i, s in enumerate(SEGMENTS):
        p = PARENT[s]
        if s in drivers:
            G[:, i] = C @ Rg[:, drivers[s]] @ C.T @ A[s]
        else:
            G[:, i] = G[:, SEGMENT_INDEX[p]] if p else np.eye(3)
        local[:, i] = G[:, i] if p is None else np.swapaxes(G[:, SEGMENT_INDEX[p]], -1, -2) @ G[:, i]
    return Rotation.from_matrix(local.reshape(-1, 3, 3)).as_rotvec().reshape(T, len(SEGMENTS), 3)


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
    it as the BVH root moves (the wearer's own travel stays in the motion; scoring removes it,
    placement.scores). A BVH whose first frame is not standing (e.g. crouched) therefore leaves
    the body's height offset by that difference.
    """
    path = Path(path)
    bvh = read_bvh(path)
    frame = _axes(up)
    drivers, neck_anchor = _find_drivers(bvh)
    _check_drivers(path, bvh, drivers, allow_missing)
    rest, ends = bvh.rest_positions()
    points = np.vstack([rest, ends])
    _check_up(path, frame, drivers, neck_anchor, rest, points)
    frame = _facing(frame, drivers, rest)
    scale = _scale(path, body, frame, drivers, neck_anchor, rest, points, scale)
    A = _rest_alignments(bvh, body, frame, drivers, neck_anchor, rest, ends, points)
    Rg = bvh.global_rotations()
    rotvec = _local_rotations(bvh, Rg, frame, drivers, A)
    p_root = bvh.positions(drivers.get("pelvis", 0), Rg)
    root_m = scale * (p_root - p_root[0]) @ frame.C.T
    used = set(drivers.values())
    unmapped = tuple(n for j, n in enumerate(bvh.names) if j not in used)
    return Motion(name=path.stem, t=np.arange(len(bvh.frames)) * bvh.frame_time, rotvec=rotvec, root_m=root_m,
                  unmapped=unmapped)
