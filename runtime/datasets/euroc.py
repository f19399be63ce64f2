"""EuRoC / ASL folders (``mav0/``) read as shipped, and converted to our layout.

::

    mav0/
      cam0/data.csv          "#timestamp [ns],filename"; the images in cam0/data/
      cam0/sensor.yaml       camera_model pinhole, intrinsics [fu, fv, cu, cv], resolution [w, h],
                             distortion_model radial-tangential (or equidistant) + coefficients,
                             T_BS: the camera in the body frame (p_body = T_BS p_cam)
      imu0/data.csv          optional: ns, w_xyz rad/s, a_xyz m/s^2 in the IMU's frame
      imu0/sensor.yaml       optional: the IMU's T_BS (identity in EuRoC: the body is the IMU)
      state_groundtruth_estimate0/data.csv
                             optional: ns, p_xyz (m), q_wxyz (, v, biases): the body's pose
                             T_world_body (its sensor.yaml's T_BS, identity in EuRoC, applied)

Frames: the IMU's rates and specific force are rotated into the camera's optical frame,
x_cam = R_cam_imu x_imu with R_cam_imu = R_BS(cam)^T R_BS(imu), and the specific force is moved
to the camera's centre, r from the IMU (6.9 cm in EuRoC): f + dw/dt x r + w x (w x r), dw/dt by
central differences of the rates (a drone's vibration makes this 0.1-0.3 m/s^2 RMS on MH_01, a
fifth of its flight's accelerations), so that imu.txt is what an IMU at the camera would read, as
shared/formats.md has it. The ground truth becomes the camera's
pose T_world_cam = T_world_body T_BS(cam), as groundtruth.txt holds. ORB-SLAM3's
``MH01_GT.txt`` style (CSV: ns, tx ty tz, qw qx qy qz: the left camera's centre, its rotation
world-to-camera) is read instead when given (``groundtruth=``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraFileError, CameraIntrinsics
from runtime.sequence import ImuLog, SequenceError, Trajectory

from .common import (DatasetSequence, check_increasing, data_rows, ns_to_seconds, numbers, parse_ns, rigid,
                     write_layout)

_CSV_LAYOUT = "#timestamp [ns],filename"
_IMU_LAYOUT = "timestamp [ns], w_x, w_y, w_z [rad/s], a_x, a_y, a_z [m/s^2]"
_GT_LAYOUT = "timestamp [ns], p_x, p_y, p_z [m], q_w, q_x, q_y, q_z"

#: distortion_model names (Kalibr's and their short forms) -> our lens model and its terms in the
#: order of distortion_coefficients.
DISTORTION_MODELS = {
    "radial-tangential": ("brown", ("k1", "k2", "p1", "p2")),
    "radtan": ("brown", ("k1", "k2", "p1", "p2")),
    "equidistant": ("fisheye", ("k1", "k2", "k3", "k4")),
    "equi": ("fisheye", ("k1", "k2", "k3", "k4")),
}
CAMERA_MODELS = ("pinhole",)


def find_mav0(path: str | Path) -> Path | None:
    """The mav0 folder at ``path`` (one holding cam0/data.csv) or inside it (path/mav0), else None."""
    path = Path(path)
    for root in (path, path / "mav0"):
        if (root / "cam0" / "data.csv").is_file():
            return root
    return None


# ---------------------------------------------------------------------------------------------
# sensor.yaml
# ---------------------------------------------------------------------------------------------

def _load_yaml(path: Path) -> dict:
    if not path.is_file():
        raise SequenceError(f"{path}: no such file; an EuRoC folder has cam0/sensor.yaml beside cam0/data.csv")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise SequenceError(f"{path}: not readable YAML ({first}); give the data set's sensor.yaml") from None
    if not isinstance(doc, dict):
        raise SequenceError(f"{path}: not a YAML mapping; give the data set's sensor.yaml (keys T_BS, intrinsics, ...)")
    return doc


def _T_BS(doc: dict, path: Path) -> np.ndarray:
    """The sensor.yaml's T_BS (4, 4): {rows: 4, cols: 4, data: [16 numbers]} or a 4x4 list."""
    if "T_BS" not in doc:
        raise SequenceError(f"{path}: no T_BS; add the sensor's pose in the body frame (T_BS: {{rows: 4, cols: 4, "
                            f"data: [16 numbers, row by row]}})")
    v = doc["T_BS"]
    data = v.get("data") if isinstance(v, dict) else v
    try:
        T = np.array(data, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        raise SequenceError(f"{path}: T_BS must hold 16 numbers (rows: 4, cols: 4, data: [...], row by row)") from None
    return rigid(T, f"{path}: T_BS")


def _vector(doc: dict, key: str, n: int, path: Path, hint: str) -> list[float]:
    v = doc.get(key)
    if (not isinstance(v, list) or len(v) != n
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
        raise SequenceError(f"{path}: {key} = {v!r} must be {n} numbers ({hint})")
    return [float(x) for x in v]


def read_camera_yaml(path: str | Path) -> tuple[CameraIntrinsics, np.ndarray]:
    """cam0/sensor.yaml -> (intrinsics, T_body_cam (4, 4), metres).

    camera_model must be pinhole; distortion_model radial-tangential gives our ``brown`` with
    k1 k2 p1 p2, equidistant our ``fisheye`` with k1..k4. Any other model is an error naming the
    file and the models read.
    """
    path = Path(path)
    doc = _load_yaml(path)
    cam_model = doc.get("camera_model", "pinhole")
    if cam_model not in CAMERA_MODELS:
        raise SequenceError(f"{path}: camera_model {cam_model!r} is not supported; wvr reads camera_model: pinhole "
                            f"(calibrate the camera with a pinhole model, e.g. Kalibr's pinhole-radtan)")
    dist = doc.get("distortion_model")
    if dist not in DISTORTION_MODELS:
        raise SequenceError(f"{path}: distortion_model {dist!r} is not supported; use radial-tangential (k1 k2 p1 p2) "
                            f"or equidistant (k1 k2 k3 k4)")
    model, terms = DISTORTION_MODELS[dist]
    coeffs = _vector(doc, "distortion_coefficients", len(terms), path, f"{dist}: {' '.join(terms)}")
    fu, fv, cu, cv = _vector(doc, "intrinsics", 4, path, "[fu, fv, cu, cv] in pixels")
    w, h = _vector(doc, "resolution", 2, path, "[width, height] in pixels")
    if w != int(w) or h != int(h):
        raise SequenceError(f"{path}: resolution = {[w, h]} must be whole pixels ([width, height])")
    try:
        cam = CameraIntrinsics(width=int(w), height=int(h), fx=fu, fy=fv, cx=cu, cy=cv, model=model,
                               **dict(zip(terms, coeffs)))
    except CameraFileError as e:
        raise SequenceError(f"{path}: {e}") from None
    return cam, _T_BS(doc, path)


# ---------------------------------------------------------------------------------------------
# data.csv files
# ---------------------------------------------------------------------------------------------

def read_frames_csv(path: str | Path) -> tuple[np.ndarray, list[Path], str | None]:
    """cam0/data.csv -> (stamps (N,) int64 ns, image paths in cam0/data/, a note or None).

    The stamps must strictly increase. Every listed image must exist, with one exception: the
    images present may be one unbroken run of rows (a cut of the recording, as EuRoC's "reduced"
    sets ship with the full data.csv); that run is the sequence and the note says so. A missing
    image inside the run, or no image at all, is an error naming the file.
    """
    path = Path(path)
    ns, files, lines = [], [], []
    for n, f in data_rows(path, f"camera's image list ('{_CSV_LAYOUT}')"):
        if len(f) != 2 or not f[1]:
            raise SequenceError(f"{path}:{n}: expected '{_CSV_LAYOUT}', got {','.join(f)!r}; fix the row or start it "
                                f"with '#'")
        ns.append(parse_ns(f[0], f"{path}:{n}"))
        files.append(path.parent / "data" / f[1])
        lines.append(n)
    check_increasing(ns, lines, path)
    present = np.flatnonzero([p.is_file() for p in files])
    if not files:
        raise SequenceError(f"{path}: lists no images; each row is '{_CSV_LAYOUT}'")
    if present.size == 0:
        raise SequenceError(f"{path}:{lines[0]}: {files[0]} is missing, as are all {len(files)} images it lists; put "
                            f"the images in {path.parent / 'data'}")
    a, b = int(present[0]), int(present[-1]) + 1
    missing = [i for i in range(a, b) if not files[i].is_file()]
    if missing:
        i = missing[0]
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise SequenceError(f"{path}:{lines[i]}: {files[i]} is missing{more}; put the images in "
                            f"{path.parent / 'data'} or remove their rows from data.csv")
    note = None
    if b - a < len(files):
        note = (f"{path}: {b - a} of its {len(files)} images are present (lines {lines[a]}-{lines[b - 1]}); "
                f"the sequence is those")
    return np.array(ns[a:b], dtype=np.int64), files[a:b], note


def read_imu_csv(path: str | Path, R_cam_imu: np.ndarray = np.eye(3), r_imu_cam: np.ndarray = np.zeros(3)
                 ) -> tuple[np.ndarray, ImuLog]:
    """imu0/data.csv -> (stamps (N,) int64 ns, ImuLog in the camera frame: t s, gyro rad/s,
    accel m/s^2, each rotated by R_cam_imu (3, 3), the specific force moved to the camera's
    centre ``r_imu_cam`` (3,) m, IMU frame, from the IMU (the module's docstring)."""
    path = Path(path)
    ns, vals, lines = [], [], []
    for n, f in data_rows(path, f"IMU log ('{_IMU_LAYOUT}')"):
        if len(f) != 7:
            raise SequenceError(f"{path}:{n}: {len(f)} fields, expected 7 ({_IMU_LAYOUT}); fix the row or start it "
                                f"with '#'")
        ns.append(parse_ns(f[0], f"{path}:{n}"))
        vals.append(numbers(f[1:], f"{path}:{n}", _IMU_LAYOUT))
        lines.append(n)
    check_increasing(ns, lines, path)
    v = np.array(vals, dtype=np.float64).reshape(-1, 6)
    t, w, f = ns_to_seconds(ns), v[:, :3], v[:, 3:]
    r = np.asarray(r_imu_cam, float)
    if len(t) >= 2 and np.any(r != 0):
        f = f + np.cross(np.gradient(w, t, axis=0), r) + np.cross(w, np.cross(w, r))
    return np.array(ns, dtype=np.int64), ImuLog(t, w @ R_cam_imu.T, f @ R_cam_imu.T)


def _read_pose_csv(path: Path, layout: str, min_fields: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows 'ns, px, py, pz, qw, qx, qy, qz, ...' -> (ns (N,), p (N, 3), q_xyzw (N, 4) unit)."""
    ns, vals, lines = [], [], []
    for n, f in data_rows(path, f"ground truth ('{layout}')"):
        if len(f) < min_fields:
            raise SequenceError(f"{path}:{n}: {len(f)} fields, expected at least {min_fields} ({layout}); fix the "
                                f"row or start it with '#'")
        ns.append(parse_ns(f[0], f"{path}:{n}"))
        vals.append(numbers(f[1:8], f"{path}:{n}", layout))
        lines.append(n)
    check_increasing(ns, lines, path)
    v = np.array(vals, dtype=np.float64).reshape(-1, 7)
    q_wxyz = v[:, 3:7]
    norm = np.linalg.norm(q_wxyz, axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= 1e-3))
    if bad.size:
        i = int(bad[0])
        raise SequenceError(f"{path}:{lines[i]}: quaternion (qw qx qy qz) has norm {norm[i]:.6g}, not 1; check the "
                            f"column order ({layout})")
    q_xyzw = q_wxyz[:, [1, 2, 3, 0]] / norm[:, None]
    return np.array(ns, dtype=np.int64), v[:, :3], q_xyzw


def read_body_groundtruth(path: str | Path, T_body_cam: np.ndarray,
                          T_body_gt: np.ndarray = np.eye(4)) -> tuple[np.ndarray, Trajectory]:
    """state_groundtruth_estimate0/data.csv (the pose T_world_gt of the frame its sensor.yaml's
    T_BS = T_body_gt places in the body) -> (ns (N,), the camera's Trajectory):
    T_world_cam = T_world_gt T_body_gt^-1 T_body_cam."""
    path = Path(path)
    ns, p, q = _read_pose_csv(path, _GT_LAYOUT + ", ...", 8)
    T_world_gt = np.zeros((len(ns), 4, 4))
    T_world_gt[:, :3, :3] = Rotation.from_quat(q).as_matrix() if len(ns) else np.zeros((0, 3, 3))
    T_world_gt[:, :3, 3] = p
    T_world_gt[:, 3, 3] = 1.0
    T_world_cam = T_world_gt @ np.linalg.inv(T_body_gt) @ T_body_cam
    return ns, Trajectory.from_T_world_cam(ns_to_seconds(ns), T_world_cam)


def read_camera_groundtruth(path: str | Path) -> tuple[np.ndarray, Trajectory]:
    """A ground truth already of the camera, ORB-SLAM3's ``MH01_GT.txt`` style (CSV rows 'ns, tx,
    ty, tz, qw, qx, qy, qz'; ns may carry a '.000' fraction) -> (ns (N,), Trajectory).

    Those files hold the camera's centre in the world but the rotation world-to-camera (the
    conjugate of the camera's orientation): read as camera-to-world, MH_01's rotations turn
    against its gyro (angular rates uncorrelated on two axes) and put gravity 90 degrees from where
    its accelerometer has it; conjugated, both agree (benchmarks/NOTES.md). So the quaternion is
    conjugated here, and T_world_cam is the camera's pose as groundtruth.txt holds it."""
    ns, p, q = _read_pose_csv(Path(path), "timestamp [ns], tx, ty, tz, qw, qx, qy, qz (the camera's pose)", 8)
    return ns, Trajectory(ns_to_seconds(ns), p, q * np.array([-1.0, -1.0, -1.0, 1.0]))


# ---------------------------------------------------------------------------------------------
# The folder
# ---------------------------------------------------------------------------------------------

def open_euroc(path: str | Path, groundtruth: str | Path | None = None, camera: str = "cam0") -> DatasetSequence:
    """Read an EuRoC / ASL folder (``mav0`` or the folder holding it) as a sequence.

    groundtruth : a camera ground truth in ORB-SLAM3's MH01_GT.txt style, used instead of
        state_groundtruth_estimate0 (which is then not read).
    camera : which camera folder ("cam0", the left one, or "cam1").
    Errors (unknown camera or lens model, missing images, stamps out of order) raise
    SequenceError naming the file and the fix.
    """
    root = find_mav0(path)
    if root is None or not (root / camera / "data.csv").is_file():
        raise SequenceError(f"{path}: no {camera}/data.csv; give an EuRoC mav0 folder (or the folder holding mav0) "
                            f"with {camera}/data.csv, {camera}/data/ and {camera}/sensor.yaml")
    cam, T_body_cam = read_camera_yaml(root / camera / "sensor.yaml")
    stamps_ns, paths, note = read_frames_csv(root / camera / "data.csv")
    imu_ns = imu = None
    if (root / "imu0" / "data.csv").is_file():
        imu_yaml = root / "imu0" / "sensor.yaml"
        T_body_imu = _T_BS(_load_yaml(imu_yaml), imu_yaml) if imu_yaml.is_file() else np.eye(4)
        R_cam_imu = T_body_cam[:3, :3].T @ T_body_imu[:3, :3]
        r_imu_cam = T_body_imu[:3, :3].T @ (T_body_cam[:3, 3] - T_body_imu[:3, 3])
        imu_ns, imu = read_imu_csv(root / "imu0" / "data.csv", R_cam_imu, r_imu_cam)
    gt_ns = gt = None
    if groundtruth is not None:
        gt_ns, gt = read_camera_groundtruth(groundtruth)
    elif (root / "state_groundtruth_estimate0" / "data.csv").is_file():
        gt_yaml = root / "state_groundtruth_estimate0" / "sensor.yaml"
        T_body_gt = _T_BS(_load_yaml(gt_yaml), gt_yaml) if gt_yaml.is_file() else np.eye(4)
        gt_ns, gt = read_body_groundtruth(root / "state_groundtruth_estimate0" / "data.csv", T_body_cam, T_body_gt)
    return DatasetSequence(root=root, camera=cam, timestamps=ns_to_seconds(stamps_ns), paths=paths,
                           groundtruth=gt, imu=imu, source="euroc", stamps_ns=stamps_ns,
                           groundtruth_ns=gt_ns, imu_ns=imu_ns, notes=(note,) if note else ())


def convert_euroc(src: str | Path, dst: str | Path, groundtruth: str | Path | None = None,
                  copy: bool = False) -> DatasetSequence:
    """Write an EuRoC folder as a sequence folder in our layout (rgb.txt with links to, or with
    ``copy`` copies of, the images; camera.toml; imu.txt in the camera frame; groundtruth.txt of
    the camera). Returns the sequence as read from ``src``."""
    seq = open_euroc(src, groundtruth)
    gt_from = groundtruth if groundtruth is not None else "state_groundtruth_estimate0 (body) composed with T_BS"
    write_layout(seq, dst, copy=copy,
                 note=f"converted from the EuRoC folder {seq.root.resolve()} by wvr convert euroc\n"
                      f"ground truth: {gt_from}; stamps are the data set's nanoseconds, exactly")
    return seq
