"""kinematics: the elevation-pan-cyclotorsion head shared by design, the twin and the runtime.

One model of the head (paper, section 2): its geometry and head.toml, forward kinematics and
Jacobians, gaze IK with the image-vertical rule, servo models and the command filter, rigid-body
dynamics of the parts, camera intrinsics, and the MJCF builder.
"""

from .chain import ChainPose, angular_jacobian, forward_kinematics, optical_centre_jacobian, point_jacobian
from .dynamics import gravity_torque, inverse_dynamics, link_inertias
from .gaze_ik import GazeResult, GazeSolution, gaze_at_direction, gaze_at_point
from .geometry import (
    JOINT_NAMES, CameraMount, HeadFileError, HeadGeometry, Joint, Part, load_head, reference_head, save_head,
)
from .servo import ServoCommandError, ServoFilter, filter_sequence
from .servo_models import HS50, SERVO_CATALOGUE, ServoModel

__all__ = [
    "JOINT_NAMES", "CameraMount", "ChainPose", "GazeResult", "GazeSolution", "HS50", "HeadFileError",
    "HeadGeometry", "Joint", "Part", "SERVO_CATALOGUE", "ServoCommandError", "ServoFilter", "ServoModel",
    "angular_jacobian", "filter_sequence", "forward_kinematics", "gaze_at_direction", "gaze_at_point",
    "gravity_torque", "inverse_dynamics", "link_inertias", "load_head", "optical_centre_jacobian",
    "point_jacobian", "reference_head", "save_head",
]
