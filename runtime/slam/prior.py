"""The camera block's prior, built in one place for the start-up from the target, the restart at
a pose found against the map (re-localisation, re-acquisition) and a saved map's session."""

from __future__ import annotations

import numpy as np

from .layout import (BA_SLICE, BG_SLICE, CAMERA_DIM_BIASED, CAMERA_DIM_SCALED, CAMERA_DIM_TIMED, G_SLICE, POSE_DIM,
                     SCALE_INDEX, TD_INDEX, check_camera_dim)
from .inertial import GRAVITY
from .quaternion import dq_dtheta_right


def pose_covariance(q: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(7, 7) the covariance of (r, q) from ``cov`` (6, 6) of (small rotation in the camera
    frame, rad; position, m), the rotation mapped by dq/dtheta at the unit quaternion ``q``."""
    G = np.zeros((POSE_DIM, 6))
    G[0:3, 3:6] = np.eye(3)
    G[3:7, 0:3] = dq_dtheta_right(q)
    return G @ cov @ G.T


def camera_prior(cam_dim: int, r, q, P_pose: np.ndarray, sigma_v: float, sigma_w: float, cfg=None,
                 still=None, gyro_bias=None, gyro_bias_sigma: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The camera block (cam_dim,) at rest at position ``r`` (3,) (world, m) and attitude ``q``
    (4,) (w x y z), and its covariance (cam_dim, cam_dim): ``P_pose`` (7, 7) on (r, q),
    velocities with standard deviations ``sigma_v`` (m/s) and ``sigma_w`` (rad/s).

    With bias states and ``cfg`` (SlamConfig): the biases' and the clock offset's priors
    (``gyro_bias_sigma0``, ``accel_bias_sigma0``, ``time_offset0``, ``time_offset_sigma0``);
    with ``still`` (inertial.StillBiases, made at ``q``) the biases a still stretch gave, the
    accelerometer's correlated with the attitude it was read through (as a new feature is with
    the camera), so that refining the attitude refines it; with ``gyro_bias`` (3,) rad/s, a start's
    own estimate of the gyro's bias with standard deviation ``gyro_bias_sigma``, that one for the
    gyro's. Without ``cfg`` the bias entries are left zero. The map's scale ``k`` and gravity
    ``g`` (a 24-number block) start at 1 and the world's gravity with no variance: nothing
    observes them until the IMU is handed the map (imu_handover.py sets them from the IMU's
    estimate)."""
    cam_dim = check_camera_dim(cam_dim)
    x_v = np.zeros(cam_dim)
    x_v[0:3], x_v[3:7] = r, q
    if cam_dim == CAMERA_DIM_SCALED:
        x_v[SCALE_INDEX] = 1.0
        x_v[G_SLICE] = GRAVITY
    P = np.zeros((cam_dim, cam_dim))
    P[:7, :7] = P_pose
    P[7:10, 7:10] = np.eye(3) * sigma_v**2
    P[10:13, 10:13] = np.eye(3) * sigma_w**2
    if cam_dim < CAMERA_DIM_BIASED or cfg is None:
        return x_v, P
    for sl, s0 in ((BG_SLICE, cfg.imu.gyro_bias_sigma0), (BA_SLICE, cfg.imu.accel_bias_sigma0)):
        P[sl, sl] = np.eye(3) * s0**2
    if cam_dim >= CAMERA_DIM_TIMED:
        x_v[TD_INDEX], P[TD_INDEX, TD_INDEX] = cfg.imu.time_offset0, cfg.imu.time_offset_sigma0**2
    if still is not None:
        x_v[BG_SLICE], P[BG_SLICE, BG_SLICE] = still.b_g, np.eye(3) * still.var_g
        J = np.zeros((3, cam_dim))
        J[:, 3:7] = still.J_q
        P[BA_SLICE, :] = 0.0
        P[:, BA_SLICE] = 0.0
        P_ax = J @ P
        x_v[BA_SLICE] = still.b_a
        P[BA_SLICE, :] = P_ax
        P[:, BA_SLICE] = P_ax.T
        P[BA_SLICE, BA_SLICE] = J @ P_ax.T + np.eye(3) * still.var_f
    if gyro_bias is not None:
        # Over a still stretch's mean rate: a still wearer's sway turns the camera by a degree a
        # second, which that mean takes in (the gyro's bias has no cross-covariance here).
        x_v[BG_SLICE], P[BG_SLICE, BG_SLICE] = gyro_bias, np.eye(3) * gyro_bias_sigma**2
    return x_v, P


#: A saved map's camera before re-localisation: wide enough that nothing is searched by it.
UNKNOWN_POSE_VARIANCES = np.r_[np.full(3, 1.0), np.full(4, 0.25)]
UNKNOWN_SIGMA_V = 0.3
UNKNOWN_SIGMA_W = 0.5


def restart_at(state, hyp, sigma_v: float, sigma_w: float, w: np.ndarray | None = None) -> None:
    """Put the camera of ``state`` at a pose ``hyp`` (startup.PoseHypothesis) found against the
    map (re-localisation, the target's re-acquisition), at rest (or turning at ``w`` (3,),
    rad/s) with velocity standard deviations ``sigma_v``, ``sigma_w``, with no correlation to the
    map; bias estimates are kept."""
    x_v, P_vv = hyp.camera_prior(sigma_v, sigma_w, state.cam_dim)
    if w is not None:
        x_v[10:13] = w
    state.restart_camera(x_v, P_vv)
