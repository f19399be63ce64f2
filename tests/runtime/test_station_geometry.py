"""The station's geometry and camera-view drawing, against independent answers: OpenCV's own
fisheye projection, analytic rays and covariances, pixels found in the drawn image."""

import math

import cv2
import numpy as np
import pytest

from kinematics.camera import CameraIntrinsics, default_camera
from runtime.apps.station import actions as A
from runtime.apps.station.geometry import (Label, VirtualObject, ellipse_axes, ellipsoid_mesh, feature_at_pixel,
                                           feature_near_ray, pixel_ray, world_to_pixels)
from runtime.apps.station.overlay import camera_view
from runtime.apps.station.slam_view import MapView, SearchView, empty_view

FISHEYE = CameraIntrinsics(640, 480, 300.0, 300.0, 320.0, 240.0, model="fisheye", k1=0.05, k2=-0.01, k3=0.002, k4=0.0)


def look_from(eye, at):
    """T_world_cam (4, 4) of a camera at ``eye`` looking at ``at`` with world z up (image y down)."""
    z = np.asarray(at, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def view_of(T, xyz, known=None):
    n = len(xyz)
    return MapView(0.0, T, np.arange(10, 10 + n), np.asarray(xyz, float), np.tile(np.eye(3) * 1e-4, (n, 1, 1)),
                   ("point",) * n, np.zeros(n, bool) if known is None else known, np.zeros(0, int), np.zeros((0, 3)),
                   np.zeros((0, 3)), np.zeros((0, 2)), None)


T0 = look_from(np.array([0.0, -1.0, 1.0]), np.array([0.0, 0.0, 0.8]))
rng = np.random.default_rng(3)
POINTS = np.array([0.0, 0.0, 0.8]) + rng.uniform(-0.3, 0.3, (12, 3))


def test_projection_through_a_fisheye_matches_opencv():
    uv = world_to_pixels(FISHEYE, T0, POINTS)
    R_cw, t_cw = T0[:3, :3].T, -T0[:3, :3].T @ T0[:3, 3]
    ref, _ = cv2.fisheye.projectPoints(POINTS.reshape(-1, 1, 3), cv2.Rodrigues(R_cw)[0], t_cw, FISHEYE.K,
                                       np.array([FISHEYE.k1, FISHEYE.k2, FISHEYE.k3, FISHEYE.k4]))
    assert np.allclose(uv, ref.reshape(-1, 2), atol=1e-6)
    behind = world_to_pixels(FISHEYE, T0, [[0.0, -2.0, 1.0]])
    assert np.isnan(behind).all()
    assert np.isnan(world_to_pixels(FISHEYE, np.full((4, 4), np.nan), POINTS)).all()


def test_a_pixel_click_picks_the_nearest_feature_within_a_few_pixels_else_none():
    v = view_of(T0, POINTS)
    uv = world_to_pixels(FISHEYE, T0, POINTS)
    k = 5
    assert feature_at_pixel(v, FISHEYE, uv[k] + [3.0, -2.0]) == v.ids[k]
    # Far from every feature: refused, not the nearest anyway.
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.eye(len(uv)) * 1e9
    lonely = uv[k] + 30.0 * (uv[k] - uv[np.argmin(d[k])]) / np.min(d[k])
    far = np.linalg.norm(uv - lonely, axis=1).min()
    assert far > 8 and feature_at_pixel(v, FISHEYE, lonely) is None
    assert feature_at_pixel(view_of(np.full((4, 4), np.nan), POINTS), FISHEYE, uv[k]) is None


def test_the_ray_through_a_features_pixel_passes_through_it_and_picks_it():
    v = view_of(T0, POINTS)
    uv = world_to_pixels(FISHEYE, T0, POINTS)
    for k in (0, 7):
        o, d = pixel_ray(FISHEYE, T0, uv[k])
        w = POINTS[k] - o
        assert np.linalg.norm(w - (w @ d) * d) < 1e-6           # the point lies on the ray
        assert feature_near_ray(v, o, d) == v.ids[k]
    o, d = pixel_ray(FISHEYE, T0, uv[0])
    assert feature_near_ray(v, o, -d) is None                    # behind the ray's origin


def test_ellipse_and_ellipsoid_are_three_sigma():
    th = math.radians(30)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    S = R @ np.diag([16.0, 4.0]) @ R.T
    axes, ang = ellipse_axes(S)
    assert np.allclose(sorted(axes), [6.0, 12.0])
    # The first semi-axis lies along the angle (cv2.ellipse's convention): an eigenvector of S.
    d = np.array([math.cos(ang), math.sin(ang)])
    assert np.allclose(S @ d, (axes[0] / 3) ** 2 * d)
    C = np.array([[4e-4, 1e-4, 0], [1e-4, 2e-4, 0], [0, 0, 1e-4]])
    c = np.array([0.1, 0.2, 0.3])
    V, F = ellipsoid_mesh(c[None], C[None])
    m = np.einsum("ni,ij,nj->n", V - c, np.linalg.inv(C), V - c)
    assert np.allclose(m, 9.0, rtol=1e-4) and F.max() < len(V)


def test_virtual_objects_outline():
    box = VirtualObject(0, "box", np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3]))
    e = box.edges()
    assert e.shape == (12, 2, 3)
    lengths = np.sort(np.linalg.norm(e[:, 1] - e[:, 0], axis=1))
    assert np.allclose(lengths, np.repeat([0.1, 0.2, 0.3], 4))
    assert np.allclose(e.reshape(-1, 3).mean(axis=0), box.xyz)
    arrow = VirtualObject(1, "arrow", np.zeros(3), np.array([0.0, 0.0, 0.2])).edges()
    assert np.allclose(arrow[0], [[0, 0, 0], [0, 0, 0.2]])


def test_a_label_is_drawn_where_the_fisheye_lens_puts_its_point():
    lb = Label(0, POINTS[3], "here")
    img = camera_view(np.zeros((480, 640, 3), np.uint8), FISHEYE, view_of(T0, POINTS[:0]), [lb], [])
    uv = world_to_pixels(FISHEYE, T0, lb.xyz[None])[0]
    magenta = (img[..., 0] > 200) & (img[..., 1] < 40) & (img[..., 2] > 200)
    ys, xs = np.nonzero(magenta[int(uv[1]) - 7:int(uv[1]) + 8, int(uv[0]) - 7:int(uv[0]) + 8])
    # The ring's pixels surround the projected point.
    assert len(xs) > 15
    centre = np.array([xs.mean() + int(uv[0]) - 7, ys.mean() + int(uv[1]) - 7])
    assert np.linalg.norm(centre - uv) < 1.5
    # Nothing is drawn without a pose (SLAM lost).
    blank = camera_view(np.zeros((480, 640, 3), np.uint8), FISHEYE, empty_view(), [lb], [])
    assert blank.max() == 0


def test_search_ellipses_are_drawn_around_their_predictions():
    cam = default_camera()
    sv = SearchView(np.array([1]), np.array([[200.0, 150.0]]), np.array([np.diag([25.0, 4.0])]),
                    np.array([[201.0, 150.0]]), np.array([True]))
    v = view_of(T0, POINTS[:1])
    v = MapView(**{**v.__dict__, "search": sv})
    img = camera_view(np.zeros((480, 640, 3), np.uint8), cam, v, [], [])
    green = (img[..., 1] > 150) & (img[..., 0] < 80) & (img[..., 2] < 80)
    ys, xs = np.nonzero(green)
    # A 3-sigma ellipse: semi-axes 15 px (u) and 6 px (v) about (200, 150).
    assert abs(xs.max() - 215) <= 1 and abs(xs.min() - 185) <= 1
    assert abs(ys.max() - 156) <= 1 and abs(ys.min() - 144) <= 1


@pytest.mark.parametrize("kind,body,why", [
    ("fixate", {"xyz": [float("nan"), 0, 0]}, "NaN"),
    ("fixate", {"xyz": [float("inf"), 0, 0]}, "NaN or infinity"),
    ("fixate", {"xyz": [1, 2]}, "3 numbers"),
    ("fixate", {"xyz": "1,2,3"}, "3 numbers"),
    ("fixate", {"feature": True}, "integer"),
    ("fixate", {"feature": 1.5}, "integer"),
    ("fixate", {"feature": 1, "xyz": [0, 0, 0]}, "exactly one"),
    ("fixate", {}, "exactly one"),
    ("fixate", [1, 2, 3], "JSON object"),
    ("label", {"xyz": [0, 0, 0]}, "text"),
    ("label", {"xyz": [0, 0, 0], "text": "x" * 300}, "text"),
    ("object", {"kind": "sphere", "xyz": [0, 0, 0]}, "kind"),
    ("object", {"kind": "box", "xyz": [0, 0, 0], "size": [0.1, -1, 0.1]}, "positive"),
    ("mode", {"mode": "fixate"}, "mode must be"),
])
def test_malformed_actions_are_refused_with_the_reason(kind, body, why):
    with pytest.raises(A.BadAction, match=why):
        A.from_json(kind, body)


def test_well_formed_actions_parse():
    a = A.from_json("fixate", {"feature": 3})
    assert isinstance(a, A.Fixate) and a.feature == 3 and a.xyz is None
    a = A.from_json("label", {"uv": [10, 20], "text": " cup "})
    assert a.text == "cup" and np.allclose(a.uv, [10, 20])
    a = A.from_json("object", {"kind": "arrow", "feature": 2})
    assert a.kind == "arrow" and a.feature == 2 and np.linalg.norm(a.size) > 0
    assert isinstance(A.from_json("stop", None), A.Stop) and isinstance(A.from_json("reset", {}), A.Reset)
