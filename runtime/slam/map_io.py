"""Saving a map and starting from it later (paper, section 4: "to be able to re-locate itself
within that environment at a later time").

A map file is a NumPy ``.npz`` archive: a JSON header (format name, version, the camera model it
was built with, the template size) and the arrays of the map: the features' state entries and
their full covariance, their kinds and anchors, and each feature's appearance (template, first
view's patch, pixel, camera centre and orientation, plane normal and how it was found) and record (id, first frame,
target point, searches and inliers). It is written to a temporary name and moved into place, so
a killed run never leaves half a map.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from kinematics.camera import CameraIntrinsics

from .features import FEATURE_DIMS, INVERSE_DEPTH
from .state import State
from .map_feature import MapFeature

FORMAT = "wvr-slam-map"
VERSION = 1


class MapFileError(ValueError):
    """A map file that cannot be used: not a map, corrupt or truncated, a newer format version,
    or built with another camera. The message names the file and the problem."""


@dataclass
class SavedMap:
    """A map as saved: the features' part of the state (``y`` (m,), ``P`` (m, m)), their kinds
    (N,) and anchors (N, 3, 3), their appearance and record (``features``), the camera pose it
    was last seen from (``T_world_cam`` (4, 4)) and the camera model."""

    y: np.ndarray
    P: np.ndarray
    kinds: np.ndarray
    anchors: np.ndarray
    features: list[MapFeature]
    T_world_cam: np.ndarray
    camera: CameraIntrinsics
    #: What fixed the map's unit when it was made (run.py's scale sources); "arbitrary" is no metre.
    scale: str = "map"

    def state_with_camera(self, cam_dim: int, cfg) -> State:
        """A filter state of this map with a camera block that knows nothing yet: at the last
        saved pose, at rest, with a covariance too wide to search (the session starts lost and
        re-localises), uncorrelated with the map."""
        from .prior import UNKNOWN_POSE_VARIANCES, UNKNOWN_SIGMA_V, UNKNOWN_SIGMA_W, camera_prior
        from .quaternion import quat_from_rotation

        x_v, P_v = camera_prior(cam_dim, self.T_world_cam[:3, 3], quat_from_rotation(self.T_world_cam[:3, :3]),
                                np.diag(UNKNOWN_POSE_VARIANCES), UNKNOWN_SIGMA_V, UNKNOWN_SIGMA_W, cfg)
        n = cam_dim + len(self.y)
        P = np.zeros((n, n))
        P[:cam_dim, :cam_dim] = P_v
        P[cam_dim:, cam_dim:] = self.P
        return State(np.concatenate([x_v, self.y]), P, cam_dim, self.kinds, self.anchors)


#: A saved map's numbers beyond these are not a map (metres and their variances).
MAX_MAP_VALUE = 1e6
MAX_MAP_VARIANCE = 1e12


def check_map_path(path: str | Path) -> Path:
    """The path a map is saved to, exactly as given: a file name ending in .npz, not a folder.
    Raises :class:`MapFileError` naming the fix."""
    path = Path(path)
    if path.is_dir():
        raise MapFileError(f"--save-map {path}: is a folder; give a file name ending in .npz (e.g. {path / 'map.npz'})")
    if path.suffix != ".npz":
        raise MapFileError(f"--save-map {path}: a map file's name ends in .npz; give {path.name}.npz or another .npz name")
    return path


def similar_map(y: np.ndarray, P: np.ndarray, kinds: np.ndarray, anchors: np.ndarray, R: np.ndarray,
                s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The features' state ``y`` (m,), covariance ``P`` (m, m) and anchors (N, 3, 3) in the world
    ``p' = s R p`` (``R`` (3, 3) a rotation, ``s`` > 0). Exact and linear for both kinds: a point
    maps as ``s R``; an inverse-depth feature's centre as ``s R``, its anchor turns with ``R`` (so
    its angles stay) and its inverse depth divides by ``s``."""
    R = np.asarray(R, float)
    J = np.zeros(len(y))                       # the diagonal part; the 3x3 blocks below
    blocks = []
    i = 0
    for kind in np.asarray(kinds, np.intp):
        blocks.append(i)
        if kind == INVERSE_DEPTH:
            J[i + 3:i + 5], J[i + 5] = 1.0, 1.0 / s
        i += int(FEATURE_DIMS[kind])
    M = np.diag(J)
    for i in blocks:
        M[i:i + 3, i:i + 3] = s * R
    y2 = M @ y
    P2 = M @ P @ M.T
    return y2, 0.5 * (P2 + P2.T), np.einsum("ij,njk->nik", R, anchors)


def similar_poses(T_world_cam: np.ndarray, R: np.ndarray, s: float) -> np.ndarray:
    """Camera-to-world poses ``T_world_cam`` (..., 4, 4) in the world ``p' = s R p`` (``R`` (3, 3)
    a rotation, ``s`` > 0): the orientation turned by ``R``, the centre moved as a point."""
    T = np.array(T_world_cam, float)
    T[..., :3, :3] = R @ T[..., :3, :3]
    T[..., :3, 3] = s * T[..., :3, 3] @ R.T
    return T


def save_map(path: str | Path, slam, R_out_world: np.ndarray | None = None, scale: float = 1.0) -> Path:
    """Write the SLAM's current map to ``path`` (a .npz name, :func:`check_map_path`); returns it.
    ``R_out_world``, ``scale``: the similarity (about the origin) that takes the filter's world to
    the one written, as for the trajectory (a natural start's unit and frame made metric and upright
    by the IMU), so that a later session's map is in metres."""
    path = check_map_path(path)
    st = slam.state
    feats = slam.features
    cd = st.cam_dim
    R = np.eye(3) if R_out_world is None else np.asarray(R_out_world, float)
    y, P, anchors = st.x[cd:], st.P[cd:, cd:], st.anchors
    T_world_cam = slam.T_world_cam() if slam.localised else np.full((4, 4), np.nan)
    similar = scale != 1.0 or not np.array_equal(R, np.eye(3))
    if similar:
        y, P, anchors = similar_map(y, P, st.kinds, anchors, R, scale)
        T_world_cam = similar_poses(T_world_cam, R, scale)
        turn = lambda v: None if v is None else R @ v               # noqa: E731
        feats = [replace(f, r0=scale * R @ f.r0, R0=turn(f.R0), normal=turn(f.normal), rays0=None) for f in feats]
    t = slam.template_px
    ph = max((f.patch.shape[0] for f in feats if f.patch is not None), default=1)
    patches = np.zeros((len(feats), ph, ph), np.float32)
    has_patch = np.zeros(len(feats), bool)
    for i, f in enumerate(feats):
        if f.patch is not None and f.patch.shape[0] == ph:
            patches[i], has_patch[i] = f.patch, True
    nan3 = np.full(3, np.nan)
    header = {"format": FORMAT, "version": VERSION, "camera": slam.cam.to_dict(), "template_px": t,
              "features": len(feats), "scale": slam.scale_source}
    arrays = dict(
        header=np.frombuffer(json.dumps(header).encode(), np.uint8),
        y=y, P=P, kinds=st.kinds, anchors=anchors, T_world_cam=T_world_cam,
        ids=np.array([f.id for f in feats], np.int64), first_frame=np.array([f.first_frame for f in feats], np.int64),
        known=np.array([f.known for f in feats], bool), attempts=np.array([f.attempts for f in feats], np.int64),
        successes=np.array([f.successes for f in feats], np.int64),
        templates=np.array([f.template for f in feats], np.float32).reshape(len(feats), t, t),
        patches=patches, has_patch=has_patch,
        uv0=np.array([f.uv0 if f.uv0 is not None else np.full(2, np.nan) for f in feats]).reshape(-1, 2),
        r0=np.array([f.r0 for f in feats]).reshape(-1, 3),
        R0=np.array([f.R0 if f.R0 is not None else np.eye(3) for f in feats]).reshape(-1, 3, 3),
        normal=np.array([f.normal if f.normal is not None else nan3 for f in feats]).reshape(-1, 3),
        normal_from_map=np.array([f.normal_from_map for f in feats], bool),
        normal_view_deg=np.array([f.normal_view_deg for f in feats], float),
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    os.replace(tmp, path)
    return path


def load_map(path: str | Path, camera: CameraIntrinsics | None = None) -> SavedMap:
    """Read a map file; with ``camera``, refuse a map built with another camera model. Raises
    :class:`MapFileError` with a one-line reason."""
    path = Path(path)
    if not path.is_file():
        raise MapFileError(f"{path}: no such map file; give the file wvr slam --save-map wrote")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):          # np.save's single array, renamed
            raise MapFileError(f"{path}: not a wvr SLAM map (a single NumPy array, not a map archive); give a file "
                               "wvr slam --save-map wrote")
        with z:
            if "header" not in z.files:
                raise MapFileError(f"{path}: not a wvr SLAM map (no header); give a file wvr slam --save-map wrote")
            header = json.loads(bytes(z["header"]).decode())
            if not isinstance(header, dict) or header.get("format") != FORMAT:
                fmt = header.get("format") if isinstance(header, dict) else type(header).__name__
                raise MapFileError(f"{path}: not a wvr SLAM map (format {fmt!r}); give a file wvr slam --save-map wrote")
            version = header.get("version")
            if not isinstance(version, int) or version > VERSION:
                raise MapFileError(f"{path}: map format version {version!r} is newer than this wvr reads ({VERSION}); "
                                   "upgrade wvr or rebuild the map")
            a = {k: z[k] for k in z.files}
    except MapFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, UnicodeDecodeError) as e:
        raise MapFileError(f"{path}: corrupt or truncated map file ({type(e).__name__}); save the map again") from None
    try:
        cam = CameraIntrinsics.from_dict(header["camera"], source=f"{path} (its camera)")
    except (KeyError, TypeError, ValueError) as e:
        raise MapFileError(f"{path}: the map's header has no usable camera model ({e})") from None
    if camera is not None and cam.to_dict() != camera.to_dict():
        mine, theirs = camera.to_dict()["camera"], cam.to_dict()["camera"]
        diff = [k for k in sorted(set(mine) | set(theirs), key=lambda k: (k != "model", k)) if mine.get(k) != theirs.get(k)]
        raise MapFileError(f"{path}: the map was built with another camera ({', '.join(diff)} differ from this "
                           "sequence's camera.toml); a map serves only the camera model it was built with")
    try:
        kinds = a["kinds"].astype(np.intp)
        n = len(kinds)
        m = int(FEATURE_DIMS[kinds].sum())
        if a["y"].shape != (m,) or a["P"].shape != (m, m) or a["anchors"].shape != (n, 3, 3) \
                or a["templates"].shape[0] != n or header.get("features") != n:
            raise ValueError("shapes")
        # Maps written before the normals were fitted to the features' looks have none of these.
        view_deg = a["normal_view_deg"] if "normal_view_deg" in a else np.zeros(n)
        if view_deg.shape != (n,):
            raise ValueError("normal_view_deg")
        feats = []
        for i in range(n):
            nrm = a["normal"][i]
            feats.append(MapFeature(
                id=int(a["ids"][i]), template=a["templates"][i].copy(), first_frame=int(a["first_frame"][i]),
                r0=a["r0"][i].copy(), known=bool(a["known"][i]), attempts=int(a["attempts"][i]),
                successes=int(a["successes"][i]), patch=a["patches"][i].copy() if a["has_patch"][i] else None,
                uv0=a["uv0"][i].copy() if np.isfinite(a["uv0"][i]).all() else None, R0=a["R0"][i].copy(),
                normal=nrm.copy() if np.isfinite(nrm).all() else None, normal_from_map=bool(a["normal_from_map"][i]),
                normal_view_deg=float(view_deg[i])))
        T = a["T_world_cam"]
        if not np.isfinite(T).all():
            T = np.eye(4)
        scale = header.get("scale", "map")       # maps written before the key: as they were read then
        if not isinstance(scale, str):
            raise ValueError("scale")
        saved = SavedMap(a["y"].astype(float), a["P"].astype(float), kinds, a["anchors"].astype(float), feats, T, cam,
                         scale)
        if not (np.isfinite(saved.y).all() and np.isfinite(saved.P).all()):
            raise ValueError("non-finite")
        if np.abs(saved.y).max(initial=0.0) > MAX_MAP_VALUE or np.abs(saved.P).max(initial=0.0) > MAX_MAP_VARIANCE:
            raise ValueError(f"values beyond {MAX_MAP_VALUE:g} or variances beyond {MAX_MAP_VARIANCE:g}")
        if (np.diag(saved.P) < 0).any() or not np.allclose(saved.P, saved.P.T, rtol=1e-6, atol=1e-12):
            raise ValueError("a covariance that is not symmetric with non-negative variances")
    except (KeyError, ValueError, IndexError, TypeError, OverflowError, AttributeError) as e:
        raise MapFileError(f"{path}: the map's arrays are inconsistent ({e}); save the map again") from None
    return saved
