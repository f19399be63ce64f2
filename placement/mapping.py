"""The whole placement study in one call: score every polygon, write scores.csv, the body maps,
zones.md and the mount files (what ``wvr placement map`` runs)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from .body import Body, Motion, make_body
from .maps import render_all_maps
from .motions import default_motions, default_poses
from .scores import SCORE_COLUMNS, ScoreSettings, ScoreTable, score_body
from .zones import write_zones


def write_scores_csv(table: ScoreTable, path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["polygon", "segment", "cx", "cy", "cz", "nx", "ny", "nz", *SCORE_COLUMNS])
        for i in table.polygon:
            w.writerow([int(i), table.segment[i], *(f"{v:.5f}" for v in table.centroid[i]),
                        *(f"{v:.5f}" for v in table.normal[i]), *(f"{table[c][i]:.6g}" for c in SCORE_COLUMNS)])


def placement_map(out: str | Path, body: Body | None = None, motions: list[Motion] | None = None,
                  settings: ScoreSettings = ScoreSettings(), pictures: bool = True, progress: bool = True) -> dict:
    """Run the study into ``out``; returns a summary (files, zone rows)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    body = make_body() if body is None else body
    motions = default_motions(body) if not motions else motions
    table = score_body(body, default_poses(body), motions, settings, progress=progress)
    write_scores_csv(table, out / "scores.csv")
    maps = render_all_maps(body, table, out) if pictures else {}
    rows = write_zones(body, table, out)
    summary = {"polygons": body.face_count, "stature_m": body.stature_m, "rays": settings.rays,
               "standoff_m": settings.standoff_m, "poses": list(table.poses), "motions": list(table.motions),
               "unmapped_joints": sorted({j for m in motions for j in m.unmapped}), "maps": maps, "zones": rows}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
