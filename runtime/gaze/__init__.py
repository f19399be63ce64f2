"""Gaze control of the active head (paper section 5): the controller (saccades, fixation,
Paths A and B, 2D tracking), its joint-rate QP, the IMU attitude filter and wearer prompts."""

from .attitude import AttitudeFilter
from .controller import MODES, ControllerSettings, GazeCommand, GazeController, GazeRefused
from .prompts import Prompt, wearer_prompt
from .qp import RateQP, RateQPSettings

__all__ = ["MODES", "AttitudeFilter", "ControllerSettings", "GazeCommand", "GazeController", "GazeRefused",
           "Prompt", "RateQP", "RateQPSettings", "wearer_prompt"]
