"""Applications over the Robot seam: the closed loop (SLAM + gaze controller + 2D trackers) that
runs the same on the twin and on the hardware rig. Nothing here imports the twin or a driver."""
