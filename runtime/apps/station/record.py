"""The station's recording, written when it stops: ``trajectory.tum`` (SLAM's poses),
``groundtruth.txt`` (the twin's true poses; twin only), ``events.csv`` (every action with its
time, source and result), ``labels.toml`` (labels and virtual objects, world frame) and
``station.json``.

Never half-written: ``station.json`` says ``"complete": false`` from the start of the session
(:func:`begin`) until every file is in place (:func:`finish`); each file is written beside its
final name and renamed into place.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from pathlib import Path

import numpy as np

from kinematics.outdir import OutputFolder, check_folder

from ...sequence import write_trajectory
from .live import StationRun

EVENTS_HEADER = ["t", "wall_time", "source", "action", "detail", "result", "reason", "first_motion_after_s"]


#: The kind (kinematics.outdir) of the station's --out folder.
KIND = "station"


def check_out(out: str | Path) -> Path:
    """The output folder, checked and nothing made (kinematics.outdir.check_folder: not a file,
    writable, not another command's or another station's results, not being written);
    OutputFolderError (a ValueError, one line) if it cannot be used."""
    return check_folder(out, KIND)


def claim_out(out: str | Path) -> OutputFolder:
    """The output folder, created, locked and INCOMPLETE until its ``close`` (after :func:`finish`)."""
    return OutputFolder(out, kind=KIND)


def _status(out: Path, complete: bool, status: str, extra: dict | None = None) -> None:
    doc = {"complete": complete, "status": status, "written": time.strftime("%Y-%m-%d %H:%M:%S"), **(extra or {})}
    _write(out / "station.json", json.dumps(doc, indent=1) + "\n")


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text)
    tmp.replace(path)


def begin(out: Path, notes: dict | None = None) -> None:
    _status(out, False, "running", notes)


def failed(out: Path, reason: str, notes: dict | None = None) -> None:
    """A session that never ran (its loop failed before its first period): no recording."""
    _status(out, False, f"failed: {reason}", notes)


def _toml_str(s: str) -> str:
    return json.dumps(s)           # a JSON string is a valid TOML basic string


def labels_toml(run: StationRun) -> str:
    lines = ["# the operator's labels and virtual objects, world frame (m)"]
    for lb in run.labels:
        lines += ["", "[[label]]", f"id = {lb.id}", f"text = {_toml_str(lb.text)}",
                  "xyz = [" + ", ".join(f"{v:.6f}" for v in lb.xyz) + "]"]
    for ob in run.objects:
        lines += ["", "[[object]]", f"id = {ob.id}", f'kind = "{ob.kind}"',
                  "xyz = [" + ", ".join(f"{v:.6f}" for v in ob.xyz) + "]",
                  "size = [" + ", ".join(f"{v:.6f}" for v in ob.size) + "]"]
    return "\n".join(lines) + "\n"


def events_csv(run: StationRun) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(EVENTS_HEADER)
    for e in run.events:
        lat = e.first_motion_wall - e.wall if math.isfinite(e.first_motion_wall) else float("nan")
        w.writerow([f"{e.t:.3f}" if math.isfinite(e.t) else "", f"{e.wall:.3f}", e.source, e.action, e.detail,
                    "accepted" if e.accepted else "refused", e.reason, f"{lat:.3f}" if math.isfinite(lat) else ""])
    return buf.getvalue()


def finish(out: Path, run: StationRun, notes: dict | None = None) -> list[str]:
    """Write the recording; returns the files written."""
    written = []
    t = np.asarray(run.times, float)
    T = np.asarray(run.T_est, float).reshape(-1, 4, 4)
    ok = np.isfinite(T).all(axis=(1, 2))
    if ok.any():
        tmp = out / "trajectory.tum.part"
        write_trajectory(tmp, t[ok], T[ok], header="SLAM camera-to-world poses during the station's session")
        tmp.replace(out / "trajectory.tum")
        written.append("trajectory.tum")
    if run.T_true:
        tmp = out / "groundtruth.txt.part"
        write_trajectory(tmp, t[:len(run.T_true)], np.asarray(run.T_true, float),
                         header="true camera-to-world poses (optical frame), scoring only")
        tmp.replace(out / "groundtruth.txt")
        written.append("groundtruth.txt")
    _write(out / "events.csv", events_csv(run))
    _write(out / "labels.toml", labels_toml(run))
    written += ["events.csv", "labels.toml"]
    _status(out, run.fault is None, run.ended or "stopped",
            {"frames": len(run.times), "events": len(run.events), "labels": len(run.labels),
             "objects": len(run.objects), **(notes or {})})
    written.append("station.json")
    return written
