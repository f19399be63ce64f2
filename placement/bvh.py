"""BVH motion files as written: the HIERARCHY (joints, offsets, channels) and the MOTION frames.

:func:`read_bvh` parses a file without interpreting it (any channel orders; Euler angles in
degrees, intrinsic in channel order; positions in file units and axes) and refuses what it
cannot read with a one-line :class:`~placement.body.BodyError` naming the line. Retargeting
onto the body is :mod:`placement.retarget`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.textnumbers import first_non_number
from kinematics.nesting import deeper_than, nesting_message

from .body import BodyError

__all__ = ["BvhData", "read_bvh"]

AXES = "XYZ"


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
                p[:, AXES.index(c[0])] += self.frames[:, self.channel_start[root] + k]
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
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as e:
        what = "is a folder" if path.is_dir() else "no such file" if not path.exists() else f"cannot be read ({e.strerror or e})"
        raise BodyError(f"{path}: {what}; give a BVH motion file (HIERARCHY then MOTION)") from None
    motion_line = next((i for i, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise BodyError(f"{name}: no MOTION section; expected a BVH file with HIERARCHY then MOTION")
    deep = deeper_than("\n".join(lines[:motion_line]), "braces")   # joint() recurses once per level
    if deep is not None:
        raise BodyError(nesting_message(name, deep))
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
            bad = first_non_number(vals)
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
