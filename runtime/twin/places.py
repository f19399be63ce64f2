"""The kinds of place a scenario happens in, each with its known target and the points its
gaze scripts look at (``target_corners``, ``look_point``, ``sweep_axes``, ``follow_point``,
``away_point``): the workbench, the kitchen counter and the office desk."""

from __future__ import annotations

from .kitchen import KitchenCounter
from .office import OfficeDesk
from .workbench import Workbench

Place = Workbench | KitchenCounter | OfficeDesk

__all__ = ["Place", "Workbench", "KitchenCounter", "OfficeDesk"]
