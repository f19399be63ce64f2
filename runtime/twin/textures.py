"""Procedural textures for the twin's scenes, drawn with OpenCV from a seeded generator, as PNG
bytes (no fetched data).

Two families:

- the workbench's own (:func:`clutter`, :func:`bench_top`): saturated, corner-rich patterns,
  kept exactly as they were so that workbench recordings do not change;
- realistic surfaces for the other scenes: large plain areas with faint mottling
  (:func:`paint`, :func:`stone`, :func:`wood`), repeated patterns (:func:`tiles`,
  :func:`keyboard`), printed matter with text (:func:`label`, :func:`poster`,
  :func:`book_spine`, :func:`carton`), a dark screen and a bright window view. Colours stay in
  the albedo range of real materials: white paint and paper about 0.75-0.85, wood 0.3-0.5,
  dark plastics 0.03-0.1, in 8-bit sRGB about 60-235 rather than 0-255.

Images are built as (H, W, 3) RGB arrays; PNGs are written in OpenCV's BGR order.
"""

from __future__ import annotations

import cv2
import numpy as np

_LETTERS = "ABEFHKLMNTXYZ47"

#: Words for titles and labels (printed matter needs text, and text needs words).
WORDS = ("Robot", "Vision", "Geometry", "Optics", "Control", "Signals", "Mechanics", "Algorithms", "Atlas",
         "History", "Design", "Garden", "Cooking", "Poems", "Physics", "Calculus", "Maps", "Systems", "Motion",
         "Light", "Music", "Rivers", "Islands", "Notes", "Letters", "Statistics", "Estimation", "Filters",
         "Modern", "Classic", "Essays", "Tables", "Bridges", "Birds", "Stone", "Winter", "Harbour")
PANTRY = ("SUGAR", "FLOUR", "RICE", "PASTA", "TEA", "COFFEE", "OATS", "SALT", "BEANS", "HONEY")


def png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 RGB image."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("OpenCV could not encode a texture as PNG")
    return buf.tobytes()


# ------------------------------------------------------------------ the workbench (unchanged)
def clutter(rng: np.random.Generator, size: int = 256, style: str = "clutter") -> bytes:
    """A PNG of a corner-rich pattern: coloured rectangles, checks, lines and letters."""
    img = np.full((size, size, 3), rng.integers(150, 255, 3), np.uint8)
    for _ in range(int(size * size / 900)):
        x, y = rng.integers(0, size, 2)
        w, h = rng.integers(size // 32, size // 6, 2)
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        kind = rng.integers(0, 4 if style == "clutter" else 2)
        if kind == 0:
            cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), colour, -1)
        elif kind == 1:
            cv2.line(img, (int(x), int(y)), (int(x + w), int(y + h)), colour, int(rng.integers(1, 4)))
        elif kind == 2:
            k = int(rng.integers(2, 5))
            cell = max(int(w) // k, 2)
            for i in range(k):
                for j in range(k):
                    if (i + j) % 2 == 0:
                        cv2.rectangle(img, (int(x) + i * cell, int(y) + j * cell),
                                      (int(x) + (i + 1) * cell, int(y) + (j + 1) * cell), colour, -1)
        else:
            text = "".join(rng.choice(list(_LETTERS), int(rng.integers(1, 4))))
            cv2.putText(img, text, (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, float(rng.uniform(0.4, 1.2)),
                        colour, int(rng.integers(1, 3)))
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()


def bench_top(rng: np.random.Generator, size_m: tuple[float, float], px_per_m: float = 320.0) -> bytes:
    """A PNG covering the whole bench top once (no tiling: a repeated pattern would invite
    mismatches a tile apart): wood with scattered sheets, notes and marks."""
    W, H = int(px_per_m * size_m[0]), int(px_per_m * size_m[1])
    img = np.zeros((H, W, 3), np.uint8)
    img[:] = (84, 122, 158)                       # wood, BGR
    for y in range(0, H, 6):                      # grain
        shade = int(rng.integers(-10, 10))
        img[y:y + 3] = np.clip(img[y:y + 3].astype(int) + shade, 0, 255)
    for _ in range(int(45 * size_m[0] * size_m[1])):
        x, y = int(rng.integers(0, W - 40)), int(rng.integers(0, H - 40))
        w, h = (int(v) for v in rng.integers(20, 70, 2))
        colour = tuple(int(c) for c in rng.integers(150, 255, 3)) if rng.uniform() < 0.7 else \
            tuple(int(c) for c in rng.integers(0, 90, 3))
        cv2.rectangle(img, (x, y), (x + w, y + h), colour, -1)
        if rng.uniform() < 0.5:                   # print on the sheet
            cv2.putText(img, "".join(rng.choice(list(_LETTERS), 2)), (x + 3, y + h - 5),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.5, (20, 20, 20), 1)
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()


# ------------------------------------------------------------------ realistic surfaces
def muted_colour(rng: np.random.Generator, lo: float, hi: float, saturation: float = 0.25) -> tuple[int, int, int]:
    """An RGB colour of brightness lo..hi (8-bit) whose channels differ from their mean by at
    most ``saturation`` of it: the muted colours of paint, cloth and card, not a screen's."""
    level = rng.uniform(lo, hi)
    hue = rng.uniform(-1.0, 1.0, 3)
    hue -= hue.mean()
    hue /= max(float(np.abs(hue).max()), 1e-6)
    rgb = level * (1.0 + saturation * rng.uniform(0.3, 1.0) * hue)
    return tuple(int(c) for c in np.clip(np.round(rgb), 0, 255))


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: float) -> np.ndarray:
    """(H, W) float noise of unit standard deviation varying over about ``cell_px`` pixels."""
    h, w = shape
    gh, gw = max(2, int(np.ceil(h / cell_px)) + 1), max(2, int(np.ceil(w / cell_px)) + 1)
    n = cv2.resize(rng.standard_normal((gh, gw)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    return n / max(float(n.std()), 1e-6)


def _finish(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _surface(rng: np.random.Generator, shape: tuple[int, int], rgb, mottle: float, grain: float,
             cell_px: float = 40.0) -> np.ndarray:
    """(H, W, 3) float: a base colour with low-frequency mottling and fine grain (fractions of it)."""
    base = np.asarray(rgb, np.float32)
    shade = 1.0 + mottle * _smooth_noise(rng, shape, cell_px) + grain * rng.standard_normal(shape).astype(np.float32)
    return shade[..., None] * base


def paint(rng: np.random.Generator, rgb=(214, 210, 200), size=(256, 256), mottle: float = 0.025,
          grain: float = 0.008) -> bytes:
    """A painted wall or door: nearly uniform, with faint roller mottling."""
    return png(_finish(_surface(rng, (size[1], size[0]), rgb, mottle, grain)))


def stone(rng: np.random.Generator, rgb=(188, 184, 176), size=(512, 256), speckle: float = 0.25) -> bytes:
    """A stone or laminate worktop: low-contrast speckles on a mottled base."""
    h, w = size[1], size[0]
    img = _surface(rng, (h, w), rgb, 0.03, 0.01, cell_px=60)
    n = int(0.004 * h * w)
    ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
    tone = 1.0 + speckle * rng.choice([-1.0, -0.6, 0.5], n)
    img[ys, xs] *= tone[:, None].astype(np.float32)
    return png(_finish(cv2.GaussianBlur(img, (3, 3), 0.6)))


def wood(rng: np.random.Generator, rgb=(150, 112, 78), size=(512, 128), grain: float = 0.07,
         period_px: float = 7.0) -> bytes:
    """Wood: grain lines along the texture's width, wavy, low contrast."""
    h, w = size[1], size[0]
    y = np.arange(h, dtype=np.float32)[:, None] + 0.8 * period_px * _smooth_noise(rng, (h, w), 80.0)
    period = float(rng.uniform(0.75, 1.25) * period_px)
    g = 0.5 + 0.5 * np.sin(2 * np.pi * y / period + 2.0 * _smooth_noise(rng, (h, w), 30.0))
    shade = 1.0 + grain * (g - 0.5) * 2.0 + 0.03 * _smooth_noise(rng, (h, w), 60.0)
    return png(_finish(shade[..., None] * np.asarray(rgb, np.float32)))


def tiles(rng: np.random.Generator, n=(4, 4), tile_px: int = 48, rgb=(228, 226, 218), grout_rgb=(168, 164, 156),
          grout_px: int = 3, tint: float = 0.015) -> bytes:
    """A block of n[0] x n[1] square tiles with grout lines; repeated over a wall (texuniform) it
    makes a periodic pattern, the classic trap for matching by appearance."""
    W, H = n[0] * tile_px, n[1] * tile_px
    img = np.empty((H, W, 3), np.float32)
    img[:] = grout_rgb
    for i in range(n[0]):
        for j in range(n[1]):
            x0, y0 = i * tile_px + grout_px // 2, j * tile_px + grout_px // 2
            x1, y1 = (i + 1) * tile_px - (grout_px + 1) // 2, (j + 1) * tile_px - (grout_px + 1) // 2
            k = 1.0 + tint * rng.standard_normal()
            glaze = 1.0 + 0.02 * np.linspace(-1, 1, x1 - x0, dtype=np.float32)[None, :]   # glaze sheen
            img[y0:y1, x0:x1] = np.asarray(rgb, np.float32) * k * glaze[..., None]
    return png(_finish(img))


def _text_mask(shape: tuple[int, int], text: str, org, scale: float, thickness: int = 1,
               font: int = cv2.FONT_HERSHEY_SIMPLEX) -> np.ndarray:
    """(H, W) float coverage 0..1 of anti-aliased text (OpenCV draws text on 8-bit images only)."""
    mask = np.zeros(shape, np.uint8)
    cv2.putText(mask, text, (int(org[0]), int(org[1])), font, scale, 255, thickness, cv2.LINE_AA)
    return mask.astype(np.float32) / 255.0


def _text(img: np.ndarray, text: str, org, scale: float, rgb, thickness: int = 1,
          font: int = cv2.FONT_HERSHEY_SIMPLEX) -> None:
    """Print ``text`` in colour ``rgb`` onto the float image ``img`` (in place)."""
    a = _text_mask(img.shape[:2], text, org, scale, thickness, font)[..., None]
    img *= 1 - a
    img += a * np.asarray(rgb, np.float32)


def _text_width(text: str, scale: float, thickness: int = 1, font: int = cv2.FONT_HERSHEY_SIMPLEX) -> int:
    return cv2.getTextSize(text, font, scale, thickness)[0][0]


def _fit_scale(text: str, width_px: float, max_scale: float, thickness: int = 1) -> float:
    return min(max_scale, 0.95 * width_px / max(_text_width(text, 1.0, thickness), 1))


def label(rng: np.random.Generator, text: str, size=(192, 128), paper=(226, 220, 204), ink=(58, 52, 48),
          band=None) -> bytes:
    """A printed paper label: one word, a thin colour band, a line of small print."""
    w, h = size
    img = _surface(rng, (h, w), paper, 0.015, 0.006)
    band = band if band is not None else muted_colour(rng, 90, 170, 0.5)
    img[int(0.12 * h):int(0.22 * h)] = band
    s = _fit_scale(text, 0.8 * w, 1.6, 2)
    tw = _text_width(text, s, 2)
    _text(img, text, ((w - tw) / 2, 0.62 * h), s, ink, 2)
    small = " ".join(rng.choice(WORDS, 2)).lower()
    _text(img, small, (0.1 * w, 0.85 * h), _fit_scale(small, 0.8 * w, 0.45), ink)
    return png(_finish(img))


def carton(rng: np.random.Generator, size=(192, 256), word: str = "OATS") -> bytes:
    """A lightly printed packet: a pale panel, a big word, a round picture, small print."""
    w, h = size
    base = muted_colour(rng, 150, 210, 0.3)
    img = _surface(rng, (h, w), base, 0.02, 0.006)
    img[int(0.55 * h):] = 0.8 * np.asarray(base, np.float32) + 0.2 * 225.0
    s = _fit_scale(word, 0.8 * w, 1.8, 3)
    _text(img, word, (0.1 * w, 0.3 * h), s, (60, 50, 45), 3)
    cv2.circle(img, (int(0.5 * w), int(0.75 * h)), int(0.17 * w), muted_colour(rng, 110, 190, 0.4), -1, cv2.LINE_AA)
    for k in range(3):
        _text(img, " ".join(rng.choice(WORDS, 2)).lower(), (0.08 * w, (0.42 + 0.05 * k) * h), 0.35, (80, 70, 65))
    return png(_finish(img))


def poster(rng: np.random.Generator, size=(256, 360), title: str | None = None) -> bytes:
    """A poster: a muted background, a picture of soft blocks and a disc, a title, lines of text."""
    w, h = size
    bg = muted_colour(rng, 175, 222, 0.15)
    img = _surface(rng, (h, w), bg, 0.02, 0.005)
    x0, y0, x1, y1 = int(0.08 * w), int(0.2 * h), int(0.92 * w), int(0.68 * h)
    pic = _surface(rng, (y1 - y0, x1 - x0), muted_colour(rng, 90, 160, 0.4), 0.15, 0.01, cell_px=50)
    for _ in range(3):
        a, b = rng.integers(0, x1 - x0, 2), rng.integers(0, y1 - y0, 2)
        cv2.rectangle(pic, (int(a.min()), int(b.min())), (int(a.max()), int(b.max())),
                      tuple(float(c) for c in muted_colour(rng, 70, 190, 0.5)), -1)
    cv2.circle(pic, (int(rng.integers(0, x1 - x0)), int(rng.integers(0, y1 - y0))), int(0.15 * w),
               tuple(float(c) for c in muted_colour(rng, 120, 220, 0.5)), -1, cv2.LINE_AA)
    img[y0:y1, x0:x1] = cv2.GaussianBlur(pic, (0, 0), 1.5)
    title = title or " ".join(rng.choice(WORDS, 2)).upper()
    _text(img, title, (0.08 * w, 0.13 * h), _fit_scale(title, 0.84 * w, 1.4, 2), (45, 40, 40), 2)
    for k in range(4):
        line = " ".join(rng.choice(WORDS, 4)).lower()
        _text(img, line, (0.08 * w, (0.76 + 0.05 * k) * h), _fit_scale(line, 0.84 * w, 0.4), (70, 65, 60))
    return png(_finish(img))


def book_spine(rng: np.random.Generator, size=(40, 220), title: str | None = None, cover=None) -> bytes:
    """A book's spine (taller than wide): cloth or paper colour, a band or two, the title running
    down the spine and an author's initials near the foot."""
    w, h = size
    cover = cover if cover is not None else muted_colour(rng, 45, 185, 0.45)
    img = _surface(rng, (h, w), cover, 0.03, 0.01, cell_px=30)
    ink = (225, 215, 190) if np.mean(cover) < 120 else (35, 30, 28)
    for y in rng.choice([0.08, 0.12, 0.88, 0.92], int(rng.integers(0, 3)), replace=False):
        img[int(y * h):int(y * h) + 3] = ink
    title = title or " ".join(rng.choice(WORDS, int(rng.integers(1, 3))))
    # The title on a strip laid along the spine, then turned a quarter turn.
    strip = _text_mask((w, h), title, (0.12 * h, 0.68 * w), _fit_scale(title, 0.7 * h, 0.5 * w / 22))
    a = cv2.rotate(strip, cv2.ROTATE_90_CLOCKWISE)[..., None]
    img = img * (1 - a) + a * np.asarray(ink, np.float32)
    return png(_finish(img))


def keyboard(rng: np.random.Generator, size=(448, 150), keys=(15, 5)) -> bytes:
    """A dark keyboard: a grid of keys a shade lighter than the case (repeated, low contrast)."""
    w, h = size
    img = _surface(rng, (h, w), (34, 34, 36), 0.02, 0.01)
    kw, kh = w / keys[0], h / keys[1]
    for i in range(keys[0]):
        for j in range(keys[1]):
            cv2.rectangle(img, (int(i * kw + 2), int(j * kh + 2)), (int((i + 1) * kw - 2), int((j + 1) * kh - 2)),
                          (52, 52, 55), -1)
    return png(_finish(img))


def screen(rng: np.random.Generator, size=(320, 192)) -> bytes:
    """A switched-off monitor: near black, a faint diagonal sheen of the room's light."""
    w, h = size
    x, y = np.meshgrid(np.linspace(0, 1, w, dtype=np.float32), np.linspace(0, 1, h, dtype=np.float32))
    sheen = 1.0 + 0.6 * np.exp(-((x - y - 0.1) ** 2) / 0.05)
    img = sheen[..., None] * np.array([12, 13, 15], np.float32) + 0.5 * rng.standard_normal((h, w, 1))
    return png(_finish(img))


def window_view(rng: np.random.Generator, size=(256, 320)) -> bytes:
    """Daylight through a window: a bright sky over the soft, darker line of trees and roofs."""
    w, h = size
    y = np.linspace(0, 1, h, dtype=np.float32)[:, None, None]
    sky = (1 - y) * np.array([205, 222, 240], np.float32) + y * np.array([235, 238, 240], np.float32)
    img = np.broadcast_to(sky, (h, w, 3)).copy()
    skyline = 0.62 * h + 0.1 * h * _smooth_noise(rng, (1, w), 40.0)[0]
    rows = np.arange(h)[:, None]
    ground = rows > skyline[None, :]
    img[ground] = np.array([120, 135, 115], np.float32) * (1 + 0.1 * rng.standard_normal((int(ground.sum()), 1)))
    return png(_finish(cv2.GaussianBlur(img, (0, 0), 2.0)))


def cupboard_door(rng: np.random.Generator, rgb=(222, 218, 206), size=(160, 256)) -> bytes:
    """A painted shaker door: a plain panel inside a frame whose edges catch the light."""
    w, h = size
    img = _surface(rng, (h, w), rgb, 0.02, 0.006)
    m = int(0.14 * w)
    cv2.rectangle(img, (m, m), (w - m, h - m), tuple(0.9 * float(c) for c in rgb), 2, cv2.LINE_AA)
    cv2.rectangle(img, (m + 3, m + 3), (w - m - 3, h - m - 3), tuple(1.03 * float(c) for c in rgb), 1, cv2.LINE_AA)
    return png(_finish(img))
