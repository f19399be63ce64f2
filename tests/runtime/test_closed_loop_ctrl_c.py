"""Ctrl-C stops the closed loop at the next period even when the signal lands inside a library
call that swallows the KeyboardInterrupt (a solver turning it into an ordinary failure)."""

from __future__ import annotations

import os
import signal

import numpy as np

from runtime.apps.closed_loop import Task, run_closed_loop
from test_station_api import TARGET_XYZ, StillRobot


class SwallowingRobot(StillRobot):
    """At its 5th period a SIGINT arrives while a library call that catches everything runs."""

    def step(self, command):
        if len(self.commands) == 4:
            try:
                os.kill(os.getpid(), signal.SIGINT)
                for _ in range(1000):      # the handler runs between bytecodes, here
                    pass
            except BaseException:          # noqa: BLE001 - the library's own catch-all
                pass
        return super().step(command)


def test_ctrl_c_inside_a_swallowing_call_still_stops_the_loop(tmp_path):
    robot = SwallowingRobot()
    old = signal.getsignal(signal.SIGINT)
    s = run_closed_loop(robot, Task("fixate", TARGET_XYZ.mean(axis=0)[None]), tmp_path, start_target=robot.target,
                        seconds=3.0, progress=False)
    assert s["ended"] == "stopped by Ctrl-C"
    assert 5 <= s["frames"] <= 7 < 60
    assert signal.getsignal(signal.SIGINT) is old        # the loop gives the handler back
    assert np.isfinite(robot.commands).all()
