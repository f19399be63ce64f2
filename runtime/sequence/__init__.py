"""Image sequences, trajectories and sensor logs in the layout of shared/formats.md.

A sequence is a folder in the TUM RGB-D layout plus two small TOML files::

    SEQ/
      rgb.txt          "timestamp path" per line, '#' comments, paths relative to SEQ
      rgb/<t>.png      8-bit (or 16-bit) colour or grey images
      camera.toml      intrinsics (kinematics.camera), required
      target.toml      optional: >= 4 known world points and their pixels in the first frame
      groundtruth.txt  optional: "timestamp tx ty tz qx qy qz qw", camera-to-world
      imu.txt          optional: "timestamp wx wy wz ax ay az", rad/s and m/s^2, camera frame
      joints.txt       optional: "timestamp q_elevation q_pan q_cyclotorsion", rad
      depth.txt        optional: "timestamp path" of depth/<t>.png, TUM RGB-D's 16-bit depth
                       images (z along the optic axis, metres x 5000; 0 = no depth), for
                       evaluating maps (the twin renders them)

Frames and units
----------------
world
    the frame the target (or the ground truth) fixes; metres.
cam
    the camera's optical frame: x right, y down, z forward along the optic axis.
``T_world_cam``
    (4, 4) homogeneous transform mapping optical-frame coordinates to world coordinates: its
    translation is the optical centre in the world, its rotation takes cam axes to world axes.
    Trajectory files store it as TUM does: position, then the unit quaternion in x y z w order.
Times are seconds (float); angles radians; pixels in the OpenCV convention.

Errors in files raise :class:`SequenceError`, one line naming the file, the line or field and
the fix. Bad images never raise: :meth:`Sequence.frames` yields them with ``image=None`` and a
``problem`` so that a long recording with a few broken frames still runs.

The package's parts: :mod:`.types` (the records: Trajectory, ImuLog, JointLog, Target, Frame),
:mod:`.textfiles` (the TUM-style text files and target.toml), :mod:`.reader` (a sequence
folder) and :mod:`.writer` (recording one). Import the names from ``runtime.sequence``.
"""

from .reader import Sequence, open_sequence
from .textfiles import (load_target, read_imu, read_joints, read_trajectory, save_target, write_imu, write_joints,
                        write_trajectory)
from .types import (DEPTH_SCALE, IMU_COLUMNS, JOINT_COLUMNS, MIN_TARGET_POINTS, QUATERNION_NORM_TOL, RECORDING, ROTATION_TOL,
                    TRAJECTORY_COLUMNS, Frame, ImuLog, JointLog, SequenceError, Target, Trajectory)
from .writer import SequenceWriter, check_new_recording

__all__ = [
    "DEPTH_SCALE", "IMU_COLUMNS", "JOINT_COLUMNS", "MIN_TARGET_POINTS", "QUATERNION_NORM_TOL", "RECORDING", "ROTATION_TOL",
    "TRAJECTORY_COLUMNS", "Frame", "ImuLog", "JointLog", "Sequence", "SequenceError", "SequenceWriter", "Target",
    "Trajectory", "check_new_recording", "load_target", "open_sequence", "read_imu", "read_joints",
    "read_trajectory", "save_target", "write_imu", "write_joints", "write_trajectory",
]
