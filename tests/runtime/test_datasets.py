"""Public benchmarks read as shipped (runtime.datasets): EuRoC, KITTI odometry, TUM depth.

Every folder is synthetic, made in tmp_path; expected values are worked by hand (a known T_BS
applied to a known IMU sample, a pose composed by hand) or by an independent route.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, save_camera
from runtime.datasets import (convert_euroc, convert_kitti, dataset_kind, ns_to_text, open_any, open_euroc,
                              open_kitti, read_depth, read_stamps_ns)
from runtime.sequence import SequenceError, write_trajectory
from wvr.cli import main

W, H = 32, 24
T0 = 1403636584763555584          # an EuRoC stamp: not a float64 of seconds to the nanosecond
DT = 50_000_000 + 7               # 20 Hz, plus odd nanoseconds that float seconds would lose
S = math.sqrt(0.5)

# The camera in the body: turned 90 degrees about the body's z (camera x = body y, camera y =
# -body x), 10 cm along body x.
R_BS = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
T_BS = np.eye(4)
T_BS[:3, :3] = R_BS
T_BS[:3, 3] = [0.1, 0.0, 0.0]


def _image(i: int) -> np.ndarray:
    return np.random.default_rng(i).integers(0, 256, (H, W), dtype=np.uint8)


def _yaml_T(T: np.ndarray) -> str:
    return "T_BS:\n  cols: 4\n  rows: 4\n  data: [" + ", ".join(repr(float(x)) for x in T.ravel()) + "]\n"


def make_mav0(root, n=4, T_bs=T_BS, camera_model="pinhole", distortion="radial-tangential", stamps=None,
              imu=True, gt=True, imu_T_bs=np.eye(4)):
    """A small mav0 folder: n frames, IMU samples and the body's ground truth."""
    mav0 = root / "mav0"
    (mav0 / "cam0" / "data").mkdir(parents=True)
    (mav0 / "cam0" / "sensor.yaml").write_text(
        "sensor_type: camera\ncomment: test\n" + _yaml_T(T_bs) + f"rate_hz: 20\nresolution: [{W}, {H}]\n"
        f"camera_model: {camera_model}\nintrinsics: [30.5, 31.5, 15.25, 11.75] #fu, fv, cu, cv\n"
        f"distortion_model: {distortion}\ndistortion_coefficients: [-0.28, 0.07, 0.0002, 1.7e-05]\n")
    stamps = [T0 + i * DT for i in range(n)] if stamps is None else stamps
    rows = ["#timestamp [ns],filename"]
    for i, ns in enumerate(stamps):
        cv2.imwrite(str(mav0 / "cam0" / "data" / f"{ns}.png"), _image(i))
        rows.append(f"{ns},{ns}.png")
    (mav0 / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    if imu:
        (mav0 / "imu0").mkdir()
        (mav0 / "imu0" / "sensor.yaml").write_text("sensor_type: imu\n" + _yaml_T(imu_T_bs) + "rate_hz: 200\n")
        lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                 "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
        for k in range(3):
            lines.append(f"{T0 + k * 5_000_001},{0.1 + k},0.2,0.3,9.81,-0.5,{1.5 + k}")
        (mav0 / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
    if gt:
        (mav0 / "state_groundtruth_estimate0").mkdir()
        # Body at (1, 2, 3), turned 90 degrees about world z (q_wxyz = (S, 0, 0, S)); then moved.
        lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
                 "q_RS_z [], v_x, v_y, v_z, bw_x, bw_y, bw_z, ba_x, ba_y, ba_z"]
        for k in range(3):
            lines.append(f"{T0 + k * DT},{1 + k},2,3,{S},0,0,{S}," + ",".join(["0.0"] * 9))
        (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(lines) + "\n")
    return mav0


def make_kitti(root, n=5, subset=None, poses=True, times_n=None, calib=None):
    """A small KITTI odometry sequence folder (sequences/07 layout) with poses/07.txt."""
    seq = root / "07"
    (seq / "image_0").mkdir(parents=True)
    for i in (range(n) if subset is None else subset):
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), _image(i))
    times_n = n if times_n is None else times_n
    (seq / "times.txt").write_text("".join(f"{k * 1.038752e-01:e}\n" for k in range(times_n)))
    calib = calib if calib is not None else (
        "P0: 3.07e+01 0.0 1.55e+01 0.0 0.0 3.07e+01 1.15e+01 0.0 0.0 0.0 1.0 0.0\n"
        "P1: 3.07e+01 0.0 1.55e+01 -1.1e+01 0.0 3.07e+01 1.15e+01 0.0 0.0 0.0 1.0 0.0\n")
    (seq / "calib.txt").write_text(calib)
    if poses:
        (seq / "poses").mkdir()
        # Frame k: turned k * 10 degrees about the camera's y (yaw of a car), at (k, 0, 2k); printed
        # to 7 digits as KITTI does, so the rotations are off by about 1e-7.
        lines = []
        for k in range(times_n):
            c, s_ = math.cos(math.radians(10 * k)), math.sin(math.radians(10 * k))
            P = [[c, 0, s_, k], [0, 1, 0, 0], [-s_, 0, c, 2 * k]]
            lines.append(" ".join(f"{x:e}" for x in np.ravel(P)))
        (seq / "poses" / "07.txt").write_text("\n".join(lines) + "\n")
    return seq


def _run_cli(argv, capsys):
    rc = main(argv)
    return rc, capsys.readouterr()


# ------------------------------------------------------------------------------------- EuRoC

def test_euroc_camera_and_exact_stamps(tmp_path):
    make_mav0(tmp_path)
    seq = open_euroc(tmp_path)                    # the folder holding mav0
    assert seq.root == tmp_path / "mav0" and seq.source == "euroc" and len(seq) == 4
    cam = seq.camera
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (W, H, 30.5, 31.5, 15.25, 11.75)
    assert cam.model == "brown" and (cam.k1, cam.k2, cam.p1, cam.p2, cam.k3) == (-0.28, 0.07, 0.0002, 1.7e-05, 0.0)
    assert seq.stamps_ns.tolist() == [T0 + i * DT for i in range(4)]          # integers, to the nanosecond
    assert seq.timestamps[1] == float("1403636584.813555591")
    assert seq.ns_at(seq.timestamps[2]) == T0 + 2 * DT
    assert ns_to_text(T0 + DT) == "1403636584.813555591"
    f = seq.frame(2)
    np.testing.assert_array_equal(f.image, _image(2))
    assert open_euroc(tmp_path / "mav0").stamps_ns.tolist() == seq.stamps_ns.tolist()


def test_euroc_equidistant_is_opencv_fisheye(tmp_path):
    make_mav0(tmp_path, distortion="equidistant", imu=False, gt=False)
    cam = open_euroc(tmp_path).camera
    assert cam.model == "fisheye" and (cam.k1, cam.k2, cam.k3, cam.k4) == (-0.28, 0.07, 0.0002, 1.7e-05)


def test_euroc_imu_rotated_into_the_camera_frame(tmp_path):
    make_mav0(tmp_path)
    seq = open_euroc(tmp_path)
    # By hand: camera x = body y, camera y = -body x, camera z = body z. Body sample k:
    # w = (0.1 + k, 0.2, 0.3), a = (9.81, -0.5, 1.5 + k).
    np.testing.assert_allclose(seq.imu.gyro, [[0.2, -0.1, 0.3], [0.2, -1.1, 0.3], [0.2, -2.1, 0.3]], atol=1e-15)
    # The specific force at the camera, r = (0.1, 0, 0) m from the IMU: dw/dt is along r (no
    # tangential term), and w x (w x r) = (w.r) w - |w|^2 r = (-0.013, 0.002, 0.003),
    # (-0.013, 0.022, 0.033), (-0.013, 0.042, 0.063) for k = 0, 1, 2.
    np.testing.assert_allclose(seq.imu.accel, [[-0.498, -9.797, 1.503], [-0.478, -9.797, 2.533],
                                               [-0.458, -9.797, 3.563]], atol=1e-12)
    assert seq.imu_ns.tolist() == [T0, T0 + 5_000_001, T0 + 10_000_002]


def test_euroc_imu_with_its_own_extrinsics(tmp_path):
    # An IMU not at the body's axes: a vector is the same body-frame vector whether it goes
    # through the camera's T_BS or the IMU's.
    rng = np.random.default_rng(5)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T_imu = np.eye(4)
    T_imu[:3, :3] = Q * np.sign(np.linalg.det(Q))
    make_mav0(tmp_path, imu_T_bs=T_imu, gt=False)
    seq = open_euroc(tmp_path)
    w_imu = np.array([[0.1 + k, 0.2, 0.3] for k in range(3)])
    np.testing.assert_allclose(seq.imu.gyro @ R_BS.T, w_imu @ T_imu[:3, :3].T, atol=1e-9)


def test_euroc_groundtruth_is_the_cameras_pose(tmp_path):
    make_mav0(tmp_path)
    seq = open_euroc(tmp_path)
    T = seq.groundtruth.T_world_cam()
    # By hand: body at (1, 2, 3) turned 90 deg about world z; the camera 10 cm along body x is
    # 10 cm along world y from it; camera x = body y = world -x; camera y = -body x = world -y.
    np.testing.assert_allclose(T[0, :3, 3], [1.0, 2.1, 3.0], atol=1e-12)
    np.testing.assert_allclose(T[0, :3, :3], [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[2, :3, 3], [3.0, 2.1, 3.0], atol=1e-12)
    assert seq.groundtruth_ns.tolist() == [T0, T0 + DT, T0 + 2 * DT]


def test_euroc_orbslam_groundtruth_file(tmp_path):
    make_mav0(tmp_path)
    gt = tmp_path / "MH01_GT.txt"
    gt.write_text("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n"
                  f"{T0}.0000000000,4.5,-1.5,0.75,{S},{S},0.0,0.0\n"
                  f"{T0 + DT}.0000000000,4.6,-1.5,0.75,1.0,0.0,0.0,0.0\n")
    seq = open_euroc(tmp_path, groundtruth=gt)
    assert seq.groundtruth_ns.tolist() == [T0, T0 + DT]
    np.testing.assert_allclose(seq.groundtruth.p_world_cam, [[4.5, -1.5, 0.75], [4.6, -1.5, 0.75]])
    # w first in the file, and the rotation world-to-camera there: conjugated.
    np.testing.assert_allclose(seq.groundtruth.q_xyzw[0], [-S, 0, 0, S], atol=1e-12)
    # Already the camera's: T_BS is not applied.
    np.testing.assert_allclose(seq.groundtruth.T_world_cam()[1, :3, :3], np.eye(3), atol=1e-12)


def test_orbslam_groundtruth_turns_as_the_gyro_says(tmp_path):
    """Two consecutive rows of ORB-SLAM3's MH01_GT.txt (50 ms apart, the fastest turn of MH_01's
    first 35 s) read as the camera's poses turn as EuRoC's gyro measured over that interval
    (imu0, rotated into cam0's frame by the sensors' T_BS): 0.28, 0.74, 0.51 rad/s."""
    make_mav0(tmp_path, gt=False)
    gt = tmp_path / "MH01_GT.txt"
    gt.write_text("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n"
                  "1403636593913555456.0000000000,4.7806380295,-1.9582612030,0.7859340459,0.3198183286,"
                  "0.7623086407,0.4903063799,-0.276046059218\n"
                  "1403636593963555584.0000000000,4.7995886731,-1.9390944066,0.7854697939,0.3308205249,"
                  "0.7702916180,0.4744559940,-0.268514642658\n")
    traj = open_euroc(tmp_path, groundtruth=gt).groundtruth
    T = traj.T_world_cam()
    w_cam = Rotation.from_matrix(T[0, :3, :3].T @ T[1, :3, :3]).as_rotvec() / (traj.t[1] - traj.t[0])
    np.testing.assert_allclose(w_cam, [0.279, 0.739, 0.506], atol=0.1)


def test_euroc_reduced_set_reads_the_images_present(tmp_path):
    mav0 = make_mav0(tmp_path, n=6, imu=False, gt=False)
    for i in (0, 5):
        (mav0 / "cam0" / "data" / f"{T0 + i * DT}.png").unlink()
    seq = open_euroc(tmp_path)
    assert seq.stamps_ns.tolist() == [T0 + i * DT for i in range(1, 5)]
    assert len(seq.notes) == 1 and "4 of its 6 images" in seq.notes[0]


@pytest.mark.parametrize("copy", [False, True])
def test_euroc_convert_then_open_equals_open(tmp_path, copy):
    make_mav0(tmp_path / "src")
    direct = open_any(tmp_path / "src")
    convert_euroc(tmp_path / "src", tmp_path / "seq", copy=copy)
    conv = open_any(tmp_path / "seq")
    assert dataset_kind(tmp_path / "seq") == "tum" and conv.source == "tum"
    assert (tmp_path / "seq" / "rgb" / f"{T0}.png").is_symlink() is not copy
    assert conv.camera == direct.camera
    assert conv.stamps_ns.tolist() == direct.stamps_ns.tolist()
    np.testing.assert_array_equal(conv.timestamps, direct.timestamps)
    for a, b in zip(conv.frames(), direct.frames()):
        np.testing.assert_array_equal(a.image, b.image)
    assert conv.imu_ns.tolist() == direct.imu_ns.tolist()
    np.testing.assert_allclose(conv.imu.gyro, direct.imu.gyro, atol=1e-9)
    np.testing.assert_allclose(conv.imu.accel, direct.imu.accel, atol=1e-9)
    assert conv.groundtruth_ns.tolist() == direct.groundtruth_ns.tolist()
    np.testing.assert_allclose(conv.groundtruth.T_world_cam(), direct.groundtruth.T_world_cam(), atol=1e-9)
    assert read_stamps_ns(tmp_path / "seq" / "rgb.txt").tolist() == direct.stamps_ns.tolist()


def test_cli_convert_euroc(tmp_path, capsys):
    make_mav0(tmp_path / "src")
    rc, out = _run_cli(["convert", "euroc", str(tmp_path / "src" / "mav0"), "--out", str(tmp_path / "seq")], capsys)
    assert rc == 0, out.err
    assert "4 frames" in out.out and "3 IMU samples" in out.out and "3 ground-truth poses" in out.out
    seq = open_any(tmp_path / "seq")
    assert seq.stamps_ns.tolist() == [T0 + i * DT for i in range(4)]
    # Refused the second time: the folder already holds a sequence.
    rc, out = _run_cli(["convert", "euroc", str(tmp_path / "src"), "--out", str(tmp_path / "seq")], capsys)
    # The folder holds the first conversion's finished results: refused, one line, naming the fix.
    assert rc == 2 and "already holds the finished" in out.err and "another --out" in out.err



def test_cli_eval_reads_a_mav0_folder_as_shipped(tmp_path, capsys):
    """wvr eval scores against EuRoC's own ground truth (the body's, moved to the camera), as wvr
    slam reads the folder: a trajectory equal to it scores 0, one 5 cm off along x scores 5 cm."""
    make_mav0(tmp_path)
    gt = open_any(tmp_path).groundtruth
    T = gt.T_world_cam()
    for name, dx in (("same", 0.0), ("off", 0.05)):
        (tmp_path / name).mkdir()
        T_est = T.copy()
        T_est[:, 0, 3] += dx
        write_trajectory(tmp_path / name / "trajectory.tum", gt.t, T_est)
        rc, out = _run_cli(["eval", str(tmp_path / "mav0"), str(tmp_path / name), "--align", "none"], capsys)
        assert rc == 0, out.err
        assert "poses matched: 3 of 3" in out.out
        assert f"ATE (no alignment):  RMSE {100 * dx:.2f} cm" in out.out, out.out


# ------------------------------------------------------------------------------------- KITTI

def test_kitti_reads_calib_times_and_poses(tmp_path):
    make_kitti(tmp_path)
    seq = open_kitti(tmp_path / "07")
    cam = seq.camera
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (W, H, 30.7, 30.7, 15.5, 11.5)
    assert seq.stamps_ns.tolist() == [0, 103875200, 207750400, 311625600, 415500800]
    T = seq.groundtruth.T_world_cam()
    c, s_ = math.cos(math.radians(30)), math.sin(math.radians(30))
    np.testing.assert_allclose(T[3, :3, 3], [3, 0, 6], atol=1e-12)
    np.testing.assert_allclose(T[3, :3, :3], [[c, 0, s_], [0, 1, 0], [-s_, 0, c]], atol=1e-6)
    np.testing.assert_array_equal(seq.frame(4).image, _image(4))


def test_kitti_subset_of_frames_picks_their_rows(tmp_path):
    make_kitti(tmp_path, subset=[2, 3, 4], times_n=10)
    seq = open_kitti(tmp_path / "07")
    assert seq.stamps_ns.tolist() == [207750400, 311625600, 415500800]
    assert len(seq.groundtruth) == 10
    np.testing.assert_array_equal(seq.frame(0).image, _image(2))


def test_kitti_poses_given_explicitly(tmp_path):
    seq_dir = make_kitti(tmp_path)
    (seq_dir / "poses" / "07.txt").rename(tmp_path / "other.txt")
    assert open_kitti(seq_dir).groundtruth is None
    seq = open_kitti(seq_dir, poses=tmp_path / "other.txt")
    np.testing.assert_allclose(seq.groundtruth.p_world_cam[2], [2, 0, 4], atol=1e-12)


@pytest.mark.parametrize("copy", [False, True])
def test_kitti_convert_then_open_equals_open(tmp_path, copy):
    src = make_kitti(tmp_path)
    direct = open_any(src)
    assert direct.source == "kitti"
    convert_kitti(src, tmp_path / "seq", copy=copy)
    conv = open_any(tmp_path / "seq")
    assert conv.camera == direct.camera
    assert conv.stamps_ns.tolist() == direct.stamps_ns.tolist()
    np.testing.assert_array_equal(conv.timestamps, direct.timestamps)
    for a, b in zip(conv.frames(), direct.frames()):
        np.testing.assert_array_equal(a.image, b.image)
    assert conv.imu is None and direct.imu is None
    np.testing.assert_allclose(conv.groundtruth.T_world_cam(), direct.groundtruth.T_world_cam(), atol=1e-9)


def test_cli_convert_kitti(tmp_path, capsys):
    src = make_kitti(tmp_path)
    rc, out = _run_cli(["convert", "kitti", str(src), "--out", str(tmp_path / "seq"), "--copy"], capsys)
    assert rc == 0, out.err
    assert "5 frames" in out.out and "copies of" in out.out
    assert not (tmp_path / "seq" / "rgb" / "000000.png").is_symlink()


# ------------------------------------------------------------------------------------- TUM depth

def _tum(root, depth: np.ndarray | None = None, depth_t: str = "1305031102.175304"):
    root.mkdir()
    save_camera(CameraIntrinsics(width=W, height=H, fx=30.0, fy=30.0, cx=15.5, cy=11.5), root / "camera.toml")
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    cv2.imwrite(str(root / "rgb" / "1.png"), _image(0))
    (root / "rgb.txt").write_text("1305031102.175304 rgb/1.png\n")
    if depth is not None:
        cv2.imwrite(str(root / "depth" / "1.png"), depth)
        (root / "depth.txt").write_text(f"{depth_t} depth/1.png\n")
    return root


def test_tum_depth_in_metres(tmp_path):
    raw = np.full((H, W), 5000, np.uint16)
    raw[0, 0] = 0
    raw[1, 2] = 12345
    seq = open_any(_tum(tmp_path / "tum", raw))
    assert seq.source == "tum" and seq.stamps_ns.tolist() == [1305031102175304000]
    d = seq.depth(0)
    assert d.dtype == np.float32 and np.isnan(d[0, 0])
    assert d[1, 2] == np.float32(12345 / 5000) and d[5, 5] == 1.0
    d2 = read_depth(tmp_path / "tum" / "depth" / "1.png", seq.camera, depth_scale=1000.0)
    assert d2[1, 2] == np.float32(12.345)


def test_tum_depth_associated_by_nearest_time(tmp_path):
    # Real TUM RGB-D stamps depth apart from colour (up to ~15 ms): 12 ms is the frame's, 30 ms not.
    raw = np.full((H, W), 10000, np.uint16)
    assert open_any(_tum(tmp_path / "a", raw, "1305031102.187304")).depth(0)[3, 3] == 2.0
    assert open_any(_tum(tmp_path / "b", raw, "1305031102.205304")).depth(0) is None
    # The plain reader (map scoring, the stabilise bench) associates and scales as open_any does.
    from runtime.sequence import open_sequence

    assert open_sequence(tmp_path / "a").depth(0)[3, 3] == 2.0 and open_sequence(tmp_path / "b").depth(0) is None
    cam_toml = tmp_path / "a" / "camera.toml"
    cam_toml.write_text(cam_toml.read_text().replace("[camera]", "[camera]\ndepth_scale = 1000.0"))
    assert open_sequence(tmp_path / "a").depth(0)[3, 3] == 10.0 and open_any(tmp_path / "a").depth(0)[3, 3] == 10.0


# ------------------------------------------------------------------------------------- TUM as shipped

def _tum_as_shipped(root, n=3, name="rgbd_dataset_freiburg1_xyz", header=True):
    """A TUM RGB-D folder as the benchmark ships it: 640x480 colour PNGs, 16-bit depth at its own
    stamps, the commented headers, the 100 Hz ground truth, accelerometer.txt and no camera.toml."""
    root.mkdir()
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    head = lambda what: f"# {what}\n# file: '{name}.bag'\n# timestamp filename\n" if header else ""  # noqa: E731
    rgb, depth = [head("color images")], [head("depth maps")]
    for i in range(n):
        t = 1305031102.175304 + i / 30
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), np.random.default_rng(i).integers(0, 256, (480, 640, 3),
                                                                                          dtype=np.uint8))
        cv2.imwrite(str(root / "depth" / f"{t - 0.015:.6f}.png"), np.full((480, 640), 5000 * (i + 1), np.uint16))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png\n")
        depth.append(f"{t - 0.015:.6f} depth/{t - 0.015:.6f}.png\n")
    (root / "rgb.txt").write_text("".join(rgb))
    (root / "depth.txt").write_text("".join(depth))
    gt = [f"{1305031102.17 + k / 100:.4f} {0.01 * k:.4f} 0 0 0 0 0 1\n" for k in range(12)]
    (root / "groundtruth.txt").write_text("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n" + "".join(gt))
    (root / "accelerometer.txt").write_text("# accelerometer data\n1305031102.17 0.0 -9.81 0.0\n")
    return root


def test_tum_as_shipped_takes_its_freiburg_camera(tmp_path):
    from runtime.datasets import FREIBURG_CAMERAS
    from runtime.sequence import open_sequence

    seq = open_any(_tum_as_shipped(tmp_path / "rec"))           # named by rgb.txt's header
    assert seq.camera == FREIBURG_CAMERAS[1] and "Freiburg 1" in seq.notes[0]
    assert len(seq) == 3 and seq.frame(2).image is not None and seq.depth(2)[240, 320] == 3.0
    assert len(seq.groundtruth) == 12
    # Named by the folder, as the benchmark's archives unpack; a camera.toml of the user's wins.
    seq2 = open_any(_tum_as_shipped(tmp_path / "rgbd_dataset_freiburg3_long_office_household", header=False))
    assert seq2.camera == FREIBURG_CAMERAS[3] and seq2.camera.k1 == 0.0
    save_camera(CameraIntrinsics(640, 480, 500.0, 500.0, 320.0, 240.0), tmp_path / "rec" / "camera.toml")
    assert open_any(tmp_path / "rec").camera.fx == 500.0 and open_any(tmp_path / "rec").notes == ()
    assert open_sequence(tmp_path / "rec").camera.fx == 500.0


def test_freiburg_cameras_undistort_as_opencv(tmp_path):
    # The published terms are OpenCV's d0..d4 (k1 k2 p1 p2 k3): our lens inverts as OpenCV does.
    from kinematics.camera import undistort
    from runtime.datasets import FREIBURG_CAMERAS

    uv = np.array([[0.0, 0.0], [639.0, 0.0], [0.0, 479.0], [639.0, 479.0], [100.0, 300.0], [320.0, 240.0]])
    for cam in FREIBURG_CAMERAS.values():
        K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
        d = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3])
        cv = cv2.undistortPoints(uv[:, None], K, d, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                                100, 1e-12))[:, 0]
        assert np.allclose(undistort(cam, uv), cv, atol=1e-6)


def test_cli_eval_reads_tum_as_shipped(tmp_path, capsys):
    seq = _tum_as_shipped(tmp_path / "rgbd_dataset_freiburg2_xyz", header=False)
    res = tmp_path / "res"
    res.mkdir()
    write_trajectory(res / "trajectory.tum", np.array([1305031102.175304, 1305031102.208637]),
                     np.stack([np.eye(4), np.eye(4)]))
    rc, out = _run_cli(["eval", str(seq), str(res)], capsys)
    assert rc == 0, out.err
    assert "poses matched: 2 of 2" in out.out


def test_tum_without_camera_toml_not_freiburg_is_refused(tmp_path, capsys):
    seq = _tum_as_shipped(tmp_path / "my_recording", header=False)
    line = _one_line_error(["slam", str(seq), "--out", str(tmp_path / "o")], capsys, "camera.toml", "freiburg")
    assert "write a camera.toml" in line


# ------------------------------------------------------------------------------------- bad input

def _one_line_error(argv, capsys, *words):
    rc, out = _run_cli(argv, capsys)
    assert rc == 2
    lines = out.err.strip().splitlines()
    assert len(lines) == 1, out.err
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def _convert_euroc(tmp_path):
    return ["convert", "euroc", str(tmp_path), "--out", str(tmp_path / "out")]


def test_bad_camera_model(tmp_path, capsys):
    make_mav0(tmp_path, camera_model="omni")
    _one_line_error(_convert_euroc(tmp_path), capsys, "sensor.yaml", "camera_model 'omni'", "pinhole")


def test_bad_distortion_model(tmp_path, capsys):
    make_mav0(tmp_path, distortion="fov")
    _one_line_error(_convert_euroc(tmp_path), capsys, "sensor.yaml", "distortion_model 'fov'", "radial-tangential")


def test_data_csv_missing_images(tmp_path, capsys):
    mav0 = make_mav0(tmp_path, n=5)
    for i in (1, 2):
        (mav0 / "cam0" / "data" / f"{T0 + i * DT}.png").unlink()
    _one_line_error(_convert_euroc(tmp_path), capsys, "data.csv:3", f"{T0 + DT}.png is missing (and 1 more)")
    for i in (0, 3, 4):
        (mav0 / "cam0" / "data" / f"{T0 + i * DT}.png").unlink()
    _one_line_error(_convert_euroc(tmp_path), capsys, "data.csv", "all 5 images")


def test_stamps_out_of_order(tmp_path, capsys):
    make_mav0(tmp_path, stamps=[T0, T0 + 2 * DT, T0 + DT])
    _one_line_error(_convert_euroc(tmp_path), capsys, "cam0/data.csv:4", "not after", "increasing time order")


def test_a_stamp_beyond_int64_nanoseconds_is_named_not_an_overflow(tmp_path, capsys):
    (tmp_path / "rgb.txt").write_text("# timestamp filename\n0.0 rgb/0.png\n1e300 rgb/1.png\n")
    with pytest.raises(SequenceError, match=r"rgb.txt:3: timestamp '1e300' is beyond 9.22e\+09 s"):
        read_stamps_ns(tmp_path / "rgb.txt")
    mav0 = make_mav0(tmp_path / "euroc")
    path = mav0 / "imu0" / "data.csv"
    path.write_text(path.read_text() + "99999999999999999999,0,0,0,0,0,9.8\n")
    _one_line_error(_convert_euroc(tmp_path / "euroc"), capsys, "imu0/data.csv", "beyond 9.22e+09 s")


def test_imu_stamps_out_of_order(tmp_path, capsys):
    mav0 = make_mav0(tmp_path)
    path = mav0 / "imu0" / "data.csv"
    path.write_text(path.read_text() + f"{T0 + 5_000_001},0,0,0,0,0,9.8\n")
    _one_line_error(_convert_euroc(tmp_path), capsys, "imu0/data.csv:5", "not after")


def test_not_a_dataset(tmp_path, capsys):
    _one_line_error(_convert_euroc(tmp_path), capsys, str(tmp_path), "mav0")


def test_calib_without_p0(tmp_path, capsys):
    src = make_kitti(tmp_path, calib="P1: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    _one_line_error(["convert", "kitti", str(src), "--out", str(tmp_path / "out")], capsys, "calib.txt", "no 'P0:'")


def test_times_shorter_than_images(tmp_path, capsys):
    src = make_kitti(tmp_path, n=5, times_n=3, poses=False)
    _one_line_error(["convert", "kitti", str(src), "--out", str(tmp_path / "out")], capsys, "times.txt",
                    "3 times", "000004.png")


def test_poses_not_matching_times(tmp_path, capsys):
    src = make_kitti(tmp_path, n=5)
    (src / "times.txt").write_text((src / "times.txt").read_text() + "9.9e+00\n")
    _one_line_error(["convert", "kitti", str(src), "--out", str(tmp_path / "out")], capsys, "07.txt",
                    "5 poses", "6 times")


def test_depth_8bit_or_wrong_size(tmp_path, capsys):
    root = _tum(tmp_path / "a", np.full((H, W), 50, np.uint8))
    with pytest.raises(SequenceError, match=r"depth/1\.png: the PNG is 8-bit, not a 16-bit.*uint16"):
        open_any(root)
    with pytest.raises(SequenceError, match=r"the image is 8-bit, not a 16-bit.*uint16"):
        read_depth(root / "depth" / "1.png", open_any(_tum(tmp_path / "b")).camera)
    root = _tum(tmp_path / "c", np.full((H + 2, W), 5000, np.uint16))
    with pytest.raises(SequenceError, match=rf"depth/1\.png: depth image is {W}x{H + 2} but camera.toml says {W}x{H}"):
        open_any(root)
    with pytest.raises(SequenceError, match="depth image is"):
        read_depth(root / "depth" / "1.png", open_any(tmp_path / "b").camera)
