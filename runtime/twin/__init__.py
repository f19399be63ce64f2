"""The MuJoCo twin: the wearer, the chosen head on the chosen mount, in a place (a workbench, a
kitchen counter, an office desk), with a real IMU's errors and a real camera's blur, exposure and
noise; records sequences in the shared format and runs closed loop (reset, step) for controllers."""

import os

# The twin renders offscreen; EGL unless the user chose another MuJoCo GL backend. This must
# happen before mujoco is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")
