"""The paper's Head / Shoulder / Chest table, computed from the scores, and mount.toml.

Zones (stated geometrically; ``radius_m`` and thresholds are arguments):

``head``      head-segment polygons at least 0.10 m above the neck joint (the head, not the
              neck) that do not face downwards (normal z > -0.5).
``shoulder``  upward-facing chest polygons (normal z > 0.5) within ``radius_m`` (0.12 m) of
              either shoulder joint.
``chest``     forward-facing chest polygons (normal . forward > 0.7) below the shoulder joints
              by at least 0.05 m.

Columns, per zone: mean field of view, handling view, motion (world and pelvis frames, mm and
deg), and two judgements by stated rules:

* frame of reference the zone ties a fixed camera to: the wearer's *attention* if the zone is
  on the head (it turns where the wearer looks); the wearer's *workspace* if the zone faces
  forward on the torso (it turns with the trunk towards the work); otherwise the *world*: a
  torso zone that faces neither the gaze nor the work leaves an active head free to refer its
  view to the world (gravity, SLAM), for most tasks.
* social acceptability, by the camera's distance from the wearer's eyes in the rest pose (a
  camera at the face is in the face of everyone the wearer talks to): < 0.15 m low,
  0.15 to 0.30 m medium, > 0.30 m high.

The best polygon of each zone (highest combined score) is written as ``mount_<zone>.toml``
(the schema of :mod:`kinematics.mountfile`); ``mount.toml`` is the best of the zones not tied to
the wearer's attention (the paper's criterion for choosing the shoulder).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinematics.mountfile import MountFile, save_mount

from .body import SEGMENT_INDEX, Body
from .scores import ScoreTable

FORWARD = np.array([0.0, -1.0, 0.0])   # the body faces -Y
ZONES = ("head", "shoulder", "chest")
ATTENTION = "wearer's attention"


@dataclass(frozen=True)
class ZoneRow:
    """One zone of the table: means over its polygons, judgements, and its best polygon.

    fov, handling_view : means of the scores (fractions). motion_mm, motion_deg : world-frame
    motion (with the wearer's progression removed); motion_pelvis_mm, motion_pelvis_deg :
    relative to the pelvis. combined : mean combined score. frame : what a fixed camera there is
    tied to. distance_to_eyes_m and acceptability : the social judgement. best_polygon,
    best_combined : the polygon with the highest combined score and that score.
    """

    zone: str
    polygons: int
    fov: float
    handling_view: float
    motion_mm: float
    motion_deg: float
    motion_pelvis_mm: float
    motion_pelvis_deg: float
    combined: float
    frame: str
    distance_to_eyes_m: float
    acceptability: str
    best_polygon: int
    best_combined: float


@dataclass(frozen=True)
class Zones:
    """The zone table: ``rows[zone]`` for each of :data:`ZONES` (None when the zone has no
    polygons), the zone ``mount.toml`` was taken from (None if none qualifies), the lines that
    compare the table with the paper's claims, and the motions and poses it was computed over."""

    rows: dict[str, ZoneRow | None]
    mount_zone: str | None
    comparison: tuple[str, ...]
    motions: tuple[str, ...]
    poses: tuple[str, ...]

    def markdown(self) -> str:
        """zones.md: the table, the choice of mount.toml and the comparison with the paper."""
        lines = ["# Where to wear the camera: Head, Shoulder, Chest", "",
                 "Computed from the per-polygon scores (`scores.csv`); zones, rules and weights are stated in "
                 "`placement/zones.py` and `placement/scores.py`. Motion is the mean displacement of the camera over "
                 f"the motions ({', '.join(self.motions)}); field and handling view are means over the poses "
                 f"({', '.join(self.poses)}).", "",
                 "| zone | polygons | field of view | handling view | motion, world (mm / deg) | motion, pelvis "
                 "(mm / deg) | ties the camera to | eyes (m) | social acceptability | combined (mean / best) |",
                 "|---|---|---|---|---|---|---|---|---|---|"]
        for zone, r in self.rows.items():
            if r is None:
                lines.append(f"| {zone} | 0 | | | | | | | | |")
                continue
            lines.append(f"| {r.zone} | {r.polygons} | {r.fov:.3f} | {r.handling_view:.3f} | "
                         f"{r.motion_mm:.0f} / {r.motion_deg:.1f} | {r.motion_pelvis_mm:.0f} / {r.motion_pelvis_deg:.1f} | "
                         f"{r.frame} | {r.distance_to_eyes_m:.2f} | {r.acceptability} | "
                         f"{r.combined:.3f} / {r.best_combined:.3f} |")
        lines.append("")
        if self.mount_zone is not None:
            chosen = self.rows[self.mount_zone]
            lines += [f"`mount.toml`: the best polygon ({chosen.best_polygon}) of the **{chosen.zone}** zone, the "
                      "highest combined score among zones that do not tie the camera to the wearer's attention. "
                      "Each zone's best polygon is in `mount_<zone>.toml`.", ""]
        if self.comparison:
            lines += ["## Against the paper's claims", "", *self.comparison, ""]
        return "\n".join(lines)


def zone_masks(body: Body, table: ScoreTable, radius_m: float = 0.12) -> dict[str, np.ndarray]:
    """(F,) bool mask of each zone's polygons."""
    c, n = table.centroid, table.normal
    seg = body.face_segment
    j = body.joints
    neck = j[SEGMENT_INDEX["head"]]
    shoulders = j[[SEGMENT_INDEX["upper_arm_l"], SEGMENT_INDEX["upper_arm_r"]]]
    near_shoulder = np.min(np.linalg.norm(c[:, None, :] - shoulders[None], axis=2), axis=1) <= radius_m
    chest = seg == SEGMENT_INDEX["chest"]
    return {
        "head": (seg == SEGMENT_INDEX["head"]) & (c[:, 2] >= neck[2] + 0.10) & (n[:, 2] > -0.5),
        "shoulder": chest & (n[:, 2] > 0.5) & near_shoulder,
        "chest": chest & (n @ FORWARD > 0.7) & (c[:, 2] <= shoulders[:, 2].min() - 0.05),
    }


def eye_point(body: Body) -> np.ndarray:
    """The eyes, rest pose: the head's front surface at 93.6% of stature (Drillis and Contini)."""
    v = body.vertices[body.vertex_segment == SEGMENT_INDEX["head"]]
    z = body.vertices[:, 2].min() + 0.936 * body.stature_m
    near = v[np.abs(v[:, 2] - z) < 0.03]
    front = near[np.argmin(near @ -FORWARD)] if len(near) else v[np.argmax(v[:, 2])]
    return np.array([0.0, front[1], z])


def reference_frame(zone: str, mean_normal: np.ndarray) -> str:
    if zone == "head":
        return ATTENTION
    if mean_normal @ FORWARD > 0.5:
        return "wearer's workspace"
    return "world (most tasks)"


def acceptability(distance_to_eyes_m: float) -> str:
    return "low" if distance_to_eyes_m < 0.15 else ("medium" if distance_to_eyes_m <= 0.30 else "high")


def zone_table(body: Body, table: ScoreTable, radius_m: float = 0.12) -> dict[str, ZoneRow | None]:
    """Each zone's row (None for a zone without polygons), in :data:`ZONES` order."""
    masks = zone_masks(body, table, radius_m)
    eyes = eye_point(body)
    rows: dict[str, ZoneRow | None] = {}
    for zone in ZONES:
        m = masks[zone]
        if not m.any():
            rows[zone] = None
            continue
        idx = np.flatnonzero(m)
        best = int(idx[np.argmax(table["combined"][idx])])
        mean_n = table.normal[idx].mean(axis=0)
        mean_n /= np.linalg.norm(mean_n)
        d_eyes = float(np.linalg.norm(table.centroid[best] - eyes))
        means = {k: float(table[k][idx].mean()) for k in ("fov", "handling_view", "motion_mm", "motion_deg",
                                                          "motion_pelvis_mm", "motion_pelvis_deg", "combined")}
        rows[zone] = ZoneRow(zone=zone, polygons=int(m.sum()), **means, frame=reference_frame(zone, mean_n),
                             distance_to_eyes_m=d_eyes, acceptability=acceptability(d_eyes),
                             best_polygon=best, best_combined=float(table["combined"][best]))
    return rows


def mount_for(body: Body, table: ScoreTable, polygon: int, zone: str) -> MountFile:
    """The mount.toml of a polygon: its segment, and the mount's position and axes in the
    segment frame (origin at the segment's joint centre, the body's axes in the rest pose).

    The mount sits ``standoff_m`` out along the polygon's normal and is levelled, as a bracket
    would level it: its x axis is the body's forward direction and its z axis the body's up,
    whatever the slope of the surface (the surface normal is kept for reference).
    """
    seg_i = int(body.face_segment[polygon])
    n = table.normal[polygon]
    c = table.centroid[polygon] + table.settings.standoff_m * n
    return MountFile(segment=str(table.segment[polygon]), position_m=c - body.joints[seg_i], forward=FORWARD,
                     up=np.array([0.0, 0.0, 1.0]), zone=zone, polygon=int(polygon), normal=n,
                     standoff_m=table.settings.standoff_m, stature_m=body.stature_m)


def paper_comparison(rows: dict[str, ZoneRow | None], mount_zone: str | None) -> tuple[str, ...]:
    """The table against the paper's claims (only when all three zones have polygons)."""
    by = {z: r for z, r in rows.items() if r is not None}
    if len(by) != 3:
        return ()
    fov_rank = sorted(by, key=lambda z: -by[z].fov)
    mo_rank = sorted(by, key=lambda z: by[z].motion_mm)
    best = max(by, key=lambda z: by[z].combined)
    out = [f"- Field of view ranks {' > '.join(fov_rank)}; the paper has head and shoulder *wide* and chest "
           f"*limited*: {'agrees' if fov_rank[-1] == 'chest' else 'does not agree'}.",
           f"- Motion (least first) ranks {' < '.join(mo_rank)}; the paper has the head's motion *large*, the "
           f"shoulder's and chest's *small*: {'agrees' if mo_rank[-1] == 'head' else 'does not agree'}.",
           f"- The best combined zone on average is the {best}; the paper favours head and shoulders"
           f"{', and here agrees' if best in ('head', 'shoulder') else ', and here does not agree'}."]
    if mount_zone is not None:
        out.append(f"- Without the attention-tied head, the {mount_zone} wins"
                   f"{' as in the paper' if mount_zone == 'shoulder' else ', unlike the paper (which chose the shoulder)'}.")
    return tuple(out)


def write_zones(body: Body, table: ScoreTable, out: str | Path, paper_check: bool = True) -> Zones:
    """zones.md and the mount files (mount_<zone>.toml, and mount.toml); returns the table."""
    out = Path(out)
    rows = zone_table(body, table)
    for r in rows.values():
        if r is not None:
            save_mount(mount_for(body, table, r.best_polygon, r.zone), out / f"mount_{r.zone}.toml")
    free = [r for r in rows.values() if r is not None and r.frame != ATTENTION]
    chosen = max(free, key=lambda r: r.best_combined) if free else None
    if chosen:
        save_mount(mount_for(body, table, chosen.best_polygon, chosen.zone), out / "mount.toml")
    mount_zone = chosen.zone if chosen else None
    zones = Zones(rows=rows, mount_zone=mount_zone,
                  comparison=paper_comparison(rows, mount_zone) if paper_check else (),
                  motions=tuple(table.motions), poses=tuple(table.poses))
    (out / "zones.md").write_text(zones.markdown())
    return zones
