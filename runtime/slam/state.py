"""The filter's state: the one door through which the filter's mean and covariance are written
(predictions, updates, features added, removed or converted, the camera restarted, trials
rolled back), over the layout of layout.py, and the covariance guard.

State vector (SI units)
-----------------------
``x = [x_v, y_0, y_1, ..., y_{N-1}]`` with one full covariance ``P`` (n, n): a single EKF over
camera and map, as in MonoSLAM.

camera block ``x_v``, 13 numbers, or 19 with IMU bias states:

====== ======= ==========================================================================
slice  symbol  meaning
====== ======= ==========================================================================
0:3    r       position of the camera's optical centre in the world frame, m
3:7    q       unit quaternion, **w x y z order**, rotating camera (optical frame: x right,
               y down, z forward) coordinates into the world frame: ``p_world = R(q) p_cam
               + r`` (quaternion.py)
7:10   v       linear velocity of the optical centre, world frame, m/s
10:13  w       angular velocity, camera (optical) frame, rad/s; ``q_new = q * q(w dt)``
13:16  b_g     gyro bias, camera frame, rad/s (only with bias states)
16:19  b_a     accelerometer bias, camera frame, m/s^2 (only with bias states)
====== ======= ==========================================================================

features: each feature ``k`` has a kind (features/: a 3D point, an inverse-depth ray, ...)
that fixes its size, and starts at ``State.starts[k]``; the offsets are kept in this table,
recomputed whenever a feature is added, removed or converted, so no code computes an index from
a fixed feature size. Each feature also carries a constant ``anchor`` (3, 3) rotation its model
may use (the inverse-depth model's reference frame for its angles; identity for points).

Covariance and the quaternion's norm direction
----------------------------------------------
Renormalising ``q`` multiplies the covariance by ``J = (I - q q^T)`` (at ``|q| = 1``), which
removes the variance along ``q`` itself: ``P`` is positive *semi*-definite with one exact null
direction. :func:`check_covariance` accepts eigenvalues down to ``-psd_rel_tol * max(diag P)``
and rejects anything more negative, and any NaN or Inf, naming the problem.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from .kernels import compiled_kernel
from .layout import (BA_SLICE, BG_SLICE, CAMERA_DIM, CAMERA_DIM_BIASED, CAMERA_DIM_SCALED, CAMERA_DIM_TIMED,
                     CAMERA_NAMES, FEATURE_DIMS, FEATURE_NAMES, G_SLICE, NOISE_DIM, POSE_DIM, Q_SLICE, R_SLICE,
                     SCALE_INDEX, TD_INDEX, V_SLICE, W_SLICE, check_camera_dim, feature_starts, state_size)

__all__ = ["BA_SLICE", "BG_SLICE", "CAMERA_DIM", "CAMERA_DIM_BIASED", "CAMERA_DIM_SCALED", "CAMERA_DIM_TIMED",
           "G_SLICE", "NOISE_DIM", "POSE_DIM", "Q_SLICE", "R_SLICE", "SCALE_INDEX", "TD_INDEX", "V_SLICE", "W_SLICE",
           "SlamNumericalError", "State", "StateSnapshot",
           "check_covariance", "check_mean", "feature_starts", "mirror_upper", "state_size"]


class SlamNumericalError(FloatingPointError):
    """The filter would put NaN/Inf into the state, or the covariance stopped being symmetric
    positive semi-definite. The message names the step and the problem; the state is left as it
    was before the failing step."""


# ---------------------------------------------------------------------------------------------
# The covariance guard
# ---------------------------------------------------------------------------------------------

def _where(where: str) -> str:
    return f" after {where}" if where else ""


#: Tile edge of _symmetric_and_finite: a tile read by rows and its mirror read by columns stay in
#: cache together.
_TILE = 32


@compiled_kernel()
def _symmetric_and_finite(P):
    """Whether the square C-contiguous ``P`` is exactly symmetric with every entry finite."""
    n = P.shape[0]
    for i0 in range(0, n, _TILE):
        for j0 in range(i0, n, _TILE):
            ok = True                     # no branch in the inner loop, so it vectorises
            for i in range(i0, min(i0 + _TILE, n)):
                for j in range(max(j0, i), min(j0 + _TILE, n)):
                    a = P[i, j]
                    ok &= (a == P[j, i]) & (a - a == 0.0)     # a - a is NaN for NaN/Inf
            if not ok:
                return False
    return True


@compiled_kernel()
def mirror_upper(P):
    """Copy the square C-contiguous ``P``'s upper triangle onto its lower one, in place (after a
    BLAS rank update that wrote one triangle), tile by tile as :func:`_symmetric_and_finite`."""
    n = P.shape[0]
    for i0 in range(0, n, _TILE):
        for j0 in range(i0, n, _TILE):
            for i in range(i0, min(i0 + _TILE, n)):
                for j in range(max(j0, i + 1), min(j0 + _TILE, n)):
                    P[j, i] = P[i, j]


@compiled_kernel()
def _runs(old_keep, new_keep):
    """Where the moved entries' index pairs break: ``starts`` (r + 1,) such that within each
    ``starts[q]:starts[q + 1]`` both ``old_keep`` and ``new_keep`` count up by one."""
    m = len(old_keep)
    starts = np.empty(m + 1, np.intp)
    r = 0
    for a in range(m):
        if a == 0 or old_keep[a] != old_keep[a - 1] + 1 or new_keep[a] != new_keep[a - 1] + 1:
            starts[r] = a
            r += 1
    starts[r] = m
    return starts[:r + 1]


@compiled_kernel(_runs)
def _rebuild_kernel(P, old_keep, new_keep, R, new_conv, B, n_new):
    """The covariance after features leave or change kind: entries that only move
    (``P[old_keep][:, old_keep]`` to ``new_keep``), converted rows ``R`` (D, n_old) placed at
    ``new_conv`` (D,) against the moved columns and as their transposes, and the converted
    features' joint block ``B`` (D, D), symmetric. Returns the new (n_new, n_new) array."""
    out = np.empty((n_new, n_new))
    runs = _runs(old_keep, new_keep)
    m = len(old_keep)
    # Each row's moved entries as a few contiguous copies (a feature's removal or change of kind
    # breaks a row into runs), which the compiler turns into block moves.
    for a in range(m):
        ia = old_keep[a]
        oa = new_keep[a]
        for q in range(len(runs) - 1):
            s0 = runs[q]
            L = runs[q + 1] - s0
            ob = new_keep[s0]
            ib = old_keep[s0]
            out[oa, ob:ob + L] = P[ia, ib:ib + L]
    for c in range(len(new_conv)):
        oc = new_conv[c]
        for b in range(m):
            v = R[c, old_keep[b]]
            out[oc, new_keep[b]] = v
            out[new_keep[b], oc] = v
        for e in range(len(new_conv)):
            out[oc, new_conv[e]] = B[c, e]
    return out


def check_mean(x: np.ndarray, where: str = "", describe=None) -> np.ndarray:
    """Raise :class:`SlamNumericalError` if the state vector has NaN/Inf; return it."""
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        what = describe(int(bad[0])) if describe else f"index {int(bad[0])}"
        raise SlamNumericalError(f"state mean x has NaN/Inf{_where(where)} at indices "
                                 f"{bad[:8].tolist()}{' ...' if bad.size > 8 else ''} ({what})")
    return x


def check_covariance(P: np.ndarray, where: str = "", psd_rel_tol: float = 1e-9, check_psd: bool = True,
                     describe=None, built_symmetric: bool = False) -> np.ndarray:
    """The symmetric-PSD guard: return ``(P + P^T) / 2`` after checking it (``P`` itself when it
    is already exactly symmetric).

    Raises :class:`SlamNumericalError` naming the problem if ``P`` is not square, has NaN/Inf,
    has a negative variance, or (``check_psd``) an eigenvalue below
    ``-psd_rel_tol * max(diag P)`` (tested by a Cholesky factorisation of ``P + tol I``).
    ``built_symmetric``: the caller assembled ``P`` exactly symmetric from parts it checked
    finite, so the O(n^2) scan for NaN/Inf and asymmetry is skipped (the variances are still
    checked).
    """
    describe = describe or (lambda i: f"index {i}")
    P = np.asarray(P, dtype=float)
    if P.ndim != 2 or P.shape[0] != P.shape[1]:
        raise SlamNumericalError(f"covariance P{_where(where)} must be square, got shape {P.shape}")
    if not (P.flags.c_contiguous and (built_symmetric or _symmetric_and_finite(P))):
        finite = np.isfinite(P)
        if not finite.all():
            i, j = np.argwhere(~finite)[0]
            raise SlamNumericalError(f"covariance P has NaN/Inf{_where(where)}, first at ({i}, {j}) "
                                     f"({describe(int(i))} / {describe(int(j))})")
        P = np.ascontiguousarray(0.5 * (P + P.T))
    d = np.diag(P)
    scale = float(d.max()) if d.size else 0.0
    tol = psd_rel_tol * max(scale, np.finfo(float).tiny)
    if d.size and d.min() < -tol:
        i = int(np.argmin(d))
        raise SlamNumericalError(f"covariance P has a negative variance P[{i},{i}] = {d[i]:.3g}"
                                 f"{_where(where)} ({describe(i)})")
    if check_psd and d.size:
        Pt = P.copy()
        Pt.flat[::len(Pt) + 1] += tol
        # LAPACK's Cholesky on the copy, in place (Pt is symmetric: its C buffer read as Fortran
        # order is the same matrix).
        _, info = scipy.linalg.lapack.dpotrf(Pt.T, lower=1, overwrite_a=1, clean=0)
        if info < 0:
            raise ValueError(f"dpotrf: illegal argument {-info}")
        if info > 0:
            lam = np.linalg.eigvalsh(P)
            raise SlamNumericalError(
                f"covariance P is not positive semi-definite{_where(where)}: smallest eigenvalue "
                f"{lam[0]:.3g} < -{tol:.3g} (psd_rel_tol {psd_rel_tol:g} x max variance {scale:.3g})")
    return P


# ---------------------------------------------------------------------------------------------
# The container
# ---------------------------------------------------------------------------------------------

@dataclass
class State:
    """Mean ``x`` (n,), covariance ``P`` (n, n), and the layout: ``cam_dim`` (13, 19 or 20), each
    feature's ``kinds`` (N,) and ``anchors`` (N, 3, 3); ``starts`` (N,) is derived.

    The arrays are owned (copied on construction); the filter's steps update ``P`` in place or
    replace it, never resize it in place.
    """

    x: np.ndarray
    P: np.ndarray
    cam_dim: int = CAMERA_DIM
    kinds: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    anchors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    #: Where the camera block stands on the IMU's clock, s after its frame's time: the clock
    #: offset it was last propagated with (a new block: its offset's mean), so measurements see
    #: ``t_d - t_ref`` of motion.
    t_ref: float | None = None

    def __post_init__(self):
        self.cam_dim = check_camera_dim(self.cam_dim)
        self.x = np.array(self.x, dtype=float).reshape(-1)
        self.P = np.ascontiguousarray(np.array(self.P, dtype=float))
        self.kinds = np.array(self.kinds, dtype=np.intp).reshape(-1)
        if len(self.anchors) == 0 and len(self.kinds):
            self.anchors = np.tile(np.eye(3), (len(self.kinds), 1, 1))
        self.anchors = np.ascontiguousarray(np.array(self.anchors, dtype=float).reshape(-1, 3, 3))
        if len(self.anchors) != len(self.kinds):
            raise ValueError(f"{len(self.kinds)} feature kinds but {len(self.anchors)} anchors")
        if np.any((self.kinds < 0) | (self.kinds >= len(FEATURE_DIMS))):
            raise ValueError(f"unknown feature kinds {sorted(set(self.kinds.tolist()))}")
        n = state_size(self.cam_dim, self.kinds)
        if len(self.x) != n:
            raise ValueError(f"a state with a {self.cam_dim}-number camera block and features of kinds "
                             f"{self.kinds.tolist()} has {n} numbers, got {len(self.x)}")
        if self.P.shape != (n, n):
            raise ValueError(f"P must have shape ({n}, {n}), got {self.P.shape}")
        self.starts = feature_starts(self.cam_dim, self.kinds)
        self.t_ref = self.t_d if self.t_ref is None else float(self.t_ref)
        self.guard("construction")

    @classmethod
    def from_camera(cls, x_v, P_vv) -> "State":
        """A state with no features: camera block (13, 19 or 20,) and its covariance."""
        x_v = np.asarray(x_v, dtype=float).reshape(-1)
        return cls(x_v, P_vv, cam_dim=len(x_v))

    def copy(self) -> "State":
        return State(self.x.copy(), self.P.copy(), self.cam_dim, self.kinds.copy(), self.anchors.copy(), self.t_ref)

    # -- views --
    @property
    def n(self) -> int:
        return len(self.x)

    @property
    def n_features(self) -> int:
        return len(self.kinds)

    @property
    def has_biases(self) -> bool:
        return self.cam_dim >= CAMERA_DIM_BIASED

    @property
    def has_time_offset(self) -> bool:
        return self.cam_dim >= CAMERA_DIM_TIMED

    @property
    def has_scale(self) -> bool:
        return self.cam_dim == CAMERA_DIM_SCALED

    @property
    def gravity(self) -> np.ndarray | None:
        """Gravity in the map's frame (3,) m/s^2 where the block has it (a natural start's), else None."""
        return self.x[G_SLICE].copy() if self.has_scale else None

    @property
    def k(self) -> float:
        """The map's units per metre (1 without its state: a metric map)."""
        return float(self.x[SCALE_INDEX]) if self.has_scale else 1.0

    @property
    def t_d(self) -> float:
        """The IMU's clock offset, s (0 without its state)."""
        return float(self.x[TD_INDEX]) if self.has_time_offset else 0.0

    @property
    def x_v(self) -> np.ndarray:
        """The camera block (a view)."""
        return self.x[:self.cam_dim]

    @property
    def r(self) -> np.ndarray:
        return self.x[R_SLICE]

    @property
    def q(self) -> np.ndarray:
        return self.x[Q_SLICE]

    @property
    def v(self) -> np.ndarray:
        return self.x[V_SLICE]

    @property
    def w(self) -> np.ndarray:
        return self.x[W_SLICE]

    @property
    def b_g(self) -> np.ndarray:
        """Gyro bias (3,) rad/s, zero without bias states."""
        return self.x[BG_SLICE] if self.has_biases else np.zeros(3)

    @property
    def b_a(self) -> np.ndarray:
        """Accelerometer bias (3,) m/s^2, zero without bias states."""
        return self.x[BA_SLICE] if self.has_biases else np.zeros(3)

    def feature_slice(self, k: int) -> slice:
        k = self._check_k(k)
        s = int(self.starts[k])
        return slice(s, s + int(FEATURE_DIMS[self.kinds[k]]))

    def feature(self, k: int) -> np.ndarray:
        """The parameters of feature ``k`` (a view; their meaning depends on its kind)."""
        return self.x[self.feature_slice(k)]

    def _check_k(self, k) -> int:
        if not (0 <= int(k) < self.n_features):
            raise IndexError(f"feature {k} does not exist (the map has {self.n_features})")
        return int(k)

    def describe(self, i: int) -> str:
        """What state index ``i`` is, for error messages."""
        for name, sl in CAMERA_NAMES:
            if sl.start <= i < min(sl.stop, self.cam_dim):
                return f"camera {name}"
        k = int(np.searchsorted(self.starts, i, side="right")) - 1
        return f"feature {k} ({FEATURE_NAMES[self.kinds[k]]})" if k >= 0 else f"index {i}"

    # -- map management --
    def add_feature(self, kind: int, y, P_yy, P_yx, anchor=None, check_psd: bool = False) -> int:
        """Append a feature of ``kind`` and return its index ``k``.

        y : (d,) its parameters; P_yy : (d, d) their covariance; P_yx : (d, n) the
        cross-covariance with the current state; anchor : (3, 3) its constant rotation
        (identity by default). The grown covariance is checked by the guard; on failure nothing
        changes.
        """
        return self.add_features([kind], y, P_yy, P_yx, None if anchor is None else [anchor], check_psd)[0]

    def add_features(self, kinds, y, P_yy, P_yx, anchors=None, check_psd: bool = False) -> list[int]:
        """Append features of ``kinds`` (m,) at once (one rebuild of ``P``) and return their
        indices. y : (d,) their parameters concatenated; P_yy : (d, d) their joint covariance;
        P_yx : (d, n) the cross-covariance with the current state; anchors : (m, 3, 3) or None
        (identities). Checked by the guard; on failure nothing changes."""
        kinds = [int(k) for k in kinds]
        dims = [int(FEATURE_DIMS[k]) for k in kinds]
        d = sum(dims)
        n = self.n
        y = np.asarray(y, dtype=float).reshape(-1)
        P_yy = np.asarray(P_yy, dtype=float)
        P_yx = np.asarray(P_yx, dtype=float)
        names = " + ".join(FEATURE_NAMES[k] for k in kinds)
        if y.shape != (d,) or P_yy.shape != (d, d) or P_yx.shape != (d, n):
            what = f"a {names} feature needs" if len(kinds) == 1 else f"new features ({names}) need"
            raise ValueError(f"{what} y ({d},), P_yy ({d}, {d}), P_yx ({d}, {n}); "
                             f"got {y.shape}, {P_yy.shape}, {P_yx.shape}")
        first = self.n_features
        offsets = n + np.concatenate([[0], np.cumsum(dims)[:-1]]) if dims else np.zeros(0)

        def new_name(i: int) -> str:
            j = int(np.searchsorted(offsets, i, side="right")) - 1
            return f"feature {first + j} ({FEATURE_NAMES[kinds[j]]}), the new one"

        if not np.isfinite(y).all():
            bad = (n + np.flatnonzero(~np.isfinite(y))).tolist()
            raise SlamNumericalError(f"state mean x has NaN/Inf after add_feature at indices {bad} "
                                     f"({new_name(bad[0])})")
        P_new = np.empty((n + d, n + d))
        P_new[:n, :n] = self.P
        P_new[n:, :n] = P_yx
        P_new[:n, n:] = P_yx.T
        P_new[n:, n:] = 0.5 * (P_yy + P_yy.T)
        # The old P passed the guard; the new blocks are written symmetric, so only their
        # finiteness needs a look unless the guard must name a bad entry.
        parts_finite = bool(np.isfinite(P_yx).all() and np.isfinite(P_yy).all())
        P_new = check_covariance(P_new, "add_feature", check_psd=check_psd,
                                 describe=lambda i: self.describe(i) if i < n else new_name(i),
                                 built_symmetric=parts_finite)
        A = np.tile(np.eye(3), (len(kinds), 1, 1)) if anchors is None else np.asarray(anchors, float).reshape(-1, 3, 3)
        self.x, self.P = np.concatenate([self.x, y]), P_new
        self.kinds = np.concatenate([self.kinds, np.array(kinds, np.intp)])
        self.anchors = np.concatenate([self.anchors, A])
        self.starts = feature_starts(self.cam_dim, self.kinds)
        return list(range(first, self.n_features))

    def remove_features(self, ks) -> None:
        """Delete the features ``ks``: their entries of ``x`` and rows and columns of ``P``. Later
        features shift down."""
        self.edit_features(remove=ks)

    def remove_feature(self, k: int) -> None:
        self.remove_features([k])

    def convert_feature(self, k: int, kind: int, y_new, J) -> None:
        """Replace feature ``k`` by a feature of another ``kind`` with parameters ``y_new`` =
        f(y) and ``J`` = df/dy (d_new, d_old): ``P`` is transformed to first order (the feature's
        rows become ``J P_y,:``, its block ``J P_yy J^T``). Its place in the order is kept."""
        self.convert_features([k], kind, [y_new], [J])

    def convert_features(self, ks, kind: int, ys_new, Js) -> None:
        """:meth:`convert_feature` for several features at once (one rebuild of ``P``):
        ``P <- T P T^T`` with ``T`` the identity except each converted feature's ``J``."""
        self.edit_features(convert=ks, kind=kind, ys_new=ys_new, Js=Js)

    def edit_features(self, remove=(), convert=(), kind: int | None = None, ys_new=(), Js=()) -> None:
        """Delete the features ``remove`` and convert the features ``convert`` to ``kind`` (as
        :meth:`convert_features`) in one rebuild of ``P``; later features shift down. Raises
        :class:`SlamNumericalError` (nothing changed) if a conversion is not finite."""
        gone = sorted({self._check_k(k) for k in np.atleast_1d(np.asarray(remove, dtype=np.intp))})
        ks = [self._check_k(k) for k in convert]
        if set(ks) & set(gone):
            raise ValueError(f"edit_features: features {sorted(set(ks) & set(gone))} both removed and converted")
        if not gone and not ks:
            return
        kinds = self.kinds.copy()
        conv = {}
        if ks:
            d_new = int(FEATURE_DIMS[kind])
            kinds[ks] = kind
            for k, y, J in zip(ks, ys_new, Js):
                sl = self.feature_slice(k)
                J = np.asarray(J, float)
                y = np.asarray(y, float).reshape(-1)
                if J.shape != (d_new, sl.stop - sl.start) or y.shape != (d_new,):
                    raise ValueError(f"convert_features: J must be ({d_new}, {sl.stop - sl.start}) and y_new ({d_new},)")
                if not (np.isfinite(y).all() and np.isfinite(J).all()):
                    raise SlamNumericalError(f"convert_features: feature {k}'s conversion is not finite")
                conv[k] = (sl, y, J)
        kept = np.setdiff1d(np.arange(self.n_features), gone)
        kinds = kinds[kept]
        starts_new = feature_starts(self.cam_dim, kinds)
        n_new = state_size(self.cam_dim, kinds)
        new_index = np.full(self.n_features, -1, np.intp)      # old feature index -> new
        new_index[kept] = np.arange(len(kept))
        # The entries that only move: old index -> new index.
        moved = np.ones(self.n, bool)
        for k in gone:
            moved[self.feature_slice(k)] = False
        for sl, _, _ in conv.values():
            moved[sl] = False
        new_slices = {k: slice(int(starts_new[new_index[k]]), int(starts_new[new_index[k]]) + len(y))
                      for k, (_, y, _) in conv.items()}
        old_keep = np.flatnonzero(moved)
        new_keep = np.ones(n_new, bool)
        for ns in new_slices.values():
            new_keep[ns] = False
        new_keep = np.flatnonzero(new_keep)
        if conv:
            # P <- T P T^T: the converted features' rows R = J P_y,: (D, n), their joint block
            # R_k,sl_j J_j^T, and every other entry moved.
            R = np.concatenate([J @ self.P[sl] for sl, _, J in conv.values()])
            offs = np.cumsum([0] + [J.shape[0] for _, _, J in conv.values()])
            B = np.concatenate([np.concatenate([R[o:o2, sl] @ J.T for sl, _, J in conv.values()], axis=1)
                                for o, o2 in zip(offs[:-1], offs[1:])])
            B = 0.5 * (B + B.T)
            new_conv = np.concatenate([np.arange(ns.start, ns.stop) for ns in new_slices.values()])
        else:
            R, B, new_conv = np.zeros((0, self.n)), np.zeros((0, 0)), np.zeros(0, np.intp)
        P = _rebuild_kernel(self.P, old_keep, new_keep, R, new_conv, B, n_new)
        x = np.empty(n_new)
        x[new_keep] = self.x[old_keep]
        for k, (_, y, _) in conv.items():
            x[new_slices[k]] = y
        self.x, self.P, self.kinds, self.starts = x, P, kinds, starts_new
        self.anchors = self.anchors[kept]

    # -- trials and the camera's restart --
    def snapshot(self, camera_only: bool = False) -> "StateSnapshot":
        """What :meth:`restore` puts back: the mean and the whole covariance, or (``camera_only``)
        the mean and the camera block's rows of ``P``, all that a prediction or a growth of the
        camera's noise changes. The layout must not change in between (no feature added,
        removed or converted)."""
        if camera_only:
            return StateSnapshot(self.x.copy(), self.P[:self.cam_dim].copy(), True, self.n)
        return StateSnapshot(self.x.copy(), self.P.copy(), False, self.n)

    def restore(self, snap: "StateSnapshot") -> None:
        """Put back a :meth:`snapshot`: the mean, and the covariance (the camera rows, written
        with their transposes as the columns: ``P`` stays exactly symmetric)."""
        if snap.n != self.n:
            raise ValueError(f"restore: the snapshot has {snap.n} numbers, the state {self.n}; a trial must not "
                             "add, remove or convert features")
        self.x = snap.x
        if snap.camera_only:
            self.P[:self.cam_dim] = snap.P
            self.P[:, :self.cam_dim] = snap.P.T
        else:
            self.P = snap.P

    def add_camera_noise(self, Q_vv: np.ndarray) -> None:
        """``P_vv <- P_vv + (Q + Q^T) / 2``: more process noise in the camera block (cd, cd)."""
        cd = self.cam_dim
        self.P[:cd, :cd] += 0.5 * (Q_vv + Q_vv.T)

    def restart_camera(self, x_v, P_vv) -> None:
        """The camera's pose and motion (the first 13 numbers) replaced by ``x_v`` with covariance
        ``P_vv`` (at least 13 of each), uncorrelated with the rest; the bias and clock states
        and their correlations with the map are kept."""
        d = CAMERA_DIM
        x = self.x.copy()
        x[:d] = x_v[:d]
        P = self.P.copy()
        P[:d, :] = 0.0
        P[:, :d] = 0.0
        P[:d, :d] = P_vv[:d, :d]
        if self.cam_dim > d:
            P[d:self.cam_dim, d:self.cam_dim] = self.P[d:self.cam_dim, d:self.cam_dim]
        self.x, self.P = x, P

    def check(self, where: str, psd_rel_tol: float = 1e-9) -> None:
        """The full covariance guard (positive semi-definiteness included), ``P`` symmetrised."""
        self.P = check_covariance(self.P, where, psd_rel_tol, True, self.describe)

    def guard(self, where: str = "", psd_rel_tol: float = 1e-9, check_psd: bool = True) -> None:
        """Run :func:`check_mean` and :func:`check_covariance` (symmetrising ``P``)."""
        check_mean(self.x, where, self.describe)
        self.P = check_covariance(self.P, where, psd_rel_tol, check_psd, self.describe)


@dataclass(frozen=True)
class StateSnapshot:
    """A state's mean and covariance (or the camera block's rows of it) kept for a trial that
    may be rolled back (:meth:`State.snapshot`, :meth:`State.restore`)."""

    x: np.ndarray
    P: np.ndarray
    camera_only: bool
    n: int
