"""The inverse-depth feature (Civera, Davison and Montiel, "Inverse Depth Parametrization for
Monocular SLAM", IEEE T-RO 2008).

``y = (c, theta, phi, rho)``, 6 numbers: ``c`` (3,) the optical centre of the camera that first
saw it (world, m), ``theta`` and ``phi`` the azimuth and elevation of its ray (rad), ``rho`` the
inverse of its depth along the ray (1/m). The point is ``c + m(theta, phi) / rho`` with::

    m = A (cos(phi) sin(theta), -sin(phi), cos(phi) cos(theta))

``A`` is the feature's constant anchor rotation (state.py): the orientation of the camera that
first saw it, so the angles are those of the first view's optical frame, as in Civera et al.'s
world frame (which was the first camera's). Their singularity (a ray along the anchor's y axis,
90 degrees from the first view's optic axis) is never reached by a feature seen in that view.

Undelayed initialisation: the feature enters the state at its first observation with
``rho = rho0`` and a ``sigma_rho`` wide enough that its 95% interval holds depths from the near
limit to infinity (``rho = 0``): it is measured from its first frame, giving orientation at
once and depth as parallax accumulates, distant points included. Once the map has depths,
``rho0`` is the median inverse depth of the points matched in the frame, its width at least their
spread (:func:`scene_prior`).

Measurement (scale-free because projection is)::

    h_C = R(q)^T (rho (c - r) + m)      h = project(cam, h_C)

Jacobians: ``d h_C/dr = -rho R^T``, ``d h_C/dq_i = (dR/dq_i)^T (rho (c - r) + m)``,
``d h_C/dc = rho R^T``, ``d h_C/dtheta = R^T dm/dtheta``, ``d h_C/dphi = R^T dm/dphi``,
``d h_C/drho = R^T (c - r)``.

Conversion to a point (section VI of the paper): when the linearity index
``L_d = 4 sigma_d |cos(alpha)| / d1`` (``sigma_d = sigma_rho / rho^2``, ``d1`` the distance from
the current camera, ``alpha`` the angle between ``m`` and the current ray) is below a threshold
(0.1), the depth is well represented by a Gaussian and the feature becomes a 3D point:
``p = c + m / rho`` with its Jacobian.
"""

from __future__ import annotations

import math

import numpy as np

from kinematics.camera import CameraIntrinsics, unproject_jacobian

from ..kernels import compiled_kernel
from ..quaternion import quat_to_rotation, rotation_derivatives
from ..layout import INVERSE_DEPTH, POSE_DIM, Q_SLICE, R_SLICE
from .ray import ray_kernel

KIND = INVERSE_DEPTH
DIM = 6


@compiled_kernel()
def direction_kernel(theta, phi):
    """m(theta, phi) (3,) in the anchor frame and its derivatives dm/dtheta, dm/dphi."""
    ct, st, cp, sp = math.cos(theta), math.sin(theta), math.cos(phi), math.sin(phi)
    m = np.array([cp * st, -sp, cp * ct])
    dm_dt = np.array([cp * ct, 0.0, -cp * st])
    dm_dp = np.array([-sp * st, -cp, -sp * ct])
    return m, dm_dt, dm_dp


@compiled_kernel(ray_kernel, direction_kernel)
def h_kernel(x, s, anchor, R, dR, model, lens, uv, H_c, H_f):
    """The inverse-depth feature ``x[s:s+6]`` (anchor rotation ``anchor``) seen from the camera
    ``x[0:7]``; as :func:`runtime.slam.features.point.h_kernel`, writing ``H_f[:, :6]``."""
    m_a, dm_dt_a, dm_dp_a = direction_kernel(x[s + 3], x[s + 4])
    rho = x[s + 5]
    m = anchor @ m_a
    dm_dt = anchor @ dm_dt_a
    dm_dp = anchor @ dm_dp_a
    e0, e1, e2 = x[s] - x[0], x[s + 1] - x[1], x[s + 2] - x[2]        # c - r
    # d = rho (c - r) + m(theta, phi): d(d)/dr = -rho I, d(d)/dc = rho I. The ray writes its
    # J R^T into H_f[:, :3], which the loop below turns into d(uv)/dc.
    if not ray_kernel(rho * e0 + m[0], rho * e1 + m[1], rho * e2 + m[2], rho, R, dR, model, lens, uv, H_c, H_f):
        return False
    for a in range(2):
        ht = hp = hr = 0.0
        for c in range(3):
            jr = H_f[a, c]
            H_f[a, c] = rho * jr
            ht += jr * dm_dt[c]
            hp += jr * dm_dp[c]
            hr += jr * (e0 if c == 0 else (e1 if c == 1 else e2))
        H_f[a, 3] = ht
        H_f[a, 4] = hp
        H_f[a, 5] = hr
    return True


@compiled_kernel(direction_kernel)
def points_and_linearity_kernel(x, P, kinds, starts, anchors, r, rho_min):
    """For every feature of the state: its point (N, 3) (inverse-depth ones at
    ``max(rho, rho_min)``) and, for inverse-depth ones, the linearity index seen from ``r``
    (inf for points and for rho <= 0)."""
    n = kinds.shape[0]
    Y = np.empty((n, 3))
    L = np.full(n, np.inf)
    for k in range(n):
        s = starts[k]
        if kinds[k] != INVERSE_DEPTH:
            Y[k, 0], Y[k, 1], Y[k, 2] = x[s], x[s + 1], x[s + 2]
            continue
        m_a, _, _ = direction_kernel(x[s + 3], x[s + 4])
        m = anchors[k] @ m_a
        rho = x[s + 5]
        rr = max(rho, rho_min)
        for i in range(3):
            Y[k, i] = x[s + i] + m[i] / rr
        if rho > 0:
            h0, h1, h2 = x[s] + m[0] / rho - r[0], x[s + 1] + m[1] / rho - r[1], x[s + 2] + m[2] / rho - r[2]
            d1 = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
            if d1 > 1e-12:
                cos_a = (m[0] * h0 + m[1] * h1 + m[2] * h2) / d1
                sigma_rho = math.sqrt(max(P[s + 5, s + 5], 0.0))
                L[k] = 4.0 * (sigma_rho / (rho * rho)) * abs(cos_a) / d1
    return Y, L


def world_point(y, anchor) -> np.ndarray:
    """(3,) ``c + m / rho`` (the point the feature stands for; infinite for rho = 0)."""
    y = np.asarray(y, float)
    m, _, _ = direction_kernel(float(y[3]), float(y[4]))
    return y[:3] + (np.asarray(anchor, float) @ m) / y[5]


def to_point(y, anchor) -> tuple[np.ndarray, np.ndarray]:
    """The 3D point ``p = c + m / rho`` (3,) and its Jacobian dp/dy (3, 6)."""
    y = np.asarray(y, float)
    A = np.asarray(anchor, float)
    m_a, dt, dp = direction_kernel(float(y[3]), float(y[4]))
    rho = float(y[5])
    m = A @ m_a
    J = np.zeros((3, 6))
    J[:, :3] = np.eye(3)
    J[:, 3] = A @ dt / rho
    J[:, 4] = A @ dp / rho
    J[:, 5] = -m / rho**2
    return y[:3] + m / rho, J


def linearity_index(y, anchor, sigma_rho: float, r_cam) -> float:
    """Civera et al.'s depth linearity index ``L_d = 4 sigma_d |cos(alpha)| / d1`` of the
    feature seen from the camera centre ``r_cam`` (3,): small (< 0.1) when the depth is well
    represented by a Gaussian in Euclidean coordinates."""
    y = np.asarray(y, float)
    rho = float(y[5])
    if not rho > 0:
        return math.inf
    m, _, _ = direction_kernel(float(y[3]), float(y[4]))
    m = np.asarray(anchor, float) @ m
    h = y[:3] + m / rho - np.asarray(r_cam, float)
    d1 = float(np.linalg.norm(h))
    cos_a = float(m @ h) / max(d1, 1e-12)
    return 4.0 * (sigma_rho / rho**2) * abs(cos_a) / max(d1, 1e-12)


def scene_prior(Y, r_cam, rho0: float, sigma_rho: float, min_points: int = 5, spread: bool = True,
                relative_width: float | None = None) -> tuple[float, float]:
    """A new feature's inverse-depth prior (mean, standard deviation), 1/m, from the points ``Y``
    (k, 3) (world, m) just matched from the camera centre ``r_cam`` (3,): the median of their
    inverse distances, with the relative width ``relative_width`` (default the configured prior's
    ``sigma_rho / rho0``) or, with ``spread``, the points' own spread of inverse distances (half
    their 16th-84th percentile range) where that is wider. With fewer than ``min_points`` finite
    points, the configured ``(rho0, sigma_rho)``.

    A fixed mean pulls a monocular map's scale towards its depth: features start at it, and
    until their parallax outweighs it the camera's translation is read at that depth's scale.
    Centred on the depths the map already holds, a new feature agrees with the map's scale and
    pulls it nowhere. In a deep scene (a hall seen past a near pallet, a road) a new feature may
    lie anywhere in the scene's depths, and a prior narrower than they are pulls the scale as a
    wrong mean would (benchmarks/NOTES.md: MH_01's first second ran at half the later scale).
    The width must also reach what the matched points do not show: a new feature goes where no
    feature is, and may be much nearer than any (a pallet the camera approaches): with a
    relative width w the 95% interval reaches depths down to 1 / (1 + 2w) of the median."""
    Y = np.asarray(Y, float).reshape(-1, 3)
    d = np.linalg.norm(Y - np.asarray(r_cam, float), axis=1)
    rho = 1.0 / d[np.isfinite(d) & (d > 0)]
    if len(rho) < min_points:
        return float(rho0), float(sigma_rho)
    lo, mean, hi = (float(v) for v in np.percentile(rho, [16, 50, 84]))
    sigma = mean * (float(sigma_rho) / float(rho0) if relative_width is None else float(relative_width))
    return mean, max(sigma, 0.5 * (hi - lo)) if spread else sigma


def angles_and_jacobian(h) -> tuple[float, float, np.ndarray]:
    """theta, phi of a ray ``h`` (3,) (any length) in the anchor frame, and d(theta, phi)/dh (2, 3)."""
    hx, hy, hz = (float(v) for v in h)
    sxz = hx * hx + hz * hz
    nxz = math.sqrt(sxz)
    n2 = sxz + hy * hy
    J = np.array([[hz / sxz, 0.0, -hx / sxz],
                  [hy * hx / (n2 * nxz), -nxz / n2, hy * hz / (n2 * nxz)]])
    return math.atan2(hx, hz), math.atan2(-hy, nxz), J


def init_from_pixel(x_v, uv, cam: CameraIntrinsics, rho0: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A new inverse-depth feature at pixel ``uv`` seen from the camera ``x_v`` (its first 7
    numbers: r, q), inverse depth ``rho0``.

    Returns y (6,), the anchor (3, 3) = R(q), dy/dx_v (6, len(x_v)) (only the r and q columns
    are nonzero) and dy/duv (6, 2); rho's own prior variance is added by the caller. The angles
    are those of the ray in the first view's optical frame; their dependence on q goes through
    ``A^T R(q) h`` with the anchor ``A`` held at the current estimate.
    """
    y, A, J_x, J_uv = init_from_pixels(x_v, np.asarray(uv, float).reshape(1, 2), cam, rho0)
    return y[0], A, J_x[0], J_uv[0]


def init_from_pixels(x_v, uvs, cam: CameraIntrinsics, rho0: float,
                     rays: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`init_from_pixel` for the pixels ``uvs`` (m, 2) seen from one camera, the lens
    inverted once for all: y (m, 6), the anchor (3, 3) they share, dy/dx_v (m, 6, len(x_v)) and
    dy/duv (m, 6, 2). A pixel the lens cannot unproject gives NaN rows. ``rays``: the pixels'
    ``unproject_jacobian`` (rays (m, 3), J (m, 3, 2)), if the caller has it."""
    x_v = np.asarray(x_v, float)
    q = x_v[Q_SLICE]
    A = quat_to_rotation(q)
    uvs = np.asarray(uvs, float).reshape(-1, 2)
    m = len(uvs)
    # (m, 3), (m, 3, 2): the rays (z > 0) and their Jacobians, unless the caller has them
    rays, J_rays = unproject_jacobian(cam, uvs) if rays is None else rays
    dR = rotation_derivatives(q)                      # m_a(q) = A^T R(q) h_c
    AdR = np.einsum("ji,kjl->kil", A, dR)             # (4, 3, 3): A^T dR_k
    y = np.empty((m, 6))
    y[:, :3] = x_v[R_SLICE]
    J_x = np.zeros((m, 6, len(x_v)))
    J_x[:, 0:3, R_SLICE] = np.eye(3)
    J_uv = np.zeros((m, 6, 2))
    for i in range(m):
        h_c = rays[i]
        theta, phi, J_ang = angles_and_jacobian(h_c)  # the anchor is this camera: m_a = h_c
        y[i, 3:] = theta, phi, rho0
        J_x[i, 3:5, Q_SLICE] = J_ang @ (AdR @ h_c).T
        J_uv[i, 3:5] = J_ang @ J_rays[i]
    assert J_x.shape[2] >= POSE_DIM
    return y, A, J_x, J_uv
