"""Single-camera EKF SLAM (MonoSLAM, Davison 2003/2007; paper section 4): the state layout and
covariance (state.py), the constant-velocity motion model (motion.py), the projective
measurement model and feature initialisation geometry (measurement.py) and the EKF predict /
update steps (filter.py)."""
