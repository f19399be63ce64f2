"""Shared helpers of the SLAM tests (not a test module): cameras, random states, central
differences, chi-square bands, and a ray-cast renderer of a printed target on a plane.

The SLAM test files import it as ``import slam_testing as st`` (pytest puts this folder on
sys.path)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from kinematics.camera import CameraIntrinsics, project, unproject
from runtime.slam.features import FEATURE_DIMS, INVERSE_DEPTH, inverse_depth
from runtime.slam.quaternion import quat_left_matrix
from runtime.slam.state import CAMERA_DIM, Q_SLICE, R_SLICE, V_SLICE, W_SLICE

PINHOLE = CameraIntrinsics(width=640, height=480, fx=514.7, fy=514.7, cx=319.5, cy=239.5)
CAMERAS = {
    "pinhole": PINHOLE,
    "brown": CameraIntrinsics(width=640, height=480, fx=500.0, fy=505.0, cx=322.0, cy=236.0,
                              model="brown", k1=-0.25, k2=0.08, p1=1e-3, p2=-5e-4, k3=-0.01),
    "fisheye": CameraIntrinsics(width=640, height=480, fx=300.0, fy=302.0, cx=318.0, cy=241.0,
                                model="fisheye", k1=0.05, k2=-0.01, k3=0.003, k4=-0.001),
    "radial-sqrt": CameraIntrinsics(width=320, height=240, fx=195.0, fy=195.0, cx=162.0, cy=125.0,
                                    model="radial-sqrt", kd1=9e-7),
}


# -- maps --------------------------------------------------------------------------------------
def feature_points(y: np.ndarray, kinds: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """(N, 3) each feature's point from the features' state ``y`` (an inverse-depth feature's
    through its conversion, at whatever depth it has: no clamp, unlike the map's own view)."""
    out, i = [], 0
    for kind, A in zip(kinds, anchors):
        d = int(FEATURE_DIMS[kind])
        out.append(inverse_depth.to_point(y[i:i + d], A)[0] if kind == INVERSE_DEPTH else y[i:i + d])
        i += d
    return np.array(out)


# -- rotations ---------------------------------------------------------------------------------

def random_quat(rng) -> np.ndarray:
    """A random unit quaternion, w x y z."""
    return Rotation.random(random_state=int(rng.integers(2**31))).as_quat()[[3, 0, 1, 2]]


def to_scipy(q) -> Rotation:
    """scipy's Rotation of a w x y z quaternion."""
    return Rotation.from_quat(np.asarray(q, float)[[1, 2, 3, 0]])


def quat_of(R) -> np.ndarray:
    """w x y z quaternion of a rotation matrix."""
    return Rotation.from_matrix(R).as_quat()[[3, 0, 1, 2]]


def rotation_error_rad(R_est, R_true) -> float:
    """Angle of R_est^T R_true, rad."""
    return float(np.linalg.norm(Rotation.from_matrix(np.asarray(R_est).T @ np.asarray(R_true)).as_rotvec()))


def tangent_basis(q) -> np.ndarray:
    """(4, 3) dq/dtheta of q * exp(theta) at 0: orthogonal to q, columns of length 1/2."""
    return quat_left_matrix(q)[:, 1:] / 2.0


def local_orientation_error(q_est, q_true) -> np.ndarray:
    """theta (3,) with R(q_true) = R(q_est) Exp(theta), rad (the estimate's own frame)."""
    return (to_scipy(q_est).inv() * to_scipy(q_true)).as_rotvec()


def orientation_covariance(P_qq, q) -> np.ndarray:
    """(3, 3) covariance of the local orientation error from the quaternion block (4, 4)."""
    Tp = 4.0 * tangent_basis(q).T          # the pseudo-inverse of dq/dtheta
    return Tp @ P_qq @ Tp.T


# -- states ------------------------------------------------------------------------------------

def random_camera(rng, w_scale: float = 1.0, cam_dim: int = CAMERA_DIM) -> np.ndarray:
    """A camera block (13, 19, 20 or 24,): random pose, velocities, (19) small biases, (20) a
    clock offset of a few ms and (24) a map's scale of 0.5-2 units per metre and gravity (9.81
    m/s^2) in a random direction of its frame."""
    x = np.concatenate([rng.normal(0, 1, 3), random_quat(rng), rng.normal(0, 0.5, 3), rng.normal(0, w_scale, 3)])
    if cam_dim > CAMERA_DIM:
        x = np.concatenate([x, rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3)])
    if cam_dim > 19:
        x = np.r_[x, rng.normal(0, 0.004)]
    if cam_dim > 20:
        u = rng.normal(size=3)
        x = np.r_[x, rng.uniform(0.5, 2.0), 9.81 * u / np.linalg.norm(u)]
    return x


def camera_covariance(q, sig_r, sig_theta, sig_v, sig_w, cam_dim: int = CAMERA_DIM, sig_bg: float = 0.01,
                      sig_ba: float = 0.1, sig_td: float = 0.005) -> np.ndarray:
    """A camera block covariance with an orientation error theta (local, rad) mapped into the
    quaternion's tangent (so P has q's norm direction as its null direction, as in the filter)."""
    P = np.zeros((cam_dim, cam_dim))
    P[R_SLICE, R_SLICE] = sig_r**2 * np.eye(3)
    T = tangent_basis(q)
    P[Q_SLICE, Q_SLICE] = sig_theta**2 * T @ T.T
    P[V_SLICE, V_SLICE] = sig_v**2 * np.eye(3)
    P[W_SLICE, W_SLICE] = sig_w**2 * np.eye(3)
    if cam_dim > CAMERA_DIM:
        P[13:16, 13:16] = sig_bg**2 * np.eye(3)
        P[16:19, 16:19] = sig_ba**2 * np.eye(3)
    if cam_dim > 19:
        P[19, 19] = sig_td**2
    if cam_dim > 20:
        P[20, 20] = 0.05**2
    return P


def state_with_points(T_world_cam: np.ndarray, points_world: np.ndarray, sigma_xyz=(0.01, 0.01, 0.01),
                      sigma_q: float = 0.01, sigma_point: float = 0.02):
    """A SLAM State: a camera at ``T_world_cam`` (4, 4) with point features ``points_world``
    (m, 3), independent Gaussian uncertainties: position ``sigma_xyz`` m per axis, quaternion
    ``sigma_q`` per component, points ``sigma_point`` m, the velocities 0.1."""
    from runtime.slam.layout import POINT
    from runtime.slam.quaternion import quat_from_rotation
    from runtime.slam.state import State

    x_v = np.zeros(CAMERA_DIM)
    x_v[0:3] = T_world_cam[:3, 3]
    x_v[3:7] = quat_from_rotation(T_world_cam[:3, :3])
    P_vv = np.eye(CAMERA_DIM) * 1e-2
    P_vv[0:3, 0:3] = np.diag(np.square(np.broadcast_to(np.asarray(sigma_xyz, float), 3)))
    P_vv[3:7, 3:7] = np.eye(4) * sigma_q**2
    s = State.from_camera(x_v, P_vv)
    m = len(points_world)
    if m:
        s.add_features([POINT] * m, np.asarray(points_world, float).ravel(), np.eye(3 * m) * sigma_point**2,
                       np.zeros((3 * m, s.n)))
    return s


def random_covariance(rng, n: int, q, scale: float = 0.02) -> np.ndarray:
    """A random full (correlated) PSD covariance (n, n) with q's block tangent to the unit
    quaternion ``q`` (rows/columns 3:7), as a running filter has it."""
    A = rng.normal(0, scale, (n, n))
    Tq = np.eye(n)
    Tq[3:7, 3:7] = np.eye(4) - np.outer(q, q)
    return Tq @ (A @ A.T + 1e-4 * np.eye(n)) @ Tq.T


# -- numerics ----------------------------------------------------------------------------------

def fd_jacobian(f, x, h: float = 1e-6) -> np.ndarray:
    """Central differences, one coordinate at a time; quaternions are perturbed in R^4 without
    renormalising, as the analytic Jacobians are defined."""
    x = np.asarray(x, dtype=float)
    cols = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((np.asarray(f(x + e), float) - np.asarray(f(x - e), float)) / (2 * h))
    return np.stack(cols, axis=-1)


def assert_jacobian(J, J_fd, rtol: float = 1e-6, atol_scale: float = 1e-6) -> None:
    """|J - J_fd| <= rtol |J_fd| + atol_scale * max|J_fd| element-wise."""
    J, J_fd = np.asarray(J), np.asarray(J_fd)
    assert J.shape == J_fd.shape, (J.shape, J_fd.shape)
    assert np.isfinite(J).all()
    tol = rtol * np.abs(J_fd) + atol_scale * max(np.abs(J_fd).max(), 1e-12)
    err = np.abs(J - J_fd)
    assert (err <= tol).all(), f"max error {err.max():.3g} at {np.unravel_index(np.argmax(err - tol), err.shape)}"


def assert_close(a, b, rel: float = 1e-9) -> None:
    """Agreement relative to the largest entry of ``b`` (covariances span many magnitudes)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, (a.shape, b.shape)
    scale = max(np.abs(b).max(), 1e-300)
    assert np.abs(a - b).max() <= rel * scale, f"relative error {np.abs(a - b).max() / scale:.3g}"


def chi2_band(dof: int, samples: int, p: float = 0.95) -> tuple[float, float]:
    """Two-sided band (probability ``p``) of the average of ``samples`` independent
    chi-square(dof) values."""
    a = (1 - p) / 2
    return chi2.ppf(a, dof * samples) / samples, chi2.ppf(1 - a, dof * samples) / samples


def pixels(cam, R_world_cam, r, X) -> np.ndarray:
    """(n, 2) pixels of world points X (n, 3) seen from the camera (R_world_cam, r)."""
    return project(cam, (np.asarray(X, float).reshape(-1, 3) - r) @ R_world_cam)


# -- a printed target on a plane ---------------------------------------------------------------

def look_at(eye, centre, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """R_world_cam of a camera at ``eye`` looking at ``centre`` (optical z forward, y down)."""
    z = np.asarray(centre, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def viewpoint(dist: float, elevation_deg: float, azimuth_deg: float = -80.0) -> tuple[np.ndarray, np.ndarray]:
    """(R_world_cam, r): a camera ``dist`` m from the origin (a target's centre on the plane
    z = 0) at ``elevation_deg`` above that plane (90: frontal), looking at it."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    r = dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return look_at(r, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0)), r


def rectangle(width: float, height: float, centre=(0.0, 0.0)) -> np.ndarray:
    """(4, 3) corners of a rectangle on the world plane z = 0, m."""
    cx, cy = centre
    w, h = width / 2, height / 2
    return np.array([[cx - w, cy - h, 0.0], [cx + w, cy - h, 0.0], [cx + w, cy + h, 0.0], [cx - w, cy + h, 0.0]])


def texture(seed: int = 0, size: int = 512, blur: float = 2.0) -> np.ndarray:
    """(size, size) float32 grey texture, 0..255: blurred noise with some structure."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (size, size)).astype(np.float32), (0, 0), blur)
    t = (t - t.mean()) / t.std()
    return np.clip(128 + 55 * t, 0, 255).astype(np.float32)


def render_target_scene(cam, R_world_cam, r, rect_xyz, card_margin: float = 0.03, background=None,
                        texture_m: float = 1.0, supersample: int = 4, edge_supersample: int = 32,
                        rect_level: float = 25.0, card_level: float = 235.0, plain_level: float = 120.0) -> np.ndarray:
    """A grey uint8 image (cam.height, cam.width) of the plane z = 0 seen from (R_world_cam, r):
    a black rectangle ``rect_xyz`` (4, 3) printed on a white card ``card_margin`` m wider on each
    side, on a background that is ``background`` (a texture spanning ``texture_m`` m around the
    origin) or plain grey. Ray-cast through the lens model and box-filtered: ``supersample``^2
    rays per pixel, ``edge_supersample``^2 in the pixels an edge of the card or the rectangle
    crosses, so edges are anti-aliased and corners sit where the geometry puts them to about
    1 / (2 edge_supersample) px (the centre of pixel (0, 0) at (0, 0))."""
    R_world_cam = np.asarray(R_world_cam, float)
    r = np.asarray(r, float)
    lo, hi = rect_xyz[:, :2].min(axis=0), rect_xyz[:, :2].max(axis=0)
    n_tex = None if background is None else background.shape[0]

    def shade(u, v):
        """Grey level and region (0 background, 1 card, 2 rectangle) of the rays at pixels (u, v)."""
        if cam.model == "brown" and not any(cam.distortion.values()):
            rays = np.column_stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(u.size)])
        else:
            rays = unproject(cam, np.column_stack([u, v]))
        rays = rays @ R_world_cam.T
        lam = -r[2] / rays[:, 2]
        ok = np.isfinite(lam) & (lam > 0)
        x, y = r[0] + lam * rays[:, 0], r[1] + lam * rays[:, 1]
        region = np.zeros(u.size, np.int8)
        region[ok & (x >= lo[0] - card_margin) & (x <= hi[0] + card_margin) & (y >= lo[1] - card_margin)
               & (y <= hi[1] + card_margin)] = 1
        region[ok & (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])] = 2
        if background is None:
            val = np.full(u.size, plain_level, np.float32)
        else:
            pad = -u.size % 1024                      # remap takes rows shorter than 32767
            mx = np.r_[(x / texture_m + 0.5) * (n_tex - 1), np.zeros(pad)].astype(np.float32).reshape(-1, 1024)
            my = np.r_[(y / texture_m + 0.5) * (n_tex - 1), np.zeros(pad)].astype(np.float32).reshape(-1, 1024)
            val = cv2.remap(background, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).ravel()[:u.size]
        val = np.where(region == 1, card_level, val)
        return np.where(region == 2, rect_level, val).astype(np.float32), region

    H, W = cam.height, cam.width
    s = int(supersample)
    off = (np.arange(s) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    du, dv = np.meshgrid(off, off)
    U = (uu[:, :, None] + du.ravel()).ravel()
    V = (vv[:, :, None] + dv.ravel()).ravel()
    val, region = shade(U, V)
    val, region = val.reshape(H, W, s * s), region.reshape(H, W, s * s)
    img = val.mean(axis=2)
    # Pixels with an edge through them (their rays disagree on the region), and their
    # neighbours (an edge may pass between the coarse rays): box-filtered finely.
    edge = (region.min(axis=2) != region.max(axis=2)).astype(np.uint8)
    edge = cv2.dilate(edge, np.ones((3, 3), np.uint8)).astype(bool)
    e = int(edge_supersample)
    off = (np.arange(e) + 0.5) / e - 0.5
    du, dv = np.meshgrid(off, off)
    ev, eu = np.nonzero(edge)
    for i in range(0, len(eu), 2048):
        U = (eu[i:i + 2048, None] + du.ravel()).ravel()
        V = (ev[i:i + 2048, None] + dv.ravel()).ravel()
        fine, _ = shade(U.astype(float), V.astype(float))
        img[ev[i:i + 2048], eu[i:i + 2048]] = fine.reshape(-1, e * e).mean(axis=1)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)
