"""Saving a map and starting from it (map_io.py): save then load round-trips every array and
feature record of a map mixing points and inverse-depth features; the loaded map makes a filter
state and a session that starts lost in the map's frame; a map from another camera model, a
truncated file, a file that is not a map, a newer format version and inconsistent arrays are
each refused with MapFileError naming the file and the problem, in one line; a failed save
leaves the previous map as it was."""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import fields, replace

import numpy as np
import pytest

import slam_testing
import test_slam_startup as su
from kinematics.camera import CameraIntrinsics
from runtime.sequence import Target
from runtime.slam import map_io
from runtime.slam.config import MapSettings, SlamConfig
from runtime.slam.features import INVERSE_DEPTH, POINT
from runtime.slam.filter import convert_to_point
from runtime.slam.map_io import MapFileError, load_map, save_map
from runtime.slam.state import CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_TIMED
from runtime.slam.system import MonoSLAM
from runtime.slam.map_feature import MapFeature

CAM = su.CAM
#: What a saved map keeps of each feature (the rest is the session's own: cached rays, the last
#: frame it was seen in, its latest innovations).
SAVED_FIELDS = ("id", "template", "first_frame", "r0", "known", "attempts", "successes", "patch", "uv0", "R0",
                "normal", "normal_from_map", "normal_view_deg")


@pytest.fixture(scope="module")
def slam() -> MonoSLAM:
    """A running SLAM on the synthetic target scene: the four target points, natural features
    started as inverse-depth rays, two of them converted to points."""
    img, uv = su.scene("near oblique")
    s = MonoSLAM(CAM, settings=MapSettings(use_imu=False))
    s.start(img, 0.0, Target(su.RECT, uv + 2.0))
    for k in range(1, 6):
        s.process(img, k / 30)
    ids = np.flatnonzero(s.state.kinds == INVERSE_DEPTH)
    assert len(ids) >= 4
    for k in ids[:2]:
        convert_to_point(s.state, int(k))
    assert set(s.state.kinds.tolist()) == {POINT, INVERSE_DEPTH} and s.localised
    return s



def assert_feature_equal(a: MapFeature, b: MapFeature) -> None:
    for name in SAVED_FIELDS:
        va, vb = getattr(a, name), getattr(b, name)
        if isinstance(va, np.ndarray) or isinstance(vb, np.ndarray):
            assert va is not None and vb is not None, name
            np.testing.assert_array_equal(va, vb, err_msg=name)
        else:
            assert va == vb, name


def test_the_angle_a_normal_was_fitted_at_round_trips_and_an_older_map_has_none(slam, tmp_path):
    before = [f.normal_view_deg for f in slam.features]
    try:
        for i, f in enumerate(slam.features):
            f.normal_view_deg = 10.0 + 1.5 * i
        path = save_map(tmp_path / "m.npz", slam)
        assert [f.normal_view_deg for f in load_map(path, CAM).features] == [10.0 + 1.5 * i for i in range(len(before))]
        # A map written before the fitted normals: the same file less that array.
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files if k != "normal_view_deg"}
        np.savez_compressed(tmp_path / "old.npz", **arrays)
        assert all(f.normal_view_deg == 0.0 for f in load_map(tmp_path / "old.npz", CAM).features)
    finally:
        for f, v in zip(slam.features, before):
            f.normal_view_deg = v


def test_save_then_load_round_trips_every_array_and_record(slam, tmp_path):
    # The path is written exactly as given: a name without .npz, or a folder, is refused.
    for bad in (tmp_path / "maps" / "bench", tmp_path):
        with pytest.raises(MapFileError, match=r"\.npz"):
            save_map(bad, slam)
    assert not (tmp_path / "maps").exists()
    path = save_map(tmp_path / "maps" / "bench.npz", slam)
    assert path == tmp_path / "maps" / "bench.npz" and path.is_file()
    assert [p.name for p in path.parent.iterdir()] == ["bench.npz"]          # no temporary left
    saved = load_map(path, CAM)
    st = slam.state
    cd = st.cam_dim
    np.testing.assert_array_equal(saved.y, st.x[cd:])
    np.testing.assert_array_equal(saved.P, st.P[cd:, cd:])
    np.testing.assert_array_equal(saved.kinds, st.kinds)
    np.testing.assert_array_equal(saved.anchors, st.anchors)
    np.testing.assert_array_equal(saved.T_world_cam, slam.T_world_cam())
    assert saved.camera == CAM
    assert len(saved.features) == len(slam.features) == st.n_features
    for a, b in zip(saved.features, slam.features):
        assert_feature_equal(a, b)
    assert any(f.patch is not None for f in saved.features) and any(f.known for f in saved.features)
    # A second save of the loaded map's session gives the same file contents.
    assert load_map(save_map(tmp_path / "again.npz", slam)).y.tobytes() == saved.y.tobytes()


@pytest.mark.parametrize("cam_dim", [CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_TIMED])
def test_a_loaded_map_makes_a_state_and_a_session_that_starts_lost(slam, tmp_path, cam_dim):
    saved = load_map(save_map(tmp_path / "m.npz", slam), CAM)
    cfg = SlamConfig()
    s = saved.state_with_camera(cam_dim, cfg)
    assert s.cam_dim == cam_dim and np.array_equal(s.kinds, saved.kinds)
    np.testing.assert_array_equal(s.x[cam_dim:], saved.y)
    np.testing.assert_allclose(s.P[cam_dim:, cam_dim:], saved.P, rtol=1e-12, atol=1e-20)
    assert not s.P[:cam_dim, cam_dim:].any()                 # the camera knows nothing of the map
    np.testing.assert_allclose(s.r, saved.T_world_cam[:3, 3])
    assert np.sqrt(s.P[0, 0]) >= 0.5                          # too wide to search: it must re-localise
    if cam_dim >= CAMERA_DIM_BIASED:
        np.testing.assert_allclose(np.diag(s.P)[13:19], [cfg.imu.gyro_bias_sigma0**2] * 3
                                   + [cfg.imu.accel_bias_sigma0**2] * 3)
    if cam_dim == CAMERA_DIM_TIMED:
        assert s.P[19, 19] == cfg.imu.time_offset_sigma0**2 and s.t_d == 0.0
    session = MonoSLAM(CAM, settings=MapSettings(use_imu=False))
    session.start_from_map(saved, 10.0)
    assert session.lost and not session.localised and np.isnan(session.T_world_cam()).all()
    assert [f.id for f in session.features] == [f.id for f in saved.features]
    assert all(f.attempts == 0 and f.successes == 0 for f in session.features)
    assert all(f.first_frame == 0 and f.last_seen == 0 for f in session.features)
    assert session.new_id() == max(f.id for f in saved.features) + 1
    # The map's four known points are the session's target, in id order, as the mapping
    # session's refined target had them.
    assert session.refined_target is not None
    np.testing.assert_allclose(session.refined_target.xyz, slam.refined_target.xyz, atol=1e-3)
    known = sorted((f.id, k) for k, f in enumerate(saved.features) if f.known)
    np.testing.assert_array_equal(session.refined_target.xyz, [s.feature(k)[:3] for _, k in known])


def write_npz(path, arrays: dict) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())


def arrays_of(path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def header(version=map_io.VERSION, fmt=map_io.FORMAT, **extra) -> np.ndarray:
    return np.frombuffer(json.dumps({"format": fmt, "version": version, **extra}).encode(), np.uint8)


def bad_files(slam, tmp_path) -> dict:
    """A good map and variants of it, each broken in one way."""
    good = save_map(tmp_path / "good.npz", slam)
    data = good.read_bytes()
    a = arrays_of(good)
    h = json.loads(bytes(a["header"]).decode())
    files = {"good": good}
    files["truncated"] = tmp_path / "truncated.npz"
    files["truncated"].write_bytes(data[:len(data) // 2])
    files["text"] = tmp_path / "notes.npz"
    files["text"].write_text("# not a map\n")
    files["no header"] = tmp_path / "no_header.npz"
    write_npz(files["no header"], {k: v for k, v in a.items() if k != "header"})
    files["other format"] = tmp_path / "other_format.npz"
    write_npz(files["other format"], {**a, "header": header(fmt="something-else")})
    files["newer"] = tmp_path / "newer.npz"
    rest = {k: v for k, v in h.items() if k not in ("format", "version")}
    write_npz(files["newer"], {**a, "header": header(version=map_io.VERSION + 1, **rest)})
    files["inconsistent"] = tmp_path / "inconsistent.npz"
    write_npz(files["inconsistent"], {**a, "P": a["P"][:-1, :-1]})
    files["non-finite"] = tmp_path / "non_finite.npz"
    y = a["y"].copy()
    y[0] = np.nan
    write_npz(files["non-finite"], {**a, "y": y})
    files["missing"] = tmp_path / "missing.npz"
    # Files that are not ours: an array saved by np.save and renamed, headers that are not a table.
    files["npy"] = tmp_path / "array.npz"
    with open(files["npy"], "wb") as fh:
        np.save(fh, np.arange(5.0))
    for name, value in (("list header", [1, 2]), ("null header", None)):
        files[name] = tmp_path / f"{name.replace(' ', '_')}.npz"
        write_npz(files[name], {**a, "header": np.frombuffer(json.dumps(value).encode(), np.uint8)})
    files["negative variance"] = tmp_path / "negative_variance.npz"
    P = a["P"].copy()
    P[0, 0] = -1e6
    write_npz(files["negative variance"], {**a, "P": P})
    files["huge"] = tmp_path / "huge.npz"
    y = a["y"].copy()
    y[0] = 1e200
    write_npz(files["huge"], {**a, "y": y})
    return files


def assert_refused(path, cam, message) -> None:
    with pytest.raises(MapFileError, match=message) as e:
        load_map(path, cam)
    text = str(e.value)
    assert text.startswith(str(path)) and "\n" not in text, text


def test_files_that_are_not_usable_maps_are_refused_in_one_line(slam, tmp_path):
    f = bad_files(slam, tmp_path)
    for name, message in [
        ("truncated", r"corrupt or truncated map file"),
        ("text", r"corrupt or truncated map file"),
        ("no header", r"not a wvr SLAM map \(no header\)"),
        ("other format", r"not a wvr SLAM map \(format 'something-else'\)"),
        ("newer", rf"map format version {map_io.VERSION + 1} is newer than this wvr reads \({map_io.VERSION}\)"),
        ("missing", r"no such map file"),
        ("npy", r"not a wvr SLAM map"),
        ("list header", r"not a wvr SLAM map \(format 'list'\)"),
        ("null header", r"not a wvr SLAM map \(format 'NoneType'\)"),
    ]:
        assert_refused(f[name], CAM, message)
        assert_refused(f[name], None, message)


def test_maps_of_another_camera_or_with_broken_arrays_are_refused_in_one_line(slam, tmp_path):
    f = bad_files(slam, tmp_path)
    other_cam = replace(CAM, fx=CAM.fx * 1.1, fy=CAM.fy * 1.1)
    fisheye = CameraIntrinsics(width=CAM.width, height=CAM.height, fx=CAM.fx, fy=CAM.fy, cx=CAM.cx, cy=CAM.cy,
                               model="fisheye", k1=0.01)
    assert_refused(f["good"], other_cam, r"built with another camera \(fx, fy differ from this sequence's camera.toml\)")
    assert_refused(f["good"], fisheye, r"built with another camera \(model, .*k1")
    assert_refused(f["inconsistent"], CAM, r"the map's arrays are inconsistent")
    assert_refused(f["non-finite"], CAM, r"the map's arrays are inconsistent")
    assert_refused(f["negative variance"], CAM, r"non-negative variances")
    assert_refused(f["huge"], CAM, r"values beyond")
    assert load_map(f["good"]).camera == CAM            # without a camera to check against


def test_a_failed_save_leaves_the_previous_map(slam, tmp_path, monkeypatch):
    path = save_map(tmp_path / "m.npz", slam)
    before = path.read_bytes()

    def killed(fh, **arrays):
        fh.write(b"PK\x03\x04 half a zip")
        raise KeyboardInterrupt

    monkeypatch.setattr(map_io.np, "savez_compressed", killed)
    with pytest.raises(KeyboardInterrupt):
        save_map(path, slam)
    assert path.read_bytes() == before
    assert zipfile.is_zipfile(path)


def test_saved_fields_are_map_features_fields():
    names = {f.name for f in fields(MapFeature)}
    assert set(SAVED_FIELDS) <= names


def test_a_map_saved_through_a_similarity_is_the_same_map_in_the_new_world(slam, tmp_path):
    """save_map with the IMU's rotation and scale: every feature's point (an inverse-depth one
    through its conversion) is s R p of the filter's, its point covariance s^2 R P R^T, and the
    pose, first views and normals are turned and scaled with it; the map's scale source is kept."""
    from scipy.spatial.transform import Rotation

    from runtime.slam.features import inverse_depth

    R, s = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix(), 2.7
    saved = load_map(save_map(tmp_path / "m.npz", slam, R, s), CAM)
    st = slam.state
    assert saved.scale == slam.scale_source == "target"

    def covariances(y, P, kinds, anchors):
        out, i = [], 0
        for kind, A in zip(kinds, anchors):
            d = 3 if kind == POINT else 6
            J = np.eye(3) if kind == POINT else inverse_depth.to_point(y[i:i + d], A)[1]
            out.append(J @ P[i:i + d, i:i + d] @ J.T)
            i += d
        return np.array(out)

    cd = st.cam_dim
    before = slam_testing.feature_points(st.x[cd:], st.kinds, st.anchors)
    np.testing.assert_allclose(slam_testing.feature_points(saved.y, saved.kinds, saved.anchors), s * before @ R.T,
                               atol=1e-9)
    C0 = covariances(st.x[cd:], st.P[cd:, cd:], st.kinds, st.anchors)
    C1 = covariances(saved.y, saved.P, saved.kinds, saved.anchors)
    np.testing.assert_allclose(C1, s**2 * np.einsum("ij,njk,lk->nil", R, C0, R), rtol=1e-9, atol=1e-15)
    # The inverse-depth features keep their angles: their anchors turn instead.
    idp = np.flatnonzero(st.kinds == INVERSE_DEPTH)
    np.testing.assert_allclose(saved.anchors[idp], R @ st.anchors[idp])
    T = slam.T_world_cam()
    np.testing.assert_allclose(saved.T_world_cam[:3, :3], R @ T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(saved.T_world_cam[:3, 3], s * R @ T[:3, 3], atol=1e-12)
    for a, b in zip(saved.features, slam.features):
        np.testing.assert_allclose(a.r0, s * R @ b.r0, atol=1e-12)
        if b.R0 is not None:
            np.testing.assert_allclose(a.R0, R @ b.R0, atol=1e-12)
        if b.normal is not None:
            np.testing.assert_allclose(a.normal, R @ b.normal, atol=1e-12)
    np.testing.assert_allclose(saved.P, saved.P.T)


def test_a_map_with_no_metre_starts_a_session_with_no_metre(slam, tmp_path):
    """A natural start's map that nothing scaled is saved as arbitrary, and a session started from
    it says so rather than calling its unit the map's metre; a map saved before the key was kept
    reads as the map's scale, as it did."""
    before = slam.scale_source
    try:
        slam.scale_source = "arbitrary"
        saved = load_map(save_map(tmp_path / "a.npz", slam), CAM)
    finally:
        slam.scale_source = before
    assert saved.scale == "arbitrary"
    session = MonoSLAM(CAM, settings=MapSettings(use_imu=False))
    session.start_from_map(saved, 0.0)
    assert session.scale_source == "arbitrary"
    session = MonoSLAM(CAM, settings=MapSettings(use_imu=False))
    session.start_from_map(load_map(save_map(tmp_path / "t.npz", slam), CAM), 0.0)
    assert session.scale_source == "map"
