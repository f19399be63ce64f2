"""The whole placement study in one call: score every polygon, write scores.csv, the body maps,
zones.md and the mount files (what ``wvr placement map`` runs)."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass
from pathlib import Path

from kinematics.outdir import output_folder

from .body import Body, Motion, make_body
from .maps import render_all_maps
from .motions import default_motions, default_poses
from .scores import SCORE_COLUMNS, ScoreSettings, ScoreTable, score_body
from .zones import Zones, write_zones


@dataclass(frozen=True)
class PlacementResult:
    """What a placement study wrote into ``folder`` and found.

    polygons : places scored. stature_m, rays, standoff_m : the body's height and the settings.
    poses, motions : the names scored over. unmapped_joints : BVH joints that drove no segment.
    maps : kind -> file name of each body map. zones : the Head/Shoulder/Chest table (its
    ``mount_zone`` is where mount.toml was taken from).
    """

    folder: Path
    polygons: int
    stature_m: float
    rays: int
    standoff_m: float
    poses: tuple[str, ...]
    motions: tuple[str, ...]
    unmapped_joints: tuple[str, ...]
    maps: dict[str, str]
    zones: Zones

    def summary(self) -> dict:
        """summary.json's contents (zones as rows, an empty zone as its name and 0 polygons)."""
        return {"polygons": self.polygons, "stature_m": self.stature_m, "rays": self.rays,
                "standoff_m": self.standoff_m, "poses": list(self.poses), "motions": list(self.motions),
                "unmapped_joints": list(self.unmapped_joints), "maps": dict(self.maps),
                "zones": [asdict(r) if r is not None else {"zone": z, "polygons": 0}
                          for z, r in self.zones.rows.items()],
                "mount_zone": self.zones.mount_zone}


def write_scores_csv(table: ScoreTable, path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["polygon", "segment", "cx", "cy", "cz", "nx", "ny", "nz", *SCORE_COLUMNS])
        for i in table.polygon:
            w.writerow([int(i), table.segment[i], *(f"{v:.5f}" for v in table.centroid[i]),
                        *(f"{v:.5f}" for v in table.normal[i]), *(f"{table[c][i]:.6g}" for c in SCORE_COLUMNS)])


def placement_map(out: str | Path, body: Body | None = None, motions: list[Motion] | None = None,
                  settings: ScoreSettings = ScoreSettings(), pictures: bool = True,
                  progress: bool = True) -> PlacementResult:
    """Run the study into ``out`` (an output folder of kinematics.outdir: checked before the
    scoring starts, INCOMPLETE until everything is written); returns what it found."""
    body = make_body() if body is None else body
    motions = default_motions(body) if not motions else motions
    with output_folder(out, kind="placement map") as out:
        table = score_body(body, default_poses(body), motions, settings, progress=progress)
        write_scores_csv(table, out / "scores.csv")
        maps = render_all_maps(body, table, out) if pictures else {}
        zones = write_zones(body, table, out)
        result = PlacementResult(folder=out, polygons=body.face_count, stature_m=body.stature_m,
                                 rays=settings.rays, standoff_m=settings.standoff_m, poses=tuple(table.poses),
                                 motions=tuple(table.motions),
                                 unmapped_joints=tuple(sorted({j for m in motions for j in m.unmapped})),
                                 maps=maps, zones=zones)
        (out / "summary.json").write_text(json.dumps(result.summary(), indent=2))
    return result
