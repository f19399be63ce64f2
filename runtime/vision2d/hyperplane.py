"""Planar-patch tracking by hyperplane approximation (paper, section 3, item 2 and Fig. 6), after
Jurie and Dhome, "Hyperplane approximation for template matching" (PAMI 2002) and "Real time
robust template matching" (BMVC 2002).

The patch is a plane region. Its *template frame* is a w x h rectangle (pixels of the reference
image for a rectangular start) with corners c = (0, 0), (w, 0), (w, h), (0, h); the state is the
homography ``H_img_tmpl`` (3, 3) mapping template coordinates to image pixels. A sampling pattern
of n points (a grid in the template) is read from the image through H_img_tmpl.

Learning (once, from the reference image): the motion is parametrised by displacements of the
template corners (homography: all 4 corners, 8 numbers; affine: the first 3 corners, 6 numbers).
N random displacements dmu (N > n) of up to ``range`` x the region's size are drawn; for each the
reference is sampled at H_img_tmpl . H_p(dmu) and the normalised intensity difference
di = I_ref - I(H_p) recorded. The linear map A (params x samples) with dmu ~= A di is the ridge
least-squares solution over those N examples. A cascade of such maps is learned for decreasing
ranges (coarse to fine) and each is applied a few times per frame.

Tracking (each frame): sample the pattern under the current H_img_tmpl, di = I_ref - I_cur,
dmu = A di; the sampled view equals the reference warped by H_p(dmu), so the true homography is
H_img_tmpl . H_p(dmu)^-1. The residual (RMS of di in normalised units: ~0 on a match, ~1.4 for
unrelated texture) and the share of the pattern inside the image decide a loss of track, which
is reported; the pose then coasts on the last velocity for a few frames rather than follow
a bad fit. Each frame starts from a constant-velocity prediction of the homography.

Occlusion (the robust variant of the BMVC paper, kept simple): the pattern is cut into blocks
(default 10 x 10). After each level of the cascade, blocks whose residual is far above the median
block's are marked occluded and the remaining rows of the learning problem are *re-solved
exactly*: with D (N, n) the training differences and M (N, P) the displacements, the ridge map
restricted to the kept samples S is A_S^T = (D_S^T D_S + lam I)^-1 D_S^T M, i.e. a solve with the
sub-block G[S, S] of the precomputed Gram matrix G = D^T D + lam I and the rows C[S] of
C = D^T M, cached per mask. Normalisation (zero mean, unit variance) also uses only the kept
samples, so a bright occluder does not shift the whole pattern's statistics.

Scale and size of the sampling pattern at run time: :meth:`HyperplaneTracker.relearn` re-learns
the cascade from the current frame with a new grid density and/or pattern extent, keeping the
tracked region (the template frame) as it is.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from . import images
from .tracker import TrackResult

MOTIONS = {"homography": 4, "affine": 3}   # motion model -> number of corners it displaces


@dataclass(frozen=True)
class HyperplaneConfig:
    """Settings of :class:`HyperplaneTracker` (one place, no literals in the code).

    grid : (nx, ny) samples of the pattern across and down the template.
    extent : the pattern's share of the template's width and height (its "size"), in (0, 1].
    motion : "homography" (8 corner-displacement parameters) or "affine" (6).
    ranges : largest corner displacement of each cascade level, as a fraction of the region's
        width (x) and height (y); coarse to fine.
    iterations : applications of each level's map per frame.
    train_factor : training perturbations per level = train_factor x samples (must exceed 1).
    ridge : ridge weight, relative to the Gram matrix's mean diagonal.
    train_noise : std of noise added to the training differences (normalised units); it makes
        the map robust to camera noise.
    blur : Gaussian sigma (pixels) applied to every image; None = 0.35 x the pattern's spacing
        in the reference image (smoother images keep the linear model valid over a wider range).
    blocks : (bx, by) blocks of the pattern for the occlusion test; (1, 1) disables it.
    outlier_factor, outlier_floor : a block is occluded when its RMS residual exceeds both
        outlier_factor x the median block's and outlier_floor (normalised units).
    max_rejected : at most this share of the blocks may be set aside; more is a loss of track.
    robust_steps : the first this many iterations of the cascade try the subset hypotheses (see track).
    switch_margin : another subset replaces the current one only if its score is lower by this share.
    trim : share of the blocks (the best-matching) that score a hypothesis.
    aligned_rms : the occluded blocks are re-decided only when the median block's RMS residual is
        below this (the patch is aligned); otherwise the subset chosen so far is kept.
    predict : start each frame from a constant-velocity prediction of the homography.
    coast_frames : while lost, the pose follows that prediction for this many frames, then stays.
    lost_residual : RMS residual (normalised units, over kept samples) above which the track is lost.
    min_inside : the share of the pattern that must fall inside the image.
    seed : random seed of the training perturbations.
    """

    grid: tuple[int, int] = (20, 20)
    extent: float = 0.9
    motion: str = "homography"
    ranges: tuple[float, ...] = (0.20, 0.10, 0.05, 0.02)
    iterations: int = 2
    train_factor: float = 2.5
    ridge: float = 1e-2
    train_noise: float = 0.05
    blur: float | None = None
    blocks: tuple[int, int] = (10, 10)
    outlier_factor: float = 2.5
    outlier_floor: float = 0.5
    max_rejected: float = 0.5
    robust_steps: int = 8
    switch_margin: float = 0.0
    trim: float = 0.7
    aligned_rms: float = 0.35
    predict: bool = True
    coast_frames: int = 10
    lost_residual: float = 0.45
    min_inside: float = 0.8
    seed: int = 0

    def check(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"motion {self.motion!r} unknown; use one of {sorted(MOTIONS)}")
        nx, ny = self.grid
        if nx < 3 or ny < 3:
            raise ValueError(f"grid {self.grid} too coarse; give at least 3 x 3 samples")
        if not 0.1 <= self.extent <= 1.0:
            raise ValueError(f"extent {self.extent} must be in [0.1, 1] (share of the region the pattern covers)")
        if not self.ranges or any(not 0 < r < 0.5 for r in self.ranges):
            raise ValueError(f"ranges {self.ranges} must be fractions of the region's size in (0, 0.5)")
        if self.train_factor <= 1.0:
            raise ValueError(f"train_factor {self.train_factor} must exceed 1 (more perturbations than samples)")
        bx, by = self.blocks
        if not (1 <= bx <= nx and 1 <= by <= ny):
            raise ValueError(f"blocks {self.blocks} must be between 1 and the grid {self.grid} in each direction")
        if self.iterations < 1:
            raise ValueError("iterations must be at least 1")


@dataclass
class _Level:
    """One cascade level: range (fraction of size), Gram G (n, n) with ridge, C = D^T M (n, P),
    and the cache of maps A_S^T (|S|, P) keyed by the kept-sample mask."""

    range: float
    G: np.ndarray
    C: np.ndarray
    cache: dict = field(default_factory=dict)

    def map_for(self, keep: np.ndarray) -> np.ndarray:
        """A_S^T (|S|, P) for the samples ``keep`` (n,) bool: the ridge solution re-solved on
        the kept rows only (exact, not an approximation of the full map)."""
        key = keep.tobytes()
        At = self.cache.get(key)
        if At is None:
            idx = np.flatnonzero(keep)
            At = np.linalg.solve(self.G[np.ix_(idx, idx)], self.C[idx])
            if len(self.cache) > 64:   # occluders move: keep the cache small
                self.cache.clear()
            self.cache[key] = At
        return At

    def full_map_for(self, keep: np.ndarray) -> np.ndarray:
        """A_S^T scattered into (n, P), zero rows for the samples left out."""
        key = b"full" + keep.tobytes()
        F = self.cache.get(key)
        if F is None:
            F = np.zeros_like(self.C)
            F[keep] = self.map_for(keep)
            self.cache[key] = F
        return F


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey from (H, W) grey or (H, W, 3) RGB uint8 (or float)."""
    return images.to_grey(image).astype(np.float32)


def corners_transform(c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
    """(3, 3) homography (4 corners) or affine map (3 corners) taking points c0 (k, 2) to c1 (k, 2)."""
    c0 = np.asarray(c0, np.float32)
    c1 = np.asarray(c1, np.float32)
    if len(c0) == 4:
        return cv2.getPerspectiveTransform(c0, c1).astype(np.float64)
    return np.vstack([cv2.getAffineTransform(c0, c1).astype(np.float64), [0.0, 0.0, 1.0]])


def apply_h(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points (n, 2) mapped by homography H (3, 3) -> (n, 2)."""
    p = pts @ H[:, :2].T + H[:, 2]
    return p[:, :2] / p[:, 2:3]


def _normalise(v: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, float]:
    """(v - mean) / std over the kept entries (last axis); also returns the smallest std seen."""
    n = np.maximum(keep.sum(-1, keepdims=True), 1)
    m = (v * keep).sum(-1, keepdims=True) / n
    d = (v - m) * keep
    s = np.sqrt((d * d).sum(-1, keepdims=True) / n)
    return (v - m) / np.maximum(s, 1e-6), float(s.min())


def check_region(region, width: int, height: int, min_size: float = 8.0) -> np.ndarray:
    """A start region as corners (4, 2) pixels, or ValueError naming the problem.

    region : (x, y, w, h) pixels (top-left corner, width, height) or a quadrilateral (4, 2)
    (corners in order around the region). It must have at least ``min_size`` px sides and lie
    inside the width x height image."""
    r = np.asarray(region, dtype=np.float64)
    if r.shape == (4,):
        x, y, w, h = r
        if not np.all(np.isfinite(r)) or w < min_size or h < min_size:
            raise ValueError(f"start window {','.join(f'{float(v):g}' for v in r)} must have finite x, y and width and height of at "
                             f"least {min_size:g} px; give --init x,y,w,h around the object")
        quad = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]])
    elif r.shape == (4, 2):
        quad = r
        if not np.all(np.isfinite(quad)):
            raise ValueError("start quadrilateral has non-finite corners")
        area = polygon_area(quad)
        if area < min_size ** 2 or not _convex(quad):
            raise ValueError(f"start quadrilateral {quad.tolist()} is degenerate or not convex; give 4 corners "
                             f"in order around a region of at least {min_size:g} x {min_size:g} px")
    else:
        raise ValueError(f"start region of shape {r.shape}: give (x, y, w, h) or 4 corners (4, 2)")
    if quad[:, 0].min() < -0.5 or quad[:, 1].min() < -0.5 or quad[:, 0].max() > width - 0.5 or \
            quad[:, 1].max() > height - 0.5:
        raise ValueError(f"start region {np.round(quad, 1).tolist()} is not inside the {width}x{height} image "
                         f"(corners within x -0.5..{width - 0.5:g}, y -0.5..{height - 0.5:g} px: pixel centres are "
                         f"whole numbers); give a window within the first frame, e.g. 0,0,{width - 1},{height - 1} "
                         f"for all of it")
    return quad


def polygon_area(poly: np.ndarray) -> float:
    """Area (px^2) of a simple polygon (k, 2) (shoelace formula)."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _convex(quad: np.ndarray) -> bool:
    """True if the polygon (4, 2) is strictly convex (consistent turn direction)."""
    d = np.roll(quad, -1, 0) - quad
    z = d[:, 0] * np.roll(d, -1, 0)[:, 1] - d[:, 1] * np.roll(d, -1, 0)[:, 0]
    return bool(np.all(z > 0) or np.all(z < 0))


class HyperplaneTracker:
    """Learned planar-patch tracker (Jurie and Dhome 2002); see the module docstring.

    ``HyperplaneTracker(image, region, config=None)`` learns from ``image`` ((H, W) grey or
    (H, W, 3) RGB uint8) and ``region`` ((x, y, w, h) pixels, or 4 corners (4, 2) pixels in
    order); ``track(image) -> TrackResult`` follows it. Attributes: ``H_img_tmpl`` (3, 3) the
    current pose, ``size`` (w, h) of the template frame, ``learn_seconds`` the last learning time.
    """

    def __init__(self, image: np.ndarray, region, config: HyperplaneConfig | None = None):
        self.config = config or HyperplaneConfig()
        self.config.check()
        grey = to_grey(image)
        quad = check_region(region, grey.shape[1], grey.shape[0])
        w = 0.5 * (np.linalg.norm(quad[1] - quad[0]) + np.linalg.norm(quad[2] - quad[3]))
        h = 0.5 * (np.linalg.norm(quad[3] - quad[0]) + np.linalg.norm(quad[2] - quad[1]))
        self.size = (float(w), float(h))
        self.corners_tmpl = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        self.H_img_tmpl = corners_transform(self.corners_tmpl, quad)
        self._learn(grey, blur_image=True)

    # ------------------------------------------------------------------ learning
    def relearn(self, image: np.ndarray, grid: tuple[int, int] | None = None, extent: float | None = None,
                ranges: tuple[float, ...] | None = None) -> float:
        """Re-learn the cascade from ``image`` at the current pose, e.g. with a denser pattern
        when the patch has grown in the image (``grid``), or a smaller or larger pattern within
        the region (``extent``), or other ranges. The tracked region (template frame) is kept;
        the reference intensities are re-read from this frame. Returns the learning time, s."""
        changes = {k: v for k, v in (("grid", grid), ("extent", extent), ("ranges", ranges)) if v is not None}
        cfg = replace(self.config, **changes)
        if grid is not None and self.config.blocks != (1, 1):
            cfg = replace(cfg, blocks=(min(cfg.blocks[0], grid[0]), min(cfg.blocks[1], grid[1])))
        cfg.check()
        self.config = cfg
        self._learn(to_grey(image), blur_image=True)
        return self.learn_seconds

    def _pattern(self) -> None:
        """Sample points (n, 2) in template coordinates (cell centres of the grid over the
        central ``extent`` of the template) and each one's block index (n,)."""
        cfg = self.config
        (nx, ny), (w, h) = cfg.grid, self.size
        fx = (np.arange(nx) + 0.5) / nx
        fy = (np.arange(ny) + 0.5) / ny
        gx, gy = np.meshgrid(0.5 * w + (fx - 0.5) * w * cfg.extent, 0.5 * h + (fy - 0.5) * h * cfg.extent)
        self.pts_tmpl = np.column_stack([gx.ravel(), gy.ravel()])
        bx = np.minimum((np.arange(nx) * cfg.blocks[0]) // nx, cfg.blocks[0] - 1)
        by = np.minimum((np.arange(ny) * cfg.blocks[1]) // ny, cfg.blocks[1] - 1)
        self.block_of = (by[:, None] * cfg.blocks[0] + bx[None, :]).ravel()
        self.n_blocks = cfg.blocks[0] * cfg.blocks[1]
        self.block_indicator = np.zeros((len(self.block_of), self.n_blocks))
        self.block_indicator[np.arange(len(self.block_of)), self.block_of] = 1.0

    def _prepare(self, grey: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(grey, (0, 0), self.blur) if self.blur > 0 else grey

    def _sample(self, img: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intensities (..., n) of the pattern under H (3, 3) or a stack (K, 3, 3) (bilinear,
        cv2.remap) and whether each point fell inside the image (..., n) bool."""
        p = np.einsum("...ij,nj->...ni", H, np.column_stack([self.pts_tmpl, np.ones(len(self.pts_tmpl))]))
        uv = p[..., :2] / p[..., 2:3]
        mx = np.ascontiguousarray(uv[..., 0].reshape(-1, len(self.pts_tmpl)), dtype=np.float32)
        my = np.ascontiguousarray(uv[..., 1].reshape(-1, len(self.pts_tmpl)), dtype=np.float32)
        vals = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        Hh, Ww = img.shape
        inside = (uv[..., 0] >= 0) & (uv[..., 0] <= Ww - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= Hh - 1)
        return vals.reshape(uv.shape[:-1]).astype(np.float64), inside

    def _learn(self, grey: np.ndarray, blur_image: bool) -> None:
        cfg = self.config
        t0 = time.perf_counter()
        self._pattern()
        n = len(self.pts_tmpl)
        k = MOTIONS[cfg.motion]
        if cfg.blur is None:
            # pattern spacing in the image (px), from the template's scale in the image
            J = np.linalg.norm(apply_h(self.H_img_tmpl, self.corners_tmpl[[1, 3]]) -
                               apply_h(self.H_img_tmpl, self.corners_tmpl[[0, 0]]), axis=1) / np.array(self.size)
            spacing = float(np.mean(J * np.array(self.size) * cfg.extent / np.array(cfg.grid)))
            self.blur = max(0.5, 0.35 * spacing)
        else:
            self.blur = float(cfg.blur)
        img = self._prepare(grey)
        ref, inside = self._sample(img, self.H_img_tmpl)
        if inside.mean() < cfg.min_inside:
            raise ValueError("the sampling pattern falls outside the image; choose a region within the frame")
        self.ref_raw = ref
        ref_n, s = _normalise(ref, np.ones(n, bool))
        if s < 1.0:
            raise ValueError(f"the region has no texture (intensity std {s:.2f} grey levels); the planar "
                             f"tracker needs a textured patch, choose another region or use mean shift")
        rng = np.random.default_rng(cfg.seed)
        N = int(np.ceil(cfg.train_factor * n))
        scale = np.array(self.size)
        self.levels = []
        for r in cfg.ranges:
            # corner displacements, uniform within +-r of the region's size per axis
            dmu = rng.uniform(-1.0, 1.0, (N, k, 2)) * r * scale
            c0 = self.corners_tmpl[:k]
            Hp = np.stack([corners_transform(c0, c0 + d) for d in dmu])
            vals, _ = self._sample(img, self.H_img_tmpl @ Hp)
            vals_n, _ = _normalise(vals, np.ones(n, bool))
            D = ref_n[None, :] - vals_n + rng.normal(0.0, cfg.train_noise, (N, n))
            M = dmu.reshape(N, 2 * k)
            G = D.T @ D
            G[np.diag_indices(n)] += cfg.ridge * np.trace(G) / n
            lvl = _Level(range=r, G=G, C=D.T @ M)
            lvl.map_for(np.ones(n, bool))   # the full map, cached
            self.levels.append(lvl)
        self.block_keep = np.ones(self.n_blocks, bool)
        self.H_velocity = np.eye(3)
        self.lost_run = 0
        self.learn_seconds = time.perf_counter() - t0

    # ------------------------------------------------------------------ tracking
    @property
    def polygon(self) -> np.ndarray:
        """(4, 2) current corners, pixels."""
        return apply_h(self.H_img_tmpl, self.corners_tmpl)

    def start_result(self) -> TrackResult:
        """The learned region as a result (residual 0: the reference itself)."""
        return self._result(False, 0.0, 1.0, None)

    def _result(self, lost: bool, residual: float, inliers: float, reason: str | None) -> TrackResult:
        centre = apply_h(self.H_img_tmpl, np.array([[0.5 * self.size[0], 0.5 * self.size[1]]]))[0]
        return TrackResult(self.polygon, centre, lost, residual, inliers, reason)

    def _residuals(self, vals: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, float]:
        """Per-sample differences (n,) normalised over the kept samples, and the smallest std."""
        ref_n, _ = _normalise(self.ref_raw, keep)
        cur_n, s = _normalise(vals, keep)
        return ref_n - cur_n, s

    def _block_rms(self, di: np.ndarray, inside: np.ndarray) -> np.ndarray:
        """RMS residual per block (n_blocks,) over the samples inside the image (inf if none)."""
        sq = np.bincount(self.block_of, weights=(di * di) * inside, minlength=self.n_blocks)
        cnt = np.bincount(self.block_of, weights=inside.astype(float), minlength=self.n_blocks)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(cnt > 0, np.sqrt(sq / np.maximum(cnt, 1)), np.inf)

    def _update_blocks(self, di: np.ndarray, inside: np.ndarray) -> None:
        """Mark occluded blocks: those whose RMS residual is well above the median block's."""
        if self.n_blocks == 1:
            return
        rms = self._block_rms(di, inside)
        finite = np.isfinite(rms)
        med = float(np.median(rms[finite]))
        if med > self.config.aligned_rms:
            # still misaligned: every block's residual is high and says nothing about occlusion;
            # keep the subset chosen so far
            return
        thr = max(self.config.outlier_factor * med, self.config.outlier_floor)
        self.block_keep = finite & (rms <= thr)

    def _hypotheses(self) -> list[np.ndarray]:
        """Block masks (n_blocks,) bool to try: the current mask (first), all blocks, and the pattern with one strip of columns, one strip of rows or one corner
        quarter left out. An occluder appearing between two frames spoils the full map's
        prediction; one of these subsets then misses most of it."""
        bx, by = self.config.blocks
        if bx * by == 1:
            return [self.block_keep]
        grid = np.ones((by, bx), bool)
        out = [self.block_keep]
        if not self.block_keep.all():
            out.append(np.ones(bx * by, bool))
        wx, wy = max(1, round(0.4 * bx)), max(1, round(0.4 * by))
        for i in range(bx - wx + 1):
            g = grid.copy(); g[:, i:i + wx] = False; out.append(g.ravel())
        for j in range(by - wy + 1):
            g = grid.copy(); g[j:j + wy, :] = False; out.append(g.ravel())
        qx, qy = (bx + 1) // 2, (by + 1) // 2
        for sx in (slice(0, qx), slice(bx - qx, bx)):
            for sy in (slice(0, qy), slice(by - qy, by)):
                g = grid.copy(); g[sy, sx] = False; out.append(g.ravel())
        return out

    def _steps(self, level: _Level, vals: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One application of a level's map for each of K sample subsets ``keep`` (K, n) bool
        at once: the updated homographies (K, 3, 3) and which of them are usable (K,) bool."""
        ref_n, _ = _normalise(self.ref_raw[None, :], keep)
        cur_n, _ = _normalise(vals[None, :], keep)
        di = (ref_n - cur_n) * keep
        dmu = np.einsum("kn,knp->kp", di, np.stack([level.full_map_for(kp) for kp in keep]))
        k = dmu.shape[1] // 2
        # the linear model holds only within the range it was learned on: a larger prediction is
        # an extrapolation (typically caused by unmodelled occlusion), so clamp it to the range
        lim = np.tile(level.range * np.asarray(self.size), k)
        dmu = np.clip(dmu, -lim, lim)
        c0 = self.corners_tmpl[:k]
        Hp_inv = np.stack([corners_transform(c0 + d.reshape(-1, 2), c0) for d in dmu])
        H = self.H_img_tmpl[None] @ Hp_inv
        ok = np.all(np.isfinite(H), axis=(1, 2)) & (np.abs(H[:, 2, 2]) > 1e-12)
        H[ok] /= H[ok, 2:3, 2:3]
        H[~ok] = np.eye(3)
        return H, ok

    def track(self, image: np.ndarray | None) -> TrackResult:
        """Follow the patch into ``image`` ((H, W) grey or (H, W, 3) RGB). A loss of track
        (residual too high, pattern out of the image or mostly occluded, degenerate pose, no
        image or no contrast) is reported in the result; the pose then coasts on the last velocity
        for ``coast_frames`` frames (or stays, with predict=False) instead of following the fit."""
        cfg = self.config
        H_before = self.H_img_tmpl.copy()
        if image is None:
            self.H_velocity = np.eye(3)
            return self._result(True, float("nan"), 0.0, "no image")
        if cfg.predict and self.lost_run == 0:
            # constant velocity in the template frame: H_t = H_t-1 (H_t-2^-1 H_t-1)
            self.H_img_tmpl = self.H_img_tmpl @ self.H_velocity
        img = self._prepare(to_grey(image))
        n = len(self.pts_tmpl)
        min_keep = (1.0 - cfg.max_rejected) * n
        reason = None
        step = 0
        for li, level in enumerate(self.levels):
            for _ in range(cfg.iterations):
                step += 1
                vals, inside = self._sample(img, self.H_img_tmpl)
                if inside.mean() < cfg.min_inside:
                    reason = f"patch left the image ({100 * inside.mean():.0f}% of the pattern inside)"
                    break
                if _normalise(vals, inside)[1] < 1.0:
                    reason = "no contrast in the patch (blank, black or saturated image)"
                    break
                # coarse levels: try several sample subsets, keep the update whose result
                # matches best on its best-matching blocks (a trimmed block residual)
                masks = np.array(self._hypotheses() if step <= cfg.robust_steps else [self.block_keep])
                keep = inside[None, :] & masks[:, self.block_of]
                usable = keep.sum(1) >= min_keep
                if not usable.any():
                    reason = f"patch mostly occluded (fewer than {100 * (1 - cfg.max_rejected):.0f}% of the samples usable)"
                    break
                masks, keep = masks[usable], keep[usable]
                Hs, ok = self._steps(level, vals, keep)
                if not ok.any():
                    reason = "degenerate pose update"
                    break
                if len(Hs) == 1:
                    self.H_img_tmpl = Hs[0]
                    continue
                # score each subset's update by the RMS residual of its best-matching blocks
                # (normalised over its own samples), so the occluder does not count
                cv, cin = self._sample(img, Hs)
                ck = cin & masks[:, self.block_of]
                ref_n, _ = _normalise(self.ref_raw[None, :], ck)
                cur_n, _ = _normalise(cv, ck)
                sq = ((ref_n - cur_n) ** 2 * cin) @ self.block_indicator
                cnt = cin.astype(float) @ self.block_indicator
                rms = np.where(cnt > 0, np.sqrt(sq / np.maximum(cnt, 1)), np.inf)
                ntrim = max(1, int(np.ceil(cfg.trim * self.n_blocks)))
                scores = np.sort(rms, axis=1)[:, :ntrim].mean(1)
                scores[~ok | (cin.mean(1) < cfg.min_inside) | (ck.sum(1) < min_keep)] = np.inf
                # hysteresis: the current subset (first) stays unless another is clearly better
                scores[1:] *= 1.0 + cfg.switch_margin
                best = int(np.argmin(scores))
                # the winner's subset is used until the residuals re-decide it after this level
                self.H_img_tmpl, self.block_keep = Hs[best], masks[best]
            if reason:
                break
            # robust step: re-decide the occluded blocks from this level's residuals
            vals, inside = self._sample(img, self.H_img_tmpl)
            di, _ = self._residuals(vals, inside & self.block_keep[self.block_of] if
                                    (inside & self.block_keep[self.block_of]).sum() >= min_keep else inside)
            self._update_blocks(di, inside)
        residual, keep = float("nan"), np.zeros(n, bool)
        if reason is None:
            vals, inside = self._sample(img, self.H_img_tmpl)
            keep = inside & self.block_keep[self.block_of]
            if inside.mean() < cfg.min_inside:
                reason = f"patch left the image ({100 * inside.mean():.0f}% of the pattern inside)"
            elif keep.sum() < min_keep:
                reason = f"patch mostly occluded ({100 * (1 - keep.mean()):.0f}% of the pattern set aside)"
            else:
                di, _ = self._residuals(vals, keep)
                residual = float(np.sqrt(np.mean(di[keep] ** 2)))
                poly = self.polygon
                area = polygon_area(poly)
                poly0 = apply_h(H_before, self.corners_tmpl)
                area0 = polygon_area(poly0)
                if not _convex(poly) or not 0.05 < area / max(area0, 1e-9) < 20.0:
                    reason = "degenerate pose (polygon folded or collapsed)"
                elif residual > cfg.lost_residual:
                    reason = f"residual {residual:.2f} above {cfg.lost_residual:g} (appearance does not match)"
                else:
                    if self.lost_run == 0:
                        self.H_velocity = np.linalg.inv(H_before) @ self.H_img_tmpl
                    self.lost_run = 0
                    return self._result(False, residual, float(keep.mean()), None)
        # lost: report it and forget the occlusion mask; the pose coasts on the last velocity
        # for a few frames (an object passing behind an occluder keeps moving), then stays
        self.lost_run += 1
        self.H_img_tmpl = H_before @ self.H_velocity if cfg.predict and self.lost_run <= cfg.coast_frames else H_before
        self.block_keep = np.ones(self.n_blocks, bool)
        return self._result(True, residual, float(keep.mean()), reason)
