"""A session's recording in the TUM layout (shared/formats.md), so that ``wvr slam`` replays it:
rgb/, rgb.txt, imu.txt, joints.txt (the joint angles as observed: commanded on a rig whose servos
report nothing), camera.toml, head.toml, target.toml. The folder is marked incomplete
(session.json ``"complete": false``) from the first frame until :meth:`finish` says otherwise;
everything recorded before a fault is kept."""

from __future__ import annotations

import json
import time
from pathlib import Path

from kinematics import HeadGeometry, save_head
from kinematics.camera import CameraIntrinsics

from ..robot import JointCommand, Observation
from ..sequence import SequenceWriter, Target


class SessionRecorder:
    def __init__(self, out: str | Path, camera: CameraIntrinsics, head: HeadGeometry, target: Target | None = None,
                 notes: dict | None = None):
        self.out = Path(out)
        self.writer = SequenceWriter(self.out, camera, target=target)
        save_head(head, self.out / "head.toml")
        self.frames = 0
        self.notes = dict(notes or {})
        self._status(False, "recording")

    def _status(self, complete: bool, reason: str) -> None:
        doc = {"complete": complete, "status": reason, "frames": self.frames, "written": time.strftime("%Y-%m-%d %H:%M:%S"),
               **self.notes}
        tmp = self.out / "session.json.part"
        tmp.write_text(json.dumps(doc, indent=1) + "\n")
        tmp.replace(self.out / "session.json")

    def __call__(self, obs: Observation, command: JointCommand) -> None:
        """One period (the closed loop's ``on_period``): the frame, its IMU samples, its joints."""
        if obs.fresh_image:
            self.writer.add_frame(obs.t, obs.image)
            self.frames += 1
        for t, w, a in zip(obs.imu.t, obs.imu.gyro, obs.imu.accel):
            self.writer.add_imu(t, w, a)
        self.writer.add_joints(obs.t, obs.q)

    def finish(self, complete: bool, reason: str = "complete") -> None:
        self.writer.close()
        self._status(complete, reason)
