"""Drivers for the real head (paper, section 2): the Pololu Maestro servo controller or Dynamixel
X-series smart servos, the camera (OpenCV VideoCapture, files, image patterns), the IMU (BNO085
UART-RVC, a text line protocol) and the rig (rig.toml -> a :class:`runtime.robot.Robot`, driven
through the safety chain of :mod:`runtime.safety`)."""


class DriverError(RuntimeError):
    """A device fault or a bad device setting, with a one-line message naming the device, the
    problem and what to do (the CLI prints it and exits with status 2)."""
