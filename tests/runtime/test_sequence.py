"""Tests for runtime.sequence: TUM files, target.toml, image sequences and their writer."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraFileError, CameraIntrinsics, save_camera
from runtime.sequence import (
    Frame,
    ImuLog,
    JointLog,
    SequenceError,
    SequenceWriter,
    Target,
    Trajectory,
    load_target,
    open_sequence,
    read_imu,
    read_joints,
    read_trajectory,
    save_target,
    write_imu,
    write_joints,
    write_trajectory,
)

# A small camera keeps image files (and the test) small.
CAM = CameraIntrinsics(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)


def random_trajectory(n: int = 20, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Times (n,) s and T_world_cam (n, 4, 4) with arbitrary rotations and positions."""
    rng = np.random.default_rng(seed)
    t = 100.0 + np.cumsum(rng.uniform(0.01, 0.1, n))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(0.0, 3.0, (n, 3))
    return t, T


def make_target() -> Target:
    xyz = [[-0.1, -0.07, 0.0012], [0.1, -0.07, 0.0], [0.1, 0.07, 0.0], [-0.1, 0.07, 0.0], [0.0, 0.0, 0.05]]
    uv = [[243.17, 301.55], [400.0, 300.0], [400.0, 180.0], [240.0, 180.0], [320.25, 240.125]]
    return Target(np.array(xyz), np.array(uv))


def colour_image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (CAM.height, CAM.width, 3), dtype=np.uint8)


def grey_image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (CAM.height, CAM.width), dtype=np.uint8)


def write_minimal_sequence(root, rgb_lines: list[str]) -> None:
    """camera.toml and rgb.txt only, for the reader's error tests."""
    root.mkdir(exist_ok=True)
    save_camera(CAM, root / "camera.toml")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")


# -- trajectories --------------------------------------------------------------------------------

def test_trajectory_round_trip_4x4(tmp_path):
    t, T = random_trajectory()
    write_trajectory(tmp_path / "traj.txt", t, T, header="estimated by a test\nsecond line")
    traj = read_trajectory(tmp_path / "traj.txt")
    assert len(traj) == len(t)
    np.testing.assert_allclose(traj.t, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(traj.T_world_cam(), T, rtol=0, atol=1e-9)
    lines = (tmp_path / "traj.txt").read_text().splitlines()
    assert lines[0] == "# estimated by a test" and lines[1] == "# second line"
    assert lines[2].startswith("# timestamp tx ty tz qx qy qz qw")


def test_trajectory_round_trip_position_quaternion(tmp_path):
    t, T = random_trajectory(seed=3)
    p = T[:, :3, 3]
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    write_trajectory(tmp_path / "traj.txt", t, (p, q))
    traj = read_trajectory(tmp_path / "traj.txt")
    np.testing.assert_allclose(traj.p_world_cam, p, rtol=0, atol=1e-9)
    np.testing.assert_allclose(traj.q_xyzw, q, rtol=0, atol=1e-9)


def test_trajectory_reads_tum_column_order(tmp_path):
    # A hand-written line: position (1, 2, 3), 90 degrees about world z (qz = qw = sqrt(1/2)).
    s = 0.7071067811865476
    (tmp_path / "gt.txt").write_text(f"1305031102.175304 1.0 2.0 3.0 0.0 0.0 {s} {s}\n")
    traj = read_trajectory(tmp_path / "gt.txt")
    assert traj.t[0] == 1305031102.175304
    np.testing.assert_array_equal(traj.p_world_cam[0], [1.0, 2.0, 3.0])
    T = traj.T_world_cam()[0]
    # Camera-to-world: the camera's x axis (first column) points along world +y.
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T @ [0, 0, 1, 1], [1.0, 2.0, 4.0, 1.0], atol=1e-12)


def test_trajectory_comments_blank_lines_and_normalisation(tmp_path):
    (tmp_path / "gt.txt").write_text(
        "# ground-truth trajectory\n"
        "# file: 'rgbd_dataset_freiburg1_xyz.bag'\n"
        "# timestamp tx ty tz qx qy qz qw\n"
        "\n"
        "1.0 0 0 0 0 0 0 1.0004\n"   # 4e-4 off unit: rounding in the file, normalised
        "   \n"
        "2.0   1 0 0\t0 0 0 1\n"
        "# a comment in the middle\n"
        "3.0 2 0 0 0 0 0 1\n")
    traj = read_trajectory(tmp_path / "gt.txt")
    np.testing.assert_array_equal(traj.t, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.linalg.norm(traj.q_xyzw, axis=1), 1.0, atol=1e-15)


@pytest.mark.parametrize("line, words", [
    ("2.0 1 0 0 0 0 1", ["7 fields", "expected 8"]),
    ("2.0 1 0 x 0 0 0 1", ["tz", "'x'", "not a number"]),
    ("2.0 1 0 0 0 0 0 nan", ["qw", "not finite"]),
    ("2.0 1 0 0 0 0 0 2", ["norm 2", "column order"]),
    ("0.5 1 0 0 0 0 0 1", ["not after", "line 2", "increasing"]),
])
def test_trajectory_malformed_line_named(tmp_path, line, words):
    path = tmp_path / "gt.txt"
    path.write_text(f"# header\n1.0 0 0 0 0 0 0 1\n\n{line}\n")
    with pytest.raises(SequenceError) as e:
        read_trajectory(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}:4:") and "\n" not in msg
    for w in words:
        assert w in msg


def test_trajectory_missing_file(tmp_path):
    with pytest.raises(SequenceError, match="no such file"):
        read_trajectory(tmp_path / "nope.txt")


def test_trajectory_slerp_halfway_and_linear_positions():
    R0 = Rotation.from_euler("xyz", [0.1, -0.2, 0.3])
    step = Rotation.from_rotvec([0.0, 0.8, 0.6])  # 1 rad about a unit axis
    R1 = step * R0
    mid = Rotation.from_rotvec([0.0, 0.4, 0.3]) * R0  # half the angle about the same axis
    q = np.vstack([R0.as_quat(), R1.as_quat()])
    traj = Trajectory(np.array([2.0, 4.0]), np.array([[0.0, 0.0, 0.0], [2.0, -4.0, 6.0]]), q)
    T = traj.at(3.0)
    np.testing.assert_allclose(T[:3, :3], mid.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1.0, -2.0, 3.0], atol=1e-12)
    quarter = traj.interpolate([2.0, 2.5, 4.0])
    np.testing.assert_allclose(quarter.p_world_cam[1], [0.5, -1.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(quarter.T_world_cam()[[0, 2], :3, :3], [R0.as_matrix(), R1.as_matrix()], atol=1e-12)


def test_trajectory_interpolation_refuses_outside_range():
    traj = Trajectory([0.0, 1.0], np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1)))
    for t in (-1e-6, 1.000001):
        with pytest.raises(SequenceError, match="outside the trajectory's range"):
            traj.at(t)


def test_write_trajectory_refuses_non_rigid(tmp_path):
    t, T = random_trajectory(3)
    T[1, :3, :3] *= 2.0
    with pytest.raises(SequenceError, match=r"T_world_cam\[1\] is not a rigid transform"):
        write_trajectory(tmp_path / "x.txt", t, T)


# -- IMU and joints ------------------------------------------------------------------------------

def test_imu_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    t = np.arange(50) * 0.005 + 12.0
    gyro, accel = rng.normal(0, 2, (50, 3)), rng.normal(0, 10, (50, 3))
    write_imu(tmp_path / "imu.txt", t, gyro, accel)
    assert (tmp_path / "imu.txt").read_text().startswith("# timestamp wx wy wz ax ay az")
    log = read_imu(tmp_path / "imu.txt")
    assert isinstance(log, ImuLog) and len(log) == 50
    np.testing.assert_allclose(log.t, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.gyro, gyro, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.accel, accel, rtol=0, atol=1e-9)


def test_joints_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    t = np.arange(30) * 0.02
    q = rng.uniform(-np.pi, np.pi, (30, 3))
    write_joints(tmp_path / "joints.txt", t, q)
    assert (tmp_path / "joints.txt").read_text().startswith("# timestamp q_elevation q_pan q_cyclotorsion")
    log = read_joints(tmp_path / "joints.txt")
    assert isinstance(log, JointLog) and len(log) == 30
    np.testing.assert_allclose(log.t, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.q, q, rtol=0, atol=1e-9)


def test_imu_and_joint_malformed_lines(tmp_path):
    (tmp_path / "imu.txt").write_text("# imu\n0.0 0 0 0 0 0 9.81\n0.1 0 0 0 0 0\n")
    with pytest.raises(SequenceError, match=r"imu\.txt:3: 6 fields, expected 7"):
        read_imu(tmp_path / "imu.txt")
    (tmp_path / "joints.txt").write_text("0.0 0 0 0\n0.1 0 pan 0\n")
    with pytest.raises(SequenceError, match=r"joints\.txt:2: q_pan = 'pan' is not a number"):
        read_joints(tmp_path / "joints.txt")


# -- target.toml ---------------------------------------------------------------------------------

def test_target_round_trip(tmp_path):
    target = make_target()
    save_target(target, tmp_path / "target.toml")
    back = load_target(tmp_path / "target.toml")
    np.testing.assert_array_equal(back.xyz, target.xyz)
    np.testing.assert_array_equal(back.uv, target.uv)


def test_target_formats_md_example_loads(tmp_path):
    point = "[[point]]\nxyz = [-0.1, -0.07, 0.0012]   # metres\nuv = [243.17, 301.55]\n"
    (tmp_path / "target.toml").write_text(point * 3 + "[[point]]\nxyz = [1, 2, 3]\nuv = [4, 5]\n")
    target = load_target(tmp_path / "target.toml")
    assert target.xyz.shape == (4, 3) and target.uv.shape == (4, 2)
    np.testing.assert_array_equal(target.xyz[3], [1.0, 2.0, 3.0])


@pytest.mark.parametrize("extra, pattern", [
    ("", r"3 \[\[point\]\] tables, but at least 4 are needed"),
    ("[[point]]\nxyz = [0, 0, 0]\nuv = [1, 2]\nuvw = 3\n", r"\[\[point\]\] 4: unknown key 'uvw'"),
    ("[[point]]\nxyz = [0, 0]\nuv = [1, 2]\n", r"\[\[point\]\] 4: xyz = \[0, 0\] must be 3 numbers"),
    ("[[point]]\nxyz = [0, 0, 0]\n", r"\[\[point\]\] 4: missing uv"),
    ("[[point]]\nxyz = [0, 0, nan]\nuv = [1, 2]\n", r"\[\[point\]\] 4: xyz = .* is not finite"),
    ("[[point]]\nxyz = [0, 0, true]\nuv = [1, 2]\n", r"must be 3 numbers"),
    ("scale = 1.0\n", r"unknown top-level key 'scale'"),
])
def test_target_errors(tmp_path, extra, pattern):
    ok = "[[point]]\nxyz = [0.0, 0.0, 0.0]\nuv = [1.0, 2.0]\n" * 3
    path = tmp_path / "target.toml"
    # Top-level keys must precede the tables in TOML.
    path.write_text(extra + ok if extra.startswith("scale") else ok + extra)
    with pytest.raises(SequenceError, match=pattern) as e:
        load_target(path)
    assert str(e.value).startswith(str(path))


# -- image sequences -----------------------------------------------------------------------------

def test_sequence_round_trip(tmp_path):
    root = tmp_path / "seq"
    images = [colour_image(0), grey_image(1), colour_image(2), grey_image(3)]
    times = [1.5, 1.533333, 1.566667, 1.6]
    t_gt, T_gt = random_trajectory(5)
    with SequenceWriter(root, CAM, target=make_target()) as w:
        for t, im in zip(times, images):
            w.add_frame(t, im)
        for t, T in zip(t_gt, T_gt):
            w.add_groundtruth(t, T)
        w.add_imu(1.5, [0.1, 0.2, 0.3], [0.0, -9.81, 0.0])
        w.add_imu(1.505, [0.1, 0.2, 0.4], [0.0, -9.81, 0.1])
        w.add_joints(1.5, [0.1, -0.2, 0.05])

    seq = open_sequence(root)
    assert len(seq) == 4 and seq.root == root and seq.camera == CAM
    np.testing.assert_allclose(seq.timestamps, times, rtol=0, atol=1e-9)
    frames = list(seq.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f, im, t in zip(frames, images, times):
        assert isinstance(f, Frame) and f.problem is None and f.ok
        assert f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, im)  # PNG is lossless; RGB order preserved
        assert f.path.name == f"{t:.6f}.png" and f.path.parent == root / "rgb"
    np.testing.assert_array_equal(seq.target.xyz, make_target().xyz)
    np.testing.assert_allclose(seq.groundtruth.T_world_cam(), T_gt, rtol=0, atol=1e-9)
    np.testing.assert_allclose(seq.imu.accel[1], [0.0, -9.81, 0.1], atol=1e-12)
    np.testing.assert_allclose(seq.joints.q, [[0.1, -0.2, 0.05]], atol=1e-12)
    for name in ("rgb.txt", "groundtruth.txt", "imu.txt", "joints.txt"):
        assert (root / name).read_text().startswith("# timestamp")
    assert not list((root / "rgb").glob("*.part"))


def test_sequence_optional_files_absent(tmp_path):
    with SequenceWriter(tmp_path, CAM) as w:
        w.add_frame(0.0, grey_image(0))
    seq = open_sequence(tmp_path)
    assert seq.target is None and seq.groundtruth is None and seq.imu is None and seq.joints is None
    assert len(seq) == 1


def test_colour_channel_order_on_disk(tmp_path):
    # Pure red in RGB must be stored as red for every other tool: cv2 reads it back as BGR.
    red = np.zeros((CAM.height, CAM.width, 3), np.uint8)
    red[..., 0] = 255
    with SequenceWriter(tmp_path, CAM) as w:
        path = w.add_frame(0.0, red)
    assert cv2.imread(str(path))[0, 0].tolist() == [0, 0, 255]


def test_sequence_16bit_and_alpha_images(tmp_path):
    write_minimal_sequence(tmp_path, ["# timestamp filename", "0.0 a.png", "0.1 b.png"])
    grey16 = np.full((CAM.height, CAM.width), 65535, np.uint16)
    grey16[0, 0] = 257 * 100
    grey16[0, 1] = 0
    assert cv2.imwrite(str(tmp_path / "a.png"), grey16)
    bgra = np.zeros((CAM.height, CAM.width, 4), np.uint8)
    bgra[..., 0], bgra[..., 3] = 200, 17  # blue in BGR, with an alpha channel
    assert cv2.imwrite(str(tmp_path / "b.png"), bgra)
    a, b = open_sequence(tmp_path).frames()
    assert a.image.dtype == np.uint8 and a.image.shape == (CAM.height, CAM.width)
    assert a.image[0, 0] == 100 and a.image[0, 1] == 0 and a.image[5, 5] == 255
    assert b.image.shape == (CAM.height, CAM.width, 3)
    assert b.image[0, 0].tolist() == [0, 0, 200]


def test_bad_frames_are_reported_not_raised(tmp_path):
    root = tmp_path / "seq"
    with SequenceWriter(root, CAM) as w:
        paths = [w.add_frame(0.1 * i, colour_image(i)) for i in range(5)]
    paths[1].unlink()                                               # missing
    data = paths[2].read_bytes()
    paths[2].write_bytes(data[: len(data) // 2])                    # truncated PNG
    paths[3].write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")  # garbage
    cv2.imwrite(str(paths[4]), np.zeros((CAM.height + 1, CAM.width, 3), np.uint8))  # wrong size
    frames = list(open_sequence(root).frames())
    assert len(frames) == 5
    assert frames[0].ok and frames[0].problem is None
    np.testing.assert_array_equal(frames[0].image, colour_image(0))
    for f in frames[1:]:
        assert f.image is None and not f.ok and str(f.path) in f.problem
    assert "no such file" in frames[1].problem
    assert "not a readable image" in frames[2].problem
    assert "not a readable image" in frames[3].problem
    assert "32x25 but camera.toml says 32x24" in frames[4].problem


def test_a_damaged_png_is_a_frame_problem_without_libpngs_chatter(tmp_path, capfd):
    root = tmp_path / "seq"
    with SequenceWriter(root, CAM) as w:
        paths = [w.add_frame(0.1 * i, colour_image(i)) for i in range(3)]
    data = paths[0].read_bytes()
    paths[0].write_bytes(data[:40] + bytes(len(data) - 60) + data[-20:])   # zeros over the image data
    paths[1].write_bytes(data[: len(data) // 2])                           # cut short
    capfd.readouterr()
    a, b, c = open_sequence(root).frames()
    assert "a damaged PNG" in a.problem and "fails its CRC" in a.problem
    assert "a damaged PNG: truncated" in b.problem
    assert c.ok
    assert capfd.readouterr().err == ""        # libpng writes straight to fd 2 when it decodes one


def test_rgb_txt_comments_blank_lines_and_spaces_in_names(tmp_path):
    write_minimal_sequence(tmp_path, ["# color images", "# timestamp filename", "",
                                      "1.0 rgb/first image.png", "  ", "2.0 rgb/b.png"])
    seq = open_sequence(tmp_path)
    np.testing.assert_array_equal(seq.timestamps, [1.0, 2.0])
    assert seq.paths[0] == tmp_path / "rgb" / "first image.png"


@pytest.mark.parametrize("lines, pattern", [
    (["1.0 a.png", "1.0 b.png"], r"rgb\.txt:2: timestamp 1\.0 is not after 1\.0 on line 1"),
    (["# c", "2.0 a.png", "1.0 b.png"], r"rgb\.txt:3: .*increasing time order"),
    (["1.0 a.png", "2.0"], r"rgb\.txt:2: expected 'timestamp path'"),
    (["one a.png"], r"rgb\.txt:1: timestamp 'one' is not a number"),
])
def test_rgb_txt_errors(tmp_path, lines, pattern):
    write_minimal_sequence(tmp_path, lines)
    with pytest.raises(SequenceError, match=pattern):
        open_sequence(tmp_path)


def test_missing_camera_toml(tmp_path):
    (tmp_path / "rgb.txt").write_text("0.0 a.png\n")
    with pytest.raises(SequenceError) as e:
        open_sequence(tmp_path)
    msg = str(e.value)
    assert str(tmp_path / "camera.toml") in msg and "missing" in msg and "[camera]" in msg


def test_bad_camera_toml_passes_through(tmp_path):
    write_minimal_sequence(tmp_path, ["0.0 a.png"])
    (tmp_path / "camera.toml").write_text("[camera]\nwidth = 32\n")
    with pytest.raises(CameraFileError, match=re.escape(str(tmp_path / "camera.toml"))):
        open_sequence(tmp_path)


def test_missing_rgb_txt_and_folder(tmp_path):
    save_camera(CAM, tmp_path / "camera.toml")
    with pytest.raises(SequenceError, match=r"rgb\.txt: missing"):
        open_sequence(tmp_path)
    with pytest.raises(SequenceError, match="not a folder"):
        open_sequence(tmp_path / "nope")


def test_bad_optional_file_named(tmp_path):
    write_minimal_sequence(tmp_path, ["0.0 a.png"])
    (tmp_path / "groundtruth.txt").write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 0\n")
    with pytest.raises(SequenceError, match=r"groundtruth\.txt:2:"):
        open_sequence(tmp_path)


# -- the writer ------------------------------------------------------------------------------------

def test_writer_marks_the_recording_incomplete_until_closed(tmp_path):
    # While the writer is open (as if the recorder were still running, or killed), readers refuse
    # the folder; what is on disk is a valid prefix for those who ask for it; closing completes it.
    w = SequenceWriter(tmp_path, CAM)
    w.add_frame(0.0, grey_image(0))
    w.add_frame(0.1, grey_image(1))
    w.add_imu(0.0, [0, 0, 0], [0, 0, 9.81])
    with pytest.raises(SequenceError, match="still being written"):
        open_sequence(tmp_path)
    seq = open_sequence(tmp_path, allow_incomplete=True)
    assert len(seq) == 2 and len(seq.imu) == 1
    assert all(f.ok for f in seq.frames())
    w.close()
    assert len(open_sequence(tmp_path)) == 2 and not (tmp_path / "INCOMPLETE").exists()
    with pytest.raises(SequenceError, match="closed"):
        w.add_frame(0.2, grey_image(2))


def test_a_killed_recording_is_refused(tmp_path):
    """A recorder killed mid-run leaves a shorter sequence that must not pass for a whole one."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(f"""
        import os, numpy as np
        from kinematics.camera import CameraIntrinsics
        from runtime.sequence import SequenceWriter
        cam = CameraIntrinsics(width={CAM.width}, height={CAM.height}, fx={CAM.fx}, fy={CAM.fy}, cx={CAM.cx}, cy={CAM.cy})
        w = SequenceWriter({str(tmp_path / "seq")!r}, cam)
        for i in range(3):
            w.add_frame(0.1 * i, np.full(({CAM.height}, {CAM.width}), 10 * i, np.uint8))
        os.kill(os.getpid(), 9)
    """)
    subprocess.run([sys.executable, "-c", code], check=False)
    with pytest.raises(SequenceError, match="stopped before the end") as e:
        open_sequence(tmp_path / "seq")
    assert "delete" in str(e.value) and "INCOMPLETE" in str(e.value)
    assert len(open_sequence(tmp_path / "seq", allow_incomplete=True)) == 3
    # A failure inside the writer's block leaves the marker too.
    with pytest.raises(RuntimeError):
        with SequenceWriter(tmp_path / "b", CAM) as w:
            w.add_frame(0.0, grey_image(0))
            raise RuntimeError("the scene broke")
    with pytest.raises(SequenceError, match="stopped before the end"):
        open_sequence(tmp_path / "b")


def test_overwrite_removes_every_optional_file_of_the_old_recording(tmp_path):
    with SequenceWriter(tmp_path / "a", CAM, target=make_target()) as w:
        w.add_frame(1.0, grey_image(0))
        w.add_depth(1.0, np.full((CAM.height, CAM.width), 1.5))
        w.add_groundtruth(1.0, np.eye(4))
        w.add_imu(1.0, [0, 0, 0], [0, 0, 9.81])
        w.add_joints(1.0, [0, 0, 0])
    with SequenceWriter(tmp_path / "a", CAM, overwrite=True) as w:
        w.add_frame(5.0, grey_image(0))
    seq = open_sequence(tmp_path / "a")
    assert len(seq) == 1 and seq.depth_paths is None
    assert seq.target is None and seq.groundtruth is None and seq.imu is None and seq.joints is None


def test_writer_refuses_bad_input(tmp_path):
    with SequenceWriter(tmp_path / "a", CAM) as w:
        w.add_frame(1.0, grey_image(0))
        with pytest.raises(SequenceError, match="not after"):
            w.add_frame(1.0, grey_image(1))
        with pytest.raises(SequenceError, match="1 us apart"):
            w.add_frame(1.0000001, grey_image(1))
        with pytest.raises(SequenceError, match="camera.toml says 32x24"):
            w.add_frame(2.0, np.zeros((10, 10), np.uint8))
        with pytest.raises(SequenceError, match="dtype float64"):
            w.add_frame(2.0, np.zeros((CAM.height, CAM.width)))
        with pytest.raises(SequenceError, match="rigid"):
            w.add_groundtruth(0.0, 2.0 * np.eye(4))
    with pytest.raises(SequenceError, match="already holds the finished results of wvr sim record") as e:
        SequenceWriter(tmp_path / "a", CAM)
    assert "overwrite" not in str(e.value) and "give another --out" in str(e.value)  # no API argument in the hint
    with SequenceWriter(tmp_path / "a", CAM, overwrite=True) as w:
        w.add_frame(5.0, grey_image(0))
    assert len(open_sequence(tmp_path / "a")) == 1
