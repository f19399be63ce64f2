"""Gaze control of the active head (paper section 5): the controller (saccades, fixation,
Paths A and B, 2D tracking), the modes it runs on each period's frozen estimate, its joint-rate
QP, the IMU attitude filter and wearer prompts."""

from .attitude import AttitudeFilter
from .estimate import GazeEstimate
from .modes import MODES, Body, Desired, Fixate, Hold, Mode, Saccade, Slave, Stabilise, Track
from .controller import ControllerSettings, GazeCommand, GazeController, GazeRefused
from .prompts import Prompt, wearer_prompt
from .qp import RateQP, RateQPSettings

__all__ = ["MODES", "AttitudeFilter", "GazeEstimate", "Body", "Desired", "Fixate", "Hold", "Mode", "Saccade", "Slave", "Stabilise", "Track", "ControllerSettings", "GazeCommand", "GazeController", "GazeRefused",
           "Prompt", "RateQP", "RateQPSettings", "wearer_prompt"]
