"""Tests for kinematics.camera: OpenCV agreement, inverses, Jacobians, camera.toml."""

from __future__ import annotations

import math
import tomllib

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics.camera import (
    DEFAULT_CAMERA,
    LENS_MODELS,
    CameraFileError,
    CameraIntrinsics,
    default_camera,
    distort,
    distort_jacobian,
    fov_x_rad,
    fov_y_rad,
    in_image,
    load_camera,
    project,
    project_jacobian,
    save_camera,
    undistort,
    undistort_jacobian,
    unproject,
    unproject_jacobian,
)

FAST = settings(max_examples=30, deadline=None)
N = 200  # points per example


# -- strategies --------------------------------------------------------------------------------

def _nonzero(lo: float, hi: float):
    """A coefficient of magnitude in [lo, hi], either sign (so distortion is never zero)."""
    return st.tuples(st.sampled_from([-1.0, 1.0]), st.floats(lo, hi)).map(lambda t: t[0] * t[1])


@st.composite
def pinholes(draw) -> dict:
    fx = draw(st.floats(300.0, 900.0))
    return dict(width=640, height=480, fx=fx, fy=fx * draw(st.floats(0.95, 1.05)),
                cx=319.5 + draw(st.floats(-20.0, 20.0)), cy=239.5 + draw(st.floats(-20.0, 20.0)))


def brown_cameras(strong: bool = False):
    """strong: wider coefficient ranges (still realistic) for the comparison with OpenCV; the
    default ranges keep the lens one-to-one over the test points, as the inverse needs."""
    s = 1.6 if strong else 1.0
    return st.builds(lambda p, k1, k2, p1, p2, k3: CameraIntrinsics(
        **p, model="brown", k1=k1, k2=k2, p1=p1, p2=p2, k3=k3),
        pinholes(), _nonzero(0.02, 0.3 * s), _nonzero(0.005, 0.1 * s), _nonzero(1e-4, 0.005 * s),
        _nonzero(1e-4, 0.005 * s), _nonzero(1e-3, 0.02 * s))


def fisheye_cameras():
    return st.builds(lambda p, k1, k2, k3, k4: CameraIntrinsics(
        **p, model="fisheye", k1=k1, k2=k2, k3=k3, k4=k4),
        pinholes(), _nonzero(0.005, 0.1), _nonzero(0.001, 0.05), _nonzero(1e-4, 0.01), _nonzero(1e-4, 0.01))


def radial_sqrt_cameras():
    # kd1 up to 2.5e-6 px^-2 keeps 1 - 2 kd1 r_d^2 > 0 at the corners (r_d <= ~430 px).
    return st.builds(lambda p, kd1: CameraIntrinsics(**p, model="radial-sqrt", kd1=kd1),
                     pinholes(), _nonzero(1e-8, 2.5e-6))


CAMERAS = {"brown": brown_cameras(), "fisheye": fisheye_cameras(), "radial-sqrt": radial_sqrt_cameras()}
seeds = st.integers(0, 2**32 - 1)


def normalised_points(cam: CameraIntrinsics, seed: int, n: int = N) -> np.ndarray:
    """(n, 2) undistorted normalised points that the camera's lens maps one-to-one."""
    rng = np.random.default_rng(seed)
    if cam.model == "fisheye":
        # Up to 1 rad (57 deg) off axis: a wide lens, still where theta_d(theta) is increasing.
        theta, phi = rng.uniform(0.0, 1.0, n), rng.uniform(-np.pi, np.pi, n)
        return np.tan(theta)[:, None] * np.column_stack([np.cos(phi), np.sin(phi)])
    if cam.model == "brown":
        # A 64 x 48 degree view (r <= 0.75), where the test coefficients keep r_d(r) increasing.
        return rng.uniform([-0.6, -0.45], [0.6, 0.45], (n, 2))
    # radial-sqrt: undistorted pixel offsets within a 640x480 frame around the principal point.
    e = rng.uniform([-320.0, -240.0], [320.0, 240.0], (n, 2))
    return e / [cam.fx, cam.fy]


def points_3d(cam: CameraIntrinsics, seed: int, n: int = N) -> np.ndarray:
    """(n, 3) points in front of the camera, 0.3 to 5 m deep, in the optical frame."""
    depth = np.random.default_rng(seed + 1).uniform(0.3, 5.0, n)
    xy = normalised_points(cam, seed, n)
    return np.column_stack([xy, np.ones(n)]) * depth[:, None]


def fd_jacobian(f, X: np.ndarray, h: float) -> np.ndarray:
    """Central differences of f: (N, d) -> (N, m), giving (N, m, d)."""
    cols = []
    for j in range(X.shape[1]):
        dX = np.zeros_like(X)
        dX[:, j] = h
        cols.append((f(X + dX) - f(X - dX)) / (2.0 * h))
    return np.stack(cols, axis=-1)


def assert_jacobian(J: np.ndarray, J_fd: np.ndarray, rtol: float = 1e-6) -> None:
    """Relative agreement, each point's matrix scaled by its largest entry (entries can be ~0)."""
    assert J.shape == J_fd.shape
    assert np.isfinite(J).all()
    scale = np.abs(J_fd).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(J - J_fd) <= rtol * scale), (np.abs(J - J_fd) / scale).max()


# -- agreement with OpenCV ---------------------------------------------------------------------

@FAST
@given(brown_cameras(strong=True), seeds)
def test_brown_matches_cv2_project_points(cam, seed):
    P = points_3d(cam, seed)
    P[:, :2] *= 1.3  # a little beyond the frame too
    dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3])
    ref = cv2.projectPoints(P, np.zeros(3), np.zeros(3), cam.K, dist)[0][:, 0, :]
    np.testing.assert_allclose(project(cam, P), ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(distort(cam, P[:, :2] / P[:, 2:]), ref, rtol=0, atol=1e-9)


@FAST
@given(fisheye_cameras(), seeds)
def test_fisheye_matches_cv2_fisheye_project_points(cam, seed):
    P = points_3d(cam, seed)
    P[0] = [0.0, 0.0, 2.0]  # on the axis, where cv2 special-cases r < 1e-8
    D = np.array([cam.k1, cam.k2, cam.k3, cam.k4])
    ref = cv2.fisheye.projectPoints(P[:, None, :], np.zeros(3), np.zeros(3), cam.K, D)[0][:, 0, :]
    np.testing.assert_allclose(project(cam, P), ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(distort(cam, P[:, :2] / P[:, 2:]), ref, rtol=0, atol=1e-9)


# -- radial-sqrt (MonoSLAM) --------------------------------------------------------------------

def formats_md_inverse(cam: CameraIntrinsics, d: np.ndarray) -> np.ndarray:
    """The closed form printed in formats.md, written out independently of the module."""
    c = np.array([cam.cx, cam.cy])
    rd2 = np.sum((d - c) ** 2, axis=1, keepdims=True)
    return c + (d - c) / np.sqrt(1.0 - 2.0 * cam.kd1 * rd2)


@FAST
@given(radial_sqrt_cameras(), seeds)
def test_radial_sqrt_formats_md_inverse_undoes_distort(cam, seed):
    xy = normalised_points(cam, seed)
    undistorted_px = xy * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    np.testing.assert_allclose(formats_md_inverse(cam, distort(cam, xy)), undistorted_px, rtol=0, atol=1e-9)


def test_radial_sqrt_analytic_point():
    cam = CameraIntrinsics(640, 480, 500.0, 500.0, 320.0, 240.0, model="radial-sqrt", kd1=1e-6)
    # (x, y) = (0.6, 0.8) is (300, 400) px from the centre: r = 500 px, 1 + 2 kd1 r^2 = 1.5.
    uv = distort(cam, [[0.6, 0.8]])
    expected = np.array([[320.0 + 300.0 / math.sqrt(1.5), 240.0 + 400.0 / math.sqrt(1.5)]])
    np.testing.assert_allclose(uv, expected, rtol=0, atol=1e-12)
    assert np.hypot(*(uv[0] - [320.0, 240.0])) == pytest.approx(500.0 / math.sqrt(1.5), abs=1e-12)
    # Inverse at r_d^2 = 250000 / 1.5: 1 - 2 kd1 r_d^2 = 2/3 exactly.
    np.testing.assert_allclose(undistort(cam, uv), [[0.6, 0.8]], rtol=0, atol=1e-15)
    # The centre maps to itself.
    np.testing.assert_array_equal(distort(cam, [[0.0, 0.0]]), [[320.0, 240.0]])


def test_radial_sqrt_outside_forward_domain_is_nan():
    cam = CameraIntrinsics(640, 480, 500.0, 500.0, 320.0, 240.0, model="radial-sqrt", kd1=-1e-6)
    # 1 + 2 kd1 r^2 <= 0 beyond r = 707 px undistorted.
    uv = distort(cam, [[2.0, 0.0], [0.1, 0.1]])
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all()


# -- inverses ----------------------------------------------------------------------------------

@pytest.mark.parametrize("model", list(LENS_MODELS))
@FAST
@given(data=st.data())
def test_undistort_inverts_distort(model, data):
    cam, seed = data.draw(CAMERAS[model]), data.draw(seeds)
    xy = normalised_points(cam, seed)
    np.testing.assert_allclose(undistort(cam, distort(cam, xy)), xy, rtol=0, atol=1e-10)


@pytest.mark.parametrize("model", list(LENS_MODELS))
@FAST
@given(data=st.data())
def test_unproject_gives_unit_rays_through_projected_points(model, data):
    cam, seed = data.draw(CAMERAS[model]), data.draw(seeds)
    P = points_3d(cam, seed)
    rays = unproject(cam, project(cam, P))
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rays, P / np.linalg.norm(P, axis=1, keepdims=True), rtol=0, atol=1e-10)


def test_undistort_beyond_the_fold_is_nan():
    # Strong barrel: r_d = r (1 - 0.4 r^2) never exceeds 0.609, so r_d = 0.8 has no preimage.
    cam = CameraIntrinsics(640, 480, 514.7, 514.7, 319.5, 239.5, k1=-0.4)
    uv = np.array([[319.5 + 0.8 * 514.7, 239.5], [400.0, 300.0], [np.nan, 1.0]])
    xy = undistort(cam, uv)
    assert np.isnan(xy[0]).all() and np.isfinite(xy[1]).all() and np.isnan(xy[2]).all()
    xy_j, J = undistort_jacobian(cam, uv)
    assert np.isnan(J[0]).all() and np.isfinite(J[1]).all()
    np.testing.assert_array_equal(xy_j, xy)


# -- Jacobians ---------------------------------------------------------------------------------

@pytest.mark.parametrize("model", list(LENS_MODELS))
@FAST
@given(data=st.data())
def test_jacobians_match_central_differences(model, data):
    cam, seed = data.draw(CAMERAS[model]), data.draw(seeds)
    n = 50
    xy = normalised_points(cam, seed, n)
    P = points_3d(cam, seed, n)
    uv = distort(cam, xy)

    val, J = distort_jacobian(cam, xy)
    np.testing.assert_array_equal(val, distort(cam, xy))
    assert_jacobian(J, fd_jacobian(lambda a: distort(cam, a), xy, 1e-6))

    val, J = undistort_jacobian(cam, uv)
    np.testing.assert_array_equal(val, undistort(cam, uv))
    assert_jacobian(J, fd_jacobian(lambda a: undistort(cam, a), uv, 1e-3))

    val, J = project_jacobian(cam, P)
    np.testing.assert_array_equal(val, project(cam, P))
    assert J.shape == (n, 2, 3)
    assert_jacobian(J, fd_jacobian(lambda a: project(cam, a), P, 1e-6))

    val, J = unproject_jacobian(cam, uv)
    np.testing.assert_allclose(val, unproject(cam, uv), rtol=0, atol=1e-15)
    assert J.shape == (n, 3, 2)
    assert_jacobian(J, fd_jacobian(lambda a: unproject(cam, a), uv, 1e-3))


def test_fisheye_jacobian_on_the_axis():
    cam = CameraIntrinsics(640, 480, 300.0, 300.0, 320.0, 240.0, model="fisheye", k1=0.05)
    uv, J = distort_jacobian(cam, [[0.0, 0.0], [1e-9, -2e-9]])
    np.testing.assert_allclose(uv, [[320.0, 240.0], [320.0 + 3e-7, 240.0 - 6e-7]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(J, [np.diag([300.0, 300.0])] * 2, rtol=0, atol=1e-9)


# -- pinhole helpers ---------------------------------------------------------------------------

def test_points_behind_the_camera_are_nan():
    cam = default_camera()
    P = np.array([[0.1, 0.1, -1.0], [0.0, 0.0, 0.0], [0.1, -0.1, 1.0]])
    uv, J = project_jacobian(cam, P)
    assert np.isnan(uv[:2]).all() and np.isnan(J[:2]).all()
    np.testing.assert_allclose(uv[2], [319.5 + 51.47, 239.5 - 51.47])
    np.testing.assert_array_equal(project(cam, P), uv)


def test_default_camera_fov_and_K():
    cam = default_camera()
    assert cam is DEFAULT_CAMERA
    assert (cam.width, cam.height, cam.model) == (640, 480, "brown")
    assert cam.distortion == {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0}
    np.testing.assert_array_equal(cam.K, [[514.7, 0, 319.5], [0, 514.7, 239.5], [0, 0, 1]])
    assert fov_x_rad(cam) == pytest.approx(2 * math.atan(320 / 514.7))
    assert fov_y_rad(cam) == pytest.approx(2 * math.atan(240 / 514.7))
    assert math.degrees(fov_x_rad(cam)) == pytest.approx(63.7, abs=0.1)
    # With no distortion, the top edge of the image is exactly fov_y / 2 off axis.
    ray = unproject(cam, [[319.5, -0.5]])[0]
    assert math.atan2(-ray[1], ray[2]) == pytest.approx(fov_y_rad(cam) / 2, abs=1e-12)


def test_in_image():
    cam = default_camera()
    uv = np.array([[-0.5, -0.5], [639.5, 479.5], [-0.51, 10], [10, 479.6], [np.nan, 3], [10, 10]])
    np.testing.assert_array_equal(in_image(cam, uv), [True, True, False, False, False, True])
    np.testing.assert_array_equal(in_image(cam, uv, margin=6.0), [False] * 5 + [True])


def test_shapes_are_checked():
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        distort(default_camera(), [0.1, 0.2])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        project(default_camera(), np.zeros((4, 2)))


# -- camera.toml -------------------------------------------------------------------------------

ROUND_TRIP = [
    default_camera(),
    CameraIntrinsics(1280, 720, 0.1 + 900.2, 901.0 / 3, 640.1, 359.7, "brown", k1=-0.1 - 0.2, k2=1e-17, p2=-3e-4),
    CameraIntrinsics(752, 480, 458.654, 457.296, 367.215, 248.375, "fisheye",
                     k1=-0.28340811, k2=0.07395907, k3=0.00019359, k4=1.76187114e-05),
    CameraIntrinsics(320, 240, 195.0, 195.0, 162.0, 125.0, "radial-sqrt", kd1=9e-6),
]


@pytest.mark.parametrize("cam", ROUND_TRIP, ids=lambda c: c.model)
def test_camera_toml_round_trip(cam, tmp_path):
    path = tmp_path / "camera.toml"
    save_camera(cam, path)
    back = load_camera(path)
    assert back == cam
    assert all(getattr(back, t) == getattr(cam, t) for t in LENS_MODELS[cam.model])  # bit-exact floats
    doc = tomllib.loads(path.read_text())
    assert set(doc) == {"camera"} and doc["camera"]["model"] == cam.model
    assert set(doc["camera"]) == {"width", "height", "fx", "fy", "cx", "cy", "model", *LENS_MODELS[cam.model]}
    save_camera(back, tmp_path / "again.toml")
    assert (tmp_path / "again.toml").read_text() == path.read_text()


def test_minimal_camera_toml_defaults_to_undistorted_brown(tmp_path):
    path = tmp_path / "camera.toml"
    path.write_text("[camera]\nwidth = 640\nheight = 480\nfx = 514.7\nfy = 514.7\ncx = 319.5\ncy = 239.5\n")
    assert load_camera(path) == default_camera()


GOOD = {"width": "640", "height": "480", "fx": "514.7", "fy": "514.7", "cx": "319.5", "cy": "239.5"}


def _toml(**fields) -> str:
    """A [camera] table from GOOD with fields replaced (None removes one), values as TOML text."""
    table = {**GOOD, **fields}
    return "[camera]\n" + "".join(f"{k} = {v}\n" for k, v in table.items() if v is not None)


BAD_FILES = {
    "unknown key": (_toml(focal="500.0"), "focal"),
    "unknown model": (_toml(model='"pinhole"'), "model"),
    "negative fx": (_toml(fx="-3"), "fx"),
    "term of another model": (_toml(kd1="1e-6"), "kd1"),
    "fisheye term with brown": (_toml(k4="0.01"), "k4"),
    "brown term with fisheye": (_toml(model='"fisheye"', p1="0.01"), "p1"),
    "missing [camera] table": ("".join(f"{k} = {v}\n" for k, v in GOOD.items()), "[camera]"),
    "non-integer width": (_toml(width="640.5"), "width"),
    "string width": (_toml(width='"640"'), "width"),
    "zero height": (_toml(height="0"), "height"),
    "missing fy": (_toml(fy=None), "fy"),
    "infinite cx": (_toml(cx="inf"), "cx"),
    "non-number k1": (_toml(k1="[0.1]"), "k1"),
    "extra table": (_toml() + "[imu]\nrate = 200\n", "imu"),
    "kd1 too large": (_toml(model='"radial-sqrt"', kd1="1e-5"), "kd1"),
    "camera not a table": ("camera = 3\n", "[camera]"),
    "not TOML": ("[camera\nwidth = 640\n", "TOML"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_camera_toml_raises_one_line_error_naming_file_and_field(case, tmp_path):
    text, field = BAD_FILES[case]
    path = tmp_path / "camera.toml"
    path.write_text(text)
    with pytest.raises(CameraFileError) as info:
        load_camera(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"{path}: ")
    assert field in msg


def test_error_messages_say_what_to_do(tmp_path):
    path = tmp_path / "camera.toml"
    for text, expected in [
        (_toml(fx="-3"), "[camera].fx = -3 must be positive (focal length in pixels, e.g. 514.7)"),
        (_toml(kd1="1e-6"), 'model "radial-sqrt", not of model "brown"'),
        (_toml(kd1="1e-6"), "k1, k2, p1, p2, k3"),
        (_toml(fxx="500.0"), "did you mean fx?"),
        (_toml(model='"radial-sqrt"', kd1="1e-5"), "use kd1 < 3.125e-06"),
    ]:
        path.write_text(text)
        with pytest.raises(CameraFileError) as info:
            load_camera(path)
        assert expected in str(info.value)


def test_missing_file_and_direct_construction_errors(tmp_path):
    with pytest.raises(CameraFileError, match="no such file"):
        load_camera(tmp_path / "nope.toml")
    with pytest.raises(CameraFileError, match=r"\[camera\]\.fy = 0.0 must be positive"):
        CameraIntrinsics(640, 480, 500.0, 0.0, 320.0, 240.0)
    with pytest.raises(CameraFileError, match=r"kd1 = 1e-06 is not a term of model \"brown\""):
        CameraIntrinsics(640, 480, 500.0, 500.0, 320.0, 240.0, kd1=np.float64(1e-6))
    with pytest.raises(CameraFileError, match=r"^here: \[camera\]\.model"):
        CameraIntrinsics.from_dict({"camera": {**DEFAULT_CAMERA.to_dict()["camera"], "model": "pinhole"}}, "here")
    # numpy scalars are accepted and stored as plain Python numbers
    cam = CameraIntrinsics(np.int64(640), np.int64(480), np.float64(500), 500, 320, 240)
    assert type(cam.width) is int and type(cam.fy) is float
    assert cam.validate("x.toml") is cam


def test_depth_scale_is_a_sequence_key_of_camera_toml(tmp_path):
    from kinematics.camera import CameraFileError, load_camera

    doc = "[camera]\nwidth = 640\nheight = 480\nfx = 500.0\nfy = 500.0\ncx = 319.5\ncy = 239.5\n"
    (tmp_path / "a.toml").write_text(doc + "depth_scale = 1000.0\n")
    assert load_camera(tmp_path / "a.toml").fx == 500.0
    for bad in ("0", "-5.0", "nan", '"x"'):
        (tmp_path / "b.toml").write_text(doc + f"depth_scale = {bad}\n")
        with pytest.raises(CameraFileError, match="depth_scale"):
            load_camera(tmp_path / "b.toml")
