"""The closed loop's human-readable outputs: report.md, summary.json and two plots."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from kinematics import JOINT_NAMES


def write_outputs(out: Path, times, summary: dict, cmd_rate, settings) -> None:
    _plots(out, times, summary, cmd_rate, settings)
    (out / "report.md").write_text(report_md(summary))
    (out / "summary.json").write_text(json.dumps({k: v for k, v in summary.items()
                                                   if k not in ("fixation_error_deg", "pitch_roll_deg")}, indent=1))


def _plots(out: Path, times, summary, cmd_rate, settings) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3))
    if "fixation_error_deg" in summary:
        ax.plot(times, summary["fixation_error_deg"], lw=1)
        ax.set_ylabel("fixation error, deg (true)")
        ax.axhline(1.0, color="grey", ls=":", lw=0.8)
    elif "pitch_roll_deg" in summary:
        pr = np.array(summary["pitch_roll_deg"])
        ax.plot(times, pr[:, 0] - pr[0, 0], lw=1, label="pitch")
        ax.plot(times, pr[:, 1] - pr[0, 1], lw=1, label="roll")
        ax.set_ylabel("change from start, deg (true)")
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no truth on this robot: nothing to score", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("t, s")
    fig.tight_layout()
    fig.savefig(out / "fixation_error.png", dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 3))
    for j, n in enumerate(JOINT_NAMES):
        ax.plot(times, np.degrees(cmd_rate[:, j]), lw=1, label=f"{n} (cmd)")
    lim = math.degrees(settings.motion_limit_rad_s)
    ax.axhline(lim, color="grey", ls=":", lw=0.8)
    ax.axhline(-lim, color="grey", ls=":", lw=0.8)
    ax.set_xlabel("t, s")
    ax.set_ylabel("joint rate, deg/s")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "joint_rates.png", dpi=100)
    plt.close(fig)


def report_md(s: dict) -> str:
    lines = [f"# Closed loop: {s['task']} on {s['scenario']}", "",
             f"{s['frames']} frames over {s['seconds']:.2f} s; controlled-motion limit {s['motion_limit_deg_s']:.0f} deg/s; "
             f"peak commanded joint rate {s['peak_cmd_rate_deg_s']:.1f} deg/s (measured {s['peak_meas_rate_deg_s']:.1f}).", ""]
    if s.get("ended", "complete") != "complete":
        lines += [f"The session ended early: {s['ended']}.", ""]
    if "fixation_rms_deg" in s:
        lines.append(f"Fixation error after the first second (true optic axis against the true direction to the "
                     f"target): RMS {s['fixation_rms_deg']:.2f} deg, peak {s['fixation_peak_deg']:.2f} deg.")
    for k, L in enumerate(s.get("landings", [])):
        if L["landed"]:
            lines.append(f"- saccade {k} to target {L['target']} at {L['start_s']:.2f} s: landed after "
                         f"{L['duration_s']:.2f} s, error {L['error_deg']:.2f} deg (max {L['error_after_deg']:.2f} over 0.3 s)")
        else:
            lines.append(f"- saccade {k} to target {L['target']} at {L['start_s']:.2f} s: did not land")
    if "pitch_max_dev_deg" in s:
        lines.append(f"Camera attitude against its start (true): pitch max {s['pitch_max_dev_deg']:.2f} deg "
                     f"(RMS {s['pitch_rms_dev_deg']:.2f}), roll max {s['roll_max_dev_deg']:.2f} deg "
                     f"(RMS {s['roll_rms_dev_deg']:.2f}).")
    if "servo_centre_rms_px" in s:
        lines.append(f"Tracking and servoing (after the first second): the target's true centre is "
                     f"{s['servo_centre_rms_px']:.1f} px RMS (max {s['servo_centre_max_px']:.1f}) from the image centre; "
                     f"the tracker's corners are {s['tracker_corner_rms_px']:.2f} px RMS from the truth; "
                     f"{s['track_lost_frames']} frames lost (tracking.csv).")
    if "ate_rmse_m" in s:
        lines.append(f"SLAM during the run: ATE RMSE {100 * s['ate_rmse_m']:.2f} cm (max {100 * s['ate_max_m']:.2f}), "
                     f"{s['lost_frames']} frames lost.")
    elif "lost_frames" in s:
        lines.append(f"SLAM during the run: {s['lost_frames']} frames lost (no truth to score its pose against).")
    for r in s["refusals"]:
        lines.append(f"- refused at {r['t']:.2f} s: {r['reason']}")
    files = "groundtruth.txt (true poses), " if "ate_rmse_m" in s or "pitch_max_dev_deg" in s else ""
    lines += ["", f"{s['prompts']} wearer prompts (prompts.csv).", "", "![error](fixation_error.png)", "",
              "![joint rates](joint_rates.png)", "",
              f"Files: {files}trajectory.tum (SLAM), task.toml, joints.csv, prompts.csv, summary.json."]
    return "\n".join(lines) + "\n"
