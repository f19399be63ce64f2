"""Tests for runtime.vision2d: the hyperplane planar-patch tracker, the mean-shift colour tracker
and the sequence runner, against sequences synthesised here with known homographies.

The synthesiser (also used by benchmarks/bench_trackers.py) warps a textured planar object by a
smooth random homography (translation, rotation, scale, perspective) over a background that
itself shifts and rotates (the moving camera), with image noise, lighting gain changes and an
optional occluding bar of another texture covering a set share of the object.
"""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

from kinematics.camera import CameraIntrinsics
from runtime.sequence import SequenceWriter
from runtime.vision2d.hyperplane import HyperplaneConfig, HyperplaneTracker
from runtime.vision2d.meanshift import MeanShiftTracker
from runtime.vision2d.track import track_sequence


# ---------------------------------------------------------------------------------------------
# Synthetic sequences with known ground truth
# ---------------------------------------------------------------------------------------------

def texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """(h, w) uint8 photo-like texture: noise at several scales plus random discs and bars."""
    img = np.zeros((h, w), np.float32)
    for scale, amp in ((64, 60.0), (16, 40.0), (4, 25.0)):
        small = rng.normal(0.0, 1.0, (max(2, h // scale), max(2, w // scale))).astype(np.float32)
        img += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(int(h * w / 1500) + 4):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        v = float(rng.uniform(-90, 90))
        if rng.random() < 0.5:
            cv2.circle(img, c, int(rng.integers(3, max(4, min(h, w) // 8))), v, -1, cv2.LINE_AA)
        else:
            d = (int(rng.integers(3, max(4, w // 6))), int(rng.integers(3, max(4, h // 6))))
            cv2.rectangle(img, c, (c[0] + d[0], c[1] + d[1]), v, -1, cv2.LINE_AA)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    return np.clip(128.0 + img, 0, 255).astype(np.uint8)


def _homography(centre, theta, scale, persp, half) -> np.ndarray:
    """Template -> image: translate to the template centre, perspective, scale, rotate, place."""
    T0 = np.array([[1, 0, -half[0]], [0, 1, -half[1]], [0, 0, 1.0]])
    P = np.array([[1, 0, 0], [0, 1, 0], [persp[0], persp[1], 1.0]])
    c, s = np.cos(theta), np.sin(theta)
    RS = np.array([[scale * c, -scale * s, 0], [scale * s, scale * c, 0], [0, 0, 1.0]])
    T1 = np.array([[1, 0, centre[0]], [0, 1, centre[1]], [0, 0, 1.0]])
    return T1 @ RS @ P @ T0


def planar_sequence(n: int = 30, image_size=(320, 240), obj_size=(100, 80), seed: int = 0,
                    occlusion: float = 0.0, occlusion_frames=None, noise: float = 2.0, amplitude=1.0,
                    drift=(0.0, 0.0), full_occlusion_frames=None, perspective: float = 1.0):
    """A textured plane moving in front of a moving background.

    Returns (frames (n, H, W, 3) uint8 RGB, corners (n, 4, 2) px true corners of the object,
    quad0 (4, 2) the object's corners in frame 0, an axis-aligned rectangle). ``occlusion`` is the share of the object covered by a bar
    of another texture sliding across it during ``occlusion_frames`` (a range; default all);
    ``drift`` (px/frame) adds a steady translation (to make the object leave the image);
    ``full_occlusion_frames`` covers the whole object with the occluder's texture.
    """
    rng = np.random.default_rng(seed)
    W, Hh = image_size
    w, h = obj_size
    tex = texture(rng, 2 * h, 2 * w).astype(np.float32)
    bg = texture(rng, 2 * Hh, 2 * W).astype(np.float32)
    occ = texture(rng, Hh, W).astype(np.float32)
    S_tex = np.array([[0.5, 0, 0.25], [0, 0.5, 0.25], [0, 0, 1.0]])   # texture px -> template coords
    ph = rng.uniform(0, 2 * np.pi, 8)
    centre0 = np.array([W / 2, Hh / 2])
    frames, corners = [], []
    tmpl = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    occ_range = range(n) if occlusion_frames is None else occlusion_frames
    for k in range(n):
        a = amplitude
        centre = centre0 + a * np.array([0.12 * W * np.sin(2 * np.pi * k / 45 + ph[0]) - 0.12 * W * np.sin(ph[0]),
                                         0.12 * Hh * np.sin(2 * np.pi * k / 38 + ph[1]) - 0.12 * Hh * np.sin(ph[1])])
        centre = centre + np.array(drift) * k
        theta = a * 0.25 * (np.sin(2 * np.pi * k / 50 + ph[2]) - np.sin(ph[2]))
        scale = 1.0 + a * 0.12 * (np.sin(2 * np.pi * k / 40 + ph[3]) - np.sin(ph[3]))
        persp = perspective * a * 0.0012 * np.array([np.sin(2 * np.pi * k / 35 + ph[4]) - np.sin(ph[4]),
                                       np.sin(2 * np.pi * k / 42 + ph[5]) - np.sin(ph[5])]) * 100 / w
        H = _homography(centre, theta, scale, persp, (w / 2, h / 2))
        # the moving camera: the background shifts and turns
        phi = 0.08 * np.sin(2 * np.pi * k / 60 + ph[6])
        A = cv2.getRotationMatrix2D((W, Hh), np.degrees(phi), 1.0)
        A[:, 2] += [-W / 2 + 25 * np.sin(2 * np.pi * k / 55 + ph[7]), -Hh / 2 + 15 * np.cos(2 * np.pi * k / 47)]
        img = cv2.warpAffine(bg, A, (W, Hh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        HS = H @ S_tex
        obj = cv2.warpPerspective(tex, HS, (W, Hh), flags=cv2.INTER_LINEAR)
        m = cv2.warpPerspective(np.ones_like(tex), HS, (W, Hh), flags=cv2.INTER_LINEAR)
        img = m * obj + (1 - m) * img
        cover = 1.0 if (full_occlusion_frames is not None and k in full_occlusion_frames) else \
            (occlusion if k in occ_range else 0.0)
        if cover > 0:
            # a bar over `cover` of the template's width, sliding across it (template coords)
            span = (1.0 - cover) * w
            x0 = 0.5 * span * (1 + np.sin(2 * np.pi * k / 20))
            band = np.zeros((2 * h, 2 * w), np.float32)
            band[:, int(round(2 * x0)):int(round(2 * (x0 + cover * w)))] = 1.0
            mb = cv2.warpPerspective(band, HS, (W, Hh), flags=cv2.INTER_LINEAR)
            img = mb * occ + (1 - mb) * img
        gain = 1.0 + 0.15 * np.sin(2 * np.pi * k / 25)
        img = gain * img + 10 * np.sin(2 * np.pi * k / 33) + rng.normal(0, noise, img.shape)
        grey = np.clip(img, 0, 255).astype(np.uint8)
        frames.append(np.repeat(grey[:, :, None], 3, axis=2))
        corners.append(_apply(H, tmpl))
    return np.array(frames), np.array(corners), corners[0]


def _apply(H, pts):
    p = pts @ H[:, :2].T + H[:, 2]
    return p[:, :2] / p[:, 2:3]


def blob_sequence(n: int = 40, image_size=(320, 240), seed: int = 0, noise: float = 3.0):
    """A saturated orange ellipse (shaded) whose axes and angle change, moving over a textured
    grey background that itself moves. Returns (frames (n, H, W, 3) RGB, centres (n, 2) px,
    sizes (n,) px = mean of the ellipse's full axes, window (x, y, w, h) of frame 0)."""
    rng = np.random.default_rng(seed)
    W, Hh = image_size
    bg = texture(rng, 2 * Hh, 2 * W).astype(np.float32)
    frames, centres, sizes = [], [], []
    for k in range(n):
        c = np.array([W / 2 + 0.25 * W * np.sin(2 * np.pi * k / 50), Hh / 2 + 0.2 * Hh * np.sin(2 * np.pi * k / 37)])
        ax = np.array([28 + 8 * np.sin(2 * np.pi * k / 30), 18 + 6 * np.cos(2 * np.pi * k / 23)])
        ang = 40 * np.sin(2 * np.pi * k / 45)
        A = np.float32([[1, 0, -W / 2 + 20 * np.sin(2 * np.pi * k / 40)], [0, 1, -Hh / 2 + 10 * np.cos(2 * np.pi * k / 35)]])
        g = cv2.warpAffine(bg, A, (W, Hh), borderMode=cv2.BORDER_REFLECT)
        img = np.repeat(g[:, :, None], 3, axis=2)
        mask = np.zeros((Hh, W), np.float32)
        cv2.ellipse(mask, (int(round(c[0] * 16)), int(round(c[1] * 16))), (int(ax[0] * 16), int(ax[1] * 16)),
                    ang, 0, 360, 1.0, -1, cv2.LINE_AA, shift=4)
        shade = 0.6 + 0.4 * (g / 255.0)   # the blob's brightness varies with the texture (3D shading)
        colour = np.stack([240 * shade, 120 * shade, 30 * shade], axis=2)
        img = mask[:, :, None] * colour + (1 - mask[:, :, None]) * img
        img = img + rng.normal(0, noise, img.shape)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
        centres.append(c)
        sizes.append(ax.mean() * 2)
    c0 = centres[0]
    window = (int(c0[0] - 25), int(c0[1] - 18), 50, 36)
    return np.array(frames), np.array(centres), np.array(sizes), window


def corner_rms(track_corners: np.ndarray, true_corners: np.ndarray) -> float:
    """RMS over frames and corners of the corner position error, px."""
    return float(np.sqrt(np.mean(np.sum((track_corners - true_corners) ** 2, axis=-1))))


def run_planar(frames, quad0, config=None):
    tr = HyperplaneTracker(frames[0], quad0, config)
    polys, lost, res = [], [], []
    for f in frames[1:]:
        r = tr.track(f)
        polys.append(r.polygon)
        lost.append(r.lost)
        res.append(r.residual)
    return np.array(polys), np.array(lost), np.array(res)


# ---------------------------------------------------------------------------------------------
# Planar tracker
# ---------------------------------------------------------------------------------------------

def test_planar_tracker_recovers_homographies_without_occlusion():
    frames, corners, quad0 = planar_sequence(n=30, seed=1)
    polys, lost, res = run_planar(frames, quad0)
    assert not lost.any(), res
    err = np.sqrt(np.sum((polys - corners[1:]) ** 2, axis=-1))
    assert err.max() < 1.0, f"max corner error {err.max():.2f} px"
    assert np.all(res < 0.5)


def test_planar_tracker_with_quarter_occlusion():
    frames, corners, quad0 = planar_sequence(n=30, seed=2, occlusion=0.25, occlusion_frames=range(4, 30))
    polys, lost, res = run_planar(frames, quad0)
    assert not lost.any(), res
    assert corner_rms(polys, corners[1:]) < 2.0


def test_occlusion_handling_is_what_keeps_the_error_low():
    """Without the robust blocks the same sequence tracks worse: the test above is not vacuous."""
    frames, corners, quad0 = planar_sequence(n=30, seed=2, occlusion=0.25, occlusion_frames=range(4, 30))
    polys_r, _, _ = run_planar(frames, quad0)
    polys_p, lost_p, _ = run_planar(frames, quad0, HyperplaneConfig(blocks=(1, 1), lost_residual=2.0))
    assert corner_rms(polys_r, corners[1:]) < corner_rms(polys_p, corners[1:])


def test_affine_motion_model_tracks_an_affine_motion():
    frames, corners, quad0 = planar_sequence(n=20, seed=3, perspective=0.0)
    polys, lost, _ = run_planar(frames, quad0, HyperplaneConfig(motion="affine"))
    assert not lost.any()
    err = np.sqrt(np.sum((polys - corners[1:]) ** 2, axis=-1))
    assert err.max() < 1.0, err.max()


def test_loss_reported_when_object_leaves_the_image():
    frames, corners, quad0 = planar_sequence(n=30, seed=4, amplitude=0.2, drift=(6.0, 0.0))
    polys, lost, _ = run_planar(frames, quad0)
    inside = np.array([(c[:, 0].min() > 0) and (c[:, 0].max() < 319) for c in corners[1:]])
    assert not lost[inside][:5].any()
    far_out = np.array([c[:, 0].mean() > 330 for c in corners[1:]])
    assert far_out.any() and lost[far_out].all()


def test_loss_reported_when_fully_occluded_then_recovered():
    frames, corners, quad0 = planar_sequence(n=26, seed=5, amplitude=0.3, full_occlusion_frames=range(12, 16))
    polys, lost, res = run_planar(frames, quad0)
    k = np.arange(1, 26)
    occluded = (k >= 12) & (k < 16)
    assert lost[occluded].all(), res
    assert not lost[~occluded].any(), res
    # after the occluder has gone, the track is good again
    err = np.sqrt(np.sum((polys[k >= 18] - corners[18:]) ** 2, axis=-1))
    assert err.max() < 1.5


def test_relearn_with_a_denser_smaller_pattern_keeps_tracking():
    frames, corners, quad0 = planar_sequence(n=24, seed=6)
    tr = HyperplaneTracker(frames[0], quad0, HyperplaneConfig(grid=(12, 12), blocks=(4, 4)))
    for f in frames[1:10]:
        assert not tr.track(f).lost
    tr.relearn(frames[9], grid=(24, 24), extent=0.7)
    assert len(tr.pts_tmpl) == 24 * 24
    polys = np.array([tr.track(f).polygon for f in frames[10:]])
    assert corner_rms(polys, corners[10:]) < 1.5


@pytest.mark.parametrize("region", [(-50, 10, 40, 40), (300, 200, 60, 60), (10, 10, 0, 30), (10, 10, 30, -5),
                                    (np.nan, 0, 20, 20)])
def test_bad_start_window_raises(region):
    frames, _, _ = planar_sequence(n=1)
    with pytest.raises(ValueError, match="start window|start region"):
        HyperplaneTracker(frames[0], region)
    with pytest.raises(ValueError, match="start window|start region"):
        MeanShiftTracker(frames[0], region)


def test_a_bad_start_window_is_printed_as_the_user_gave_it_with_the_bounds():
    from runtime.vision2d.hyperplane import check_region

    with pytest.raises(ValueError) as e:
        check_region(np.array([0.0, 0.0, 1.0, 1.0]), 640, 480)     # as --init arrives: numpy floats
    assert "start window 0,0,1,1 must have" in str(e.value) and "np.float64" not in str(e.value)
    with pytest.raises(ValueError) as e:
        check_region((0, 0, 640, 480), 640, 480)
    assert "x -0.5..639.5, y -0.5..479.5" in str(e.value) and "e.g. 0,0,639,479" in str(e.value)
    np.testing.assert_allclose(check_region((0, 0, 639, 479), 640, 480)[2], [639, 479])   # the advice is taken


def test_blank_region_raises():
    with pytest.raises(ValueError, match="no texture"):
        HyperplaneTracker(np.full((120, 160), 90, np.uint8), (20, 20, 60, 50))


# ---------------------------------------------------------------------------------------------
# Mean shift
# ---------------------------------------------------------------------------------------------

def test_mean_shift_keeps_the_centre_within_a_tenth_of_the_size():
    frames, centres, sizes, window = blob_sequence(n=40, seed=7)
    tr = MeanShiftTracker(frames[0], window)
    errs = []
    for f, c, s in zip(frames[1:], centres[1:], sizes[1:]):
        r = tr.track(f)
        assert not r.lost
        errs.append(np.linalg.norm(r.centre - c) / s)
    assert max(errs) < 0.10, max(errs)


def test_mean_shift_reports_loss_when_the_blob_disappears():
    frames, centres, sizes, window = blob_sequence(n=12, seed=8)
    tr = MeanShiftTracker(frames[0], window)
    for f in frames[1:6]:
        assert not tr.track(f).lost
    grey = np.repeat(cv2.cvtColor(frames[6], cv2.COLOR_RGB2GRAY)[:, :, None], 3, axis=2)
    r = tr.track(grey)
    assert r.lost and r.reason
    r = tr.track(frames[7])   # reacquired: it came back near the last window
    assert not r.lost
    assert np.linalg.norm(r.centre - centres[7]) < 0.2 * sizes[7]


def test_mean_shift_needs_colour():
    with pytest.raises(ValueError, match="colour"):
        MeanShiftTracker(np.full((120, 160), 90, np.uint8), (20, 20, 40, 40))


# ---------------------------------------------------------------------------------------------
# The sequence runner
# ---------------------------------------------------------------------------------------------

def _write_sequence(root, frames, bad=()):
    cam = CameraIntrinsics(width=frames.shape[2], height=frames.shape[1], fx=300.0, fy=300.0,
                           cx=frames.shape[2] / 2 - 0.5, cy=frames.shape[1] / 2 - 0.5)
    with SequenceWriter(root, cam) as w:
        for k, f in enumerate(frames):
            path = w.add_frame(0.1 * k + 1.0, f)
            if k in bad:
                path.write_bytes(b"not a png")


@pytest.mark.parametrize("method", ["hyperplane", "meanshift"])
def test_runner_writes_files_that_parse(tmp_path, method):
    if method == "hyperplane":
        frames, corners, quad0 = planar_sequence(n=10, seed=9)
        init = tuple(int(round(v)) for v in (quad0[0, 0], quad0[0, 1], quad0[2, 0] - quad0[0, 0],
                                              quad0[2, 1] - quad0[0, 1]))
        truth = corners.mean(axis=1)
    else:
        frames, truth, _, init = blob_sequence(n=10, seed=9)
    _write_sequence(tmp_path / "seq", frames, bad=(4,))
    out = tmp_path / "out"
    totals = track_sequence(tmp_path / "seq", out, init=init, method=method, progress=False)
    assert totals.frames == 10 and totals.skipped == 1
    rows = list(csv.DictReader(open(out / "polygons.csv")))
    assert len(rows) == 10
    assert list(rows[0]) == ["t", "x0", "y0", "x1", "y1", "x2", "y2", "x3", "y3", "lost", "residual"]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames"] == 10 and stats["skipped_unreadable"] == 1 and stats["lost_frames"] >= 1
    assert rows[4]["lost"] == "1"
    for k, row in enumerate(rows):
        if k == 4:
            continue
        poly = np.array([float(row[c]) for c in ("x0", "y0", "x1", "y1", "x2", "y2", "x3", "y3")]).reshape(4, 2)
        assert row["lost"] == "0"
        assert np.linalg.norm(poly.mean(axis=0) - truth[k]) < 5.0
    pngs = sorted((out / "annotated").glob("*.png"))
    assert len(pngs) == 9 and pngs[0].name == "000000.png"
    assert cv2.imread(str(pngs[0])).shape == frames[0].shape


def test_runner_rejects_bad_input(tmp_path):
    frames, _, _ = planar_sequence(n=3)
    _write_sequence(tmp_path / "seq", frames)
    with pytest.raises(ValueError, match="start window"):
        track_sequence(tmp_path / "seq", tmp_path / "o", init=(0, 0, 0, 10), progress=False)
    with pytest.raises(ValueError, match="method"):
        track_sequence(tmp_path / "seq", tmp_path / "o", init=(10, 10, 50, 50), method="kalman", progress=False)


@pytest.mark.slow
def test_planar_tracker_on_the_twin_card_a_quarter_occluded(tmp_path):
    """The twin's hand-held card, the camera following it: corners against the card's true
    corners projected by the true camera poses, with the occluder over a quarter from 1.5 s."""
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")
    from kinematics.camera import project
    from runtime.sequence import open_sequence
    from runtime.twin.recorder import record
    from runtime.twin.scenarios import get_scenario
    from wvr.cli import make_twin

    sc = get_scenario("workbench-card")
    twin = make_twin()
    try:
        seq = open_sequence(record(twin, sc, tmp_path / "card", seconds=2.5, seed=0, progress=False))
    finally:
        twin.close()
    T = seq.groundtruth.interpolate(seq.timestamps).T_world_cam()
    frames = [f.image for f in seq.frames()]
    truth = [project(seq.camera, (sc.card_corners(t) - T[i, :3, 3]) @ T[i, :3, :3]) for i, t in enumerate(seq.timestamps)]
    tr = HyperplaneTracker(frames[0], truth[0])
    err = []
    for img, true in zip(frames[1:], truth[1:]):
        r = tr.track(img)
        assert not r.lost
        err.append(np.sqrt(np.mean(np.sum((r.polygon - true) ** 2, axis=1))))
    t = np.asarray(seq.timestamps[1:])
    occluded = t >= 1.5                       # the occluder is fully over the card from 1.5 s
    assert np.sqrt(np.mean(np.square(err)[occluded])) < 2.0
    assert np.sqrt(np.mean(np.square(err)[~occluded])) < 1.0


def test_every_tracker_meets_the_protocol_and_is_built_by_name():
    from runtime.vision2d.track import METHODS, TRACKERS, make_tracker
    from runtime.vision2d.tracker import Tracker

    assert set(METHODS) == set(TRACKERS) == {"hyperplane", "meanshift"}
    frames, _, _, window = blob_sequence(n=3, seed=2)
    for method in METHODS:
        t = make_tracker(method, frames[0], window)
        assert isinstance(t, Tracker) and isinstance(t, TRACKERS[method][0])
        r0 = t.start_result()
        assert not r0.lost and r0.polygon.shape == (4, 2)
        # The start result is the start window: its corners span it.
        np.testing.assert_allclose(r0.polygon.min(axis=0), window[:2], atol=1.5)
        np.testing.assert_allclose(r0.polygon.max(axis=0), np.add(window[:2], window[2:]), atol=1.5)
        r1 = t.track(frames[1])        # a deforming blob: the planar tracker may lose it, saying so
        assert r1.polygon.shape == (4, 2) and (r1.lost == (r1.reason is not None))
