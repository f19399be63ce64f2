"""Gaze control of the active head (paper section 5): the controller (saccades, fixation,
Paths A and B, 2D tracking), its joint-rate QP, the IMU attitude filter and wearer prompts."""

from .attitude import AttitudeFilter
from .modes import MODES, Body, Desired, Fixate, Hold, Mode, Saccade, Slave, Stabilise, Track
from .controller import ControllerSettings, GazeCommand, GazeController, GazeRefused
from .prompts import Prompt, wearer_prompt
from .qp import RateQP, RateQPSettings

__all__ = ["MODES", "AttitudeFilter", "Body", "Desired", "Fixate", "Hold", "Mode", "Saccade", "Slave", "Stabilise", "Track", "ControllerSettings", "GazeCommand", "GazeController", "GazeRefused",
           "Prompt", "RateQP", "RateQPSettings", "wearer_prompt"]
