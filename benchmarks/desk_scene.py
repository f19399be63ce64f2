"""A desk scene that the twin did not make: textured planar patches (a desk top, papers, boxes,
a wall with posters, the printed target) ray-cast here in numpy, independently of MuJoCo and of
the twin's scenes, textures, motions and image model. Used by ``bench_slam_desk.py`` to test the
SLAM on images it was never tuned on.

The world: z up, the desk top at z = 0, the wearer on the -y side. Cameras follow
``formats.md``: x right, y down, z along the optic axis; poses are (R_world_cam, r_world_cam).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.camera import CameraIntrinsics, project, unproject
from runtime.sequence import SequenceWriter, Target

TEXEL_M = 0.0015            # texture resolution, m per texel


@dataclass(frozen=True)
class Patch:
    """A textured rectangle: corner ``o`` (3,), unit axes ``ex``, ``ey`` (3,), size (w, h) m,
    texture (rows along ey, columns along ex) float32 grey 0..255."""

    o: np.ndarray
    ex: np.ndarray
    ey: np.ndarray
    w: float
    h: float
    tex: np.ndarray


# -- textures ----------------------------------------------------------------------------------

def _blank(w_m: float, h_m: float, level: float, texel_m: float = TEXEL_M) -> np.ndarray:
    return np.full((max(2, round(h_m / texel_m)), max(2, round(w_m / texel_m))), level, np.float32)


def _finish(t: np.ndarray) -> np.ndarray:
    """Blur by about a texel (a print's and a lens's softness; keeps the sampling unaliased)."""
    return cv2.GaussianBlur(t.astype(np.float32), (0, 0), 0.8)


def wood(rng, w_m, h_m) -> np.ndarray:
    """Low-contrast grain along x: a real desk top gives few good corners."""
    t = _blank(w_m, h_m, 0)
    yy, xx = np.mgrid[0:t.shape[0], 0:t.shape[1]].astype(np.float32)
    warp = cv2.GaussianBlur(rng.normal(0, 1, t.shape).astype(np.float32), (0, 0), 40) * 400
    grain = np.sin((yy + warp) * 2 * np.pi / rng.uniform(12, 25))
    noise = cv2.GaussianBlur(rng.normal(0, 1, t.shape).astype(np.float32), (0, 0), 3)
    return _finish(np.clip(150 + 8 * grain + 5 * noise / noise.std(), 0, 255))


def printed_page(rng, w_m, h_m) -> np.ndarray:
    """A page of text: a heading, lines of words, perhaps a figure."""
    t = _blank(w_m, h_m, rng.uniform(215, 240)).astype(np.uint8)      # OpenCV draws text in 8 bits
    H, W = t.shape
    y = int(0.08 * H)
    cv2.putText(t, "".join(rng.choice(list("ABCDEFGHKMNPRSTUVWXYZ"), 8)), (int(0.1 * W), y),
                cv2.FONT_HERSHEY_DUPLEX, W / 260, 30, 2, cv2.LINE_AA)
    y += int(0.06 * H)
    while y < 0.92 * H:
        if rng.random() < 0.1:                                     # a figure
            h = int(rng.uniform(0.1, 0.2) * H)
            x0 = int(rng.uniform(0.1, 0.4) * W)
            cv2.rectangle(t, (x0, y), (x0 + int(0.4 * W), min(y + h, H - 1)), int(rng.uniform(40, 150)), -1)
            y += h + int(0.03 * H)
            continue
        x = int(0.1 * W)
        while x < 0.85 * W:
            word = "".join(rng.choice(list("abcdefghijklmnopqrstuvwxyz"), int(rng.integers(2, 9))))
            cv2.putText(t, word, (x, y), cv2.FONT_HERSHEY_SIMPLEX, W / 520, 40, 1, cv2.LINE_AA)
            x += int(len(word) * W / 40) + int(W / 40)
        y += int(0.035 * H)
    return _finish(t)


def poster(rng, w_m, h_m) -> np.ndarray:
    """Shapes of many greys on a flat ground, a title."""
    t = _blank(w_m, h_m, rng.uniform(60, 200)).astype(np.uint8)
    H, W = t.shape
    for _ in range(int(rng.integers(8, 20))):
        c = (int(rng.uniform(0, W)), int(rng.uniform(0, H)))
        level = int(rng.uniform(0, 255))
        if rng.random() < 0.5:
            cv2.circle(t, c, int(rng.uniform(0.03, 0.15) * W), level, -1, cv2.LINE_AA)
        else:
            pts = (np.array(c) + rng.normal(0, 0.12 * W, (int(rng.integers(3, 6)), 2))).astype(np.int32)
            cv2.fillPoly(t, [pts], level, cv2.LINE_AA)
    cv2.putText(t, "".join(rng.choice(list("ABCDEFGHKMNPRSTUVWXYZ"), 6)), (int(0.08 * W), int(0.9 * H)),
                cv2.FONT_HERSHEY_TRIPLEX, W / 200, int(rng.choice([20, 240])), 3, cv2.LINE_AA)
    return _finish(t)


def carton(rng, w_m, h_m) -> np.ndarray:
    """A box face: a mottled ground, a printed band and a label."""
    t = _blank(w_m, h_m, 0)
    H, W = t.shape
    noise = cv2.GaussianBlur(rng.normal(0, 1, t.shape).astype(np.float32), (0, 0), rng.uniform(2, 8))
    t = np.clip(rng.uniform(90, 190) + 25 * noise / noise.std(), 0, 255).astype(np.uint8)
    y0 = int(rng.uniform(0.2, 0.6) * H)
    cv2.rectangle(t, (0, y0), (W - 1, y0 + max(2, int(0.12 * H))), int(rng.uniform(10, 250)), -1)
    lx, ly = int(rng.uniform(0.1, 0.5) * W), int(rng.uniform(0.05, 0.5) * H)
    cv2.rectangle(t, (lx, ly), (lx + int(0.35 * W), ly + int(0.2 * H)), 235, -1)
    cv2.putText(t, "".join(rng.choice(list("0123456789ABCDEF"), 4)), (lx + 3, ly + int(0.15 * H)),
                cv2.FONT_HERSHEY_SIMPLEX, W / 400, 25, 1, cv2.LINE_AA)
    return _finish(t)


def target_card(rect_w, rect_h, margin, ink=30.0, paper=225.0, texel_m=0.00025) -> np.ndarray:
    """The known rectangle printed on a card ``margin`` m wider on each side, in texels fine
    enough (0.25 mm) that its sides fall on texel boundaries where the geometry puts them."""
    t = _blank(rect_w + 2 * margin, rect_h + 2 * margin, paper, texel_m)
    m, x1, y1 = (round(v / texel_m) for v in (margin, margin + rect_w, margin + rect_h))
    t[m:y1, m:x1] = ink
    return t


# -- the scene ---------------------------------------------------------------------------------

def _flat(o, angle, w, h, tex, z) -> Patch:
    """A patch lying on the desk at height z, its corner at o (x, y), turned by angle about z."""
    c, s = np.cos(angle), np.sin(angle)
    # The texture's first row at the far edge: seen from above it reads the right way round.
    return Patch(np.array([o[0] - h * s, o[1] + h * c, z]), np.array([c, s, 0.0]), np.array([s, -c, 0.0]), w, h, tex)


def _box(rng, centre_xy, w, d, h, angle) -> list[Patch]:
    """Top and four sides of a box standing on the desk."""
    c, s = np.cos(angle), np.sin(angle)
    ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    o = np.array([*centre_xy, 0.0]) - ex * w / 2 - ey * d / 2
    down = -ez
    return [
        Patch(o + ez * h, ex, ey, w, d, carton(rng, w, d)),                            # top
        Patch(o + ez * h, ex, down, w, h, carton(rng, w, h)),                          # front (-y)
        Patch(o + ey * d + ez * h, ex, down, w, h, carton(rng, w, h)),                 # back
        Patch(o + ez * h, ey, down, d, h, carton(rng, d, h)),                          # left
        Patch(o + ex * w + ez * h, ey, down, d, h, carton(rng, d, h)),                 # right
    ]


@dataclass(frozen=True)
class DeskScene:
    patches: tuple
    target_xyz: np.ndarray          # (4, 3) the printed rectangle's corners, m


def make_desk(scene_seed: int, rect=(0.21, 0.15), target_centre=(0.0, 0.12)) -> DeskScene:
    """A desk with the target card, papers, boxes and a postered wall; ``scene_seed`` fixes it."""
    rng = np.random.default_rng(10_000 + scene_seed)
    rw, rh = rect
    margin = 0.02
    patches = [Patch(np.array([-0.9, -0.4, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 1.8, 1.0,
                     wood(rng, 1.8, 1.0))]
    # The wall behind the desk and its posters (a little in front of it).
    wall_y = 0.6
    wall = _blank(3.0, 1.4, 0)
    wall += np.clip(rng.uniform(150, 200) + 6 * cv2.GaussianBlur(rng.normal(0, 1, wall.shape).astype(np.float32),
                                                                 (0, 0), 20) * 20, 0, 255)
    patches.append(Patch(np.array([-1.5, wall_y, 1.4]), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), 3.0, 1.4,
                         _finish(wall)))
    for x0 in rng.permutation(np.linspace(-1.1, 0.7, 4))[:3]:
        w, h = rng.uniform(0.3, 0.5), rng.uniform(0.35, 0.6)
        patches.append(Patch(np.array([x0 + rng.uniform(-0.05, 0.05), wall_y - 0.002, rng.uniform(0.75, 1.2)]),
                             np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), w, h, poster(rng, w, h)))
    # Pages beside the target, none over it; boxes further back or to the sides.
    tx, ty = target_centre
    for k, side in enumerate(rng.permutation([-1, 1, -1, 1])[:3]):
        x = tx + side * rng.uniform(0.2, 0.45)
        y = ty + rng.uniform(-0.3, 0.15)
        patches.append(_flat((x - 0.105, y - 0.15), rng.uniform(-0.4, 0.4), 0.21, 0.297,
                             printed_page(rng, 0.21, 0.297), 0.0004 + 0.0002 * k))
    spots = [(-0.55, 0.35), (0.5, 0.38), (-0.15, 0.45), (0.75, 0.05), (-0.75, 0.0)]
    for i in rng.permutation(len(spots))[:3]:
        w, d, h = rng.uniform(0.12, 0.3), rng.uniform(0.1, 0.25), rng.uniform(0.05, 0.3)
        patches += _box(rng, np.array(spots[i]) + rng.uniform(-0.05, 0.05, 2), w, d, h, rng.uniform(-0.5, 0.5))
    # The printed target, flat on the desk, a millimetre above the pages' level.
    z = 0.0012
    patches.append(Patch(np.array([tx - rw / 2 - margin, ty - rh / 2 - margin, z]), np.array([1.0, 0, 0]),
                         np.array([0, 1.0, 0]), rw + 2 * margin, rh + 2 * margin, target_card(rw, rh, margin)))
    target = np.array([[tx - rw / 2, ty - rh / 2, z], [tx + rw / 2, ty - rh / 2, z],
                       [tx + rw / 2, ty + rh / 2, z], [tx - rw / 2, ty + rh / 2, z]])
    return DeskScene(tuple(patches), target)


# -- rendering ---------------------------------------------------------------------------------

def _remap(tex, mx, my) -> np.ndarray:
    """Bilinear samples of ``tex`` at (mx, my) texel coordinates (any length)."""
    n = mx.size
    pad = -n % 1024
    X = np.r_[mx, np.zeros(pad)].astype(np.float32).reshape(-1, 1024)
    Y = np.r_[my, np.zeros(pad)].astype(np.float32).reshape(-1, 1024)
    return cv2.remap(tex, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()[:n]


class Renderer:
    """Grey images of a DeskScene through a camera's lens: ``samples`` rays a pixel, each at its
    own offset in the pixel and its own instant in the exposure (anti-aliasing and motion blur
    in one), the nearest patch along each ray."""

    def __init__(self, cam: CameraIntrinsics, scene: DeskScene, samples: int = 4):
        self.cam, self.scene = cam, scene
        uu, vv = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
        offs = [((i + 0.5) / samples - 0.5, (((3 * i) % samples) + 0.5) / samples - 0.5) for i in range(samples)]
        self.rays = [unproject(cam, np.column_stack([uu.ravel() + du, vv.ravel() + dv])) for du, dv in offs]
        self.background = 90.0

    def _nearest(self, d, r):
        """(t, patch, a, b) of the nearest patch along each world ray ``d`` (n, 3) from ``r``: the
        ray's length to it (inf: none), its index (-1: none) and the hit's patch coordinates, m."""
        n = d.shape[0]
        best = np.full(n, np.inf)
        who = np.full(n, -1)
        A, B = np.zeros(n), np.zeros(n)
        for k, p in enumerate(self.scene.patches):
            normal = np.cross(p.ex, p.ey)
            den = d @ normal
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((p.o - r) @ normal) / den
            ok = (t > 1e-3) & (t < best)
            if not ok.any():
                continue
            idx = np.nonzero(ok)[0]
            X = r + t[idx, None] * d[idx] - p.o
            a, b = X @ p.ex, X @ p.ey
            inside = (a >= 0) & (a <= p.w) & (b >= 0) & (b <= p.h)
            idx, a, b = idx[inside], a[inside], b[inside]
            best[idx], who[idx], A[idx], B[idx] = t[idx], k, a, b
        return best, who, A, B

    def _shade(self, rays_cam, R_world_cam, r) -> np.ndarray:
        d = rays_cam @ np.asarray(R_world_cam).T
        n = d.shape[0]
        _, who, A, B = self._nearest(d, r)
        val = np.full(n, self.background, np.float32)
        for k in np.unique(who[who >= 0]):
            p = self.scene.patches[k]
            sel = who == k
            H, W = p.tex.shape
            # Texel i covers [i, i + 1) of the patch's W texels; remap puts texel i's centre at i.
            val[sel] = _remap(p.tex, A[sel] * (W / p.w) - 0.5, B[sel] * (H / p.h) - 0.5)
        return val

    def render(self, poses) -> np.ndarray:
        """(height, width) float32 image: the mean over the rays, ray set i seen from poses[i]
        (one pose per ray set: the camera's pose at that instant of the exposure)."""
        acc = np.zeros(self.cam.width * self.cam.height, np.float32)
        for rays, (R, r) in zip(self.rays, poses):
            acc += self._shade(rays, R, r)
        return (acc / len(self.rays)).reshape(self.cam.height, self.cam.width)


    def depth(self, R_world_cam, r, rng: np.random.Generator | None = None) -> np.ndarray:
        """(height, width) depth along the optic axis, m, at each pixel's centre (0: no surface),
        as a structured-light sensor registered to this camera gives it: with ``rng``, its noise
        (sigma_z = 1.45e-3 z^2, the Kinect's) and 1/5000 m steps."""
        cam = self.cam
        uu, vv = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
        rays = unproject(cam, np.column_stack([uu.ravel(), vv.ravel()]))
        t, *_ = self._nearest(rays @ np.asarray(R_world_cam).T, r)
        z = np.where(np.isfinite(t), t * rays[:, 2], 0.0)
        if rng is not None:
            z = np.where(z > 0, np.round((z + rng.normal(0.0, 1.45e-3 * z**2)) * 5000) / 5000, 0.0)
        return z.reshape(cam.height, cam.width)


# -- motions -----------------------------------------------------------------------------------

def look_at(eye, centre, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """R_world_cam of a camera at ``eye`` looking at ``centre`` (optical z forward, y down)."""
    z = np.asarray(centre, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


class HandHeld:
    """A hand-held camera over the desk: a slow wander of the eye and of the point looked at, a
    roll, a hand's tremor; with ``away`` the gaze goes to the side (the target out of view) for
    a stretch and comes back."""

    def __init__(self, seed: int, target_centre, distance: float = 0.6, away: tuple | None = None):
        rng = np.random.default_rng(20_000 + seed)
        self.centre = np.asarray(target_centre, float)
        elev = rng.uniform(0.7, 1.0)                               # rad above the desk
        azim = rng.uniform(-0.4, 0.4)
        self.eye0 = self.centre + distance * np.array([np.sin(azim) * np.cos(elev), -np.cos(azim) * np.cos(elev),
                                                      np.sin(elev)])

        def waves(n, amp, f_lo, f_hi):
            return (rng.uniform(0.5, 1.0, (n, 3)) * amp, rng.uniform(f_lo, f_hi, (n, 3)), rng.uniform(0, 2 * np.pi, (n, 3)))

        self.eye_w = waves(3, 0.05, 0.08, 0.5)
        self.look_w = waves(3, 0.03, 0.1, 0.6)
        self.shake_w = waves(4, 0.0025, 2.0, 7.0)
        self.roll_w = waves(2, 0.06, 0.05, 0.3)
        self.away = away
        self.away_to = self.centre + np.array([rng.choice([-1, 1]) * rng.uniform(0.75, 0.95), rng.uniform(0.1, 0.3), 0.1])

    @staticmethod
    def _sum(w, t):
        amp, f, ph = w
        return (amp * np.sin(2 * np.pi * f * t + ph)).sum(axis=0)

    def pose(self, t: float):
        """(R_world_cam, r_world_cam) at time t, s."""
        eye = self.eye0 + self._sum(self.eye_w, t)
        look = self.centre + self._sum(self.look_w, t)
        if self.away is not None:
            t0, t1, ramp = self.away
            s = np.clip(min(t - t0, t1 - t) / ramp, 0.0, 1.0)
            s = 0.5 - 0.5 * np.cos(np.pi * s)                      # smooth out and back
            look = (1 - s) * look + s * self.away_to
        R = look_at(eye, look)
        shake = self._sum(self.shake_w, t)
        shake[2] += self._sum(self.roll_w, t)[0]
        return R @ Rotation.from_rotvec(shake).as_matrix(), eye


# -- a sequence on disk --------------------------------------------------------------------------

def write_sequence(out: Path, cam: CameraIntrinsics, scene: DeskScene, motion: HandHeld, seconds: float,
                   seed: int, fps: float = 30.0, exposure_s: float = 0.008, noise_grey: float = 2.0,
                   click_px: tuple = (2.0, 3.0)) -> Path:
    """A sequence in ``formats.md``'s layout (runtime.sequence.SequenceWriter): grey PNGs
    (sensor noise, motion blur over the exposure, an auto-exposure's slow gain and one step),
    groundtruth.txt, camera.toml and a target.toml whose pixels are clicks ``click_px`` px off
    the truth."""
    rng = np.random.default_rng(30_000 + seed)
    ren = Renderer(cam, scene)
    n = int(round(seconds * fps))
    step_t, step = rng.uniform(0.3, 0.7) * seconds, rng.choice([-1, 1]) * rng.uniform(0.12, 0.2)
    gain_w = (rng.uniform(0.03, 0.06), rng.uniform(0.1, 0.3), rng.uniform(0, 2 * np.pi))
    with SequenceWriter(out, cam) as w:
        for i in range(n):
            t = i / fps
            inst = t - exposure_s / 2 + exposure_s * (np.arange(len(ren.rays)) + 0.5) / len(ren.rays)
            img = ren.render([motion.pose(s) for s in inst])
            gain = 1.0 + gain_w[0] * np.sin(2 * np.pi * gain_w[1] * t + gain_w[2])
            gain *= 1.0 + step * np.clip((t - step_t) / 0.3, 0.0, 1.0)
            img = img * gain + rng.normal(0.0, noise_grey, img.shape)
            w.add_frame(t, np.clip(np.round(img), 0, 255).astype(np.uint8))
            R, r = motion.pose(t)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, r
            w.add_groundtruth(t, T)
        R, r = motion.pose(0.0)
        uv = project(cam, (scene.target_xyz - r) @ R)
        ang = rng.uniform(0, 2 * np.pi, 4)
        clicks = uv + rng.uniform(*click_px, (4, 1)) * np.column_stack([np.cos(ang), np.sin(ang)])
        w.set_target(Target(scene.target_xyz, clicks))
    return Path(out)
