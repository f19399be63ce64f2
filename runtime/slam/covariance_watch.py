"""The covariance's full positive-semi-definiteness check, run beside the tracker.

The check is a Cholesky factorisation of ``P`` (n x n, n ~ 900 on a 150-feature map of inverse
depths: several milliseconds). Made on the tracking thread every few frames, it was a periodic
stall; here the cheap O(n^2) part (NaN/Inf, symmetry, negative variances) stays on the frame
that asks for it, and the factorisation of a copy runs on a worker thread (LAPACK releases the
GIL). A failure is raised on the tracking thread at the next frame that looks, naming the frame
it was found at; nothing the filter computes depends on the check's outcome.
"""

from __future__ import annotations

from concurrent.futures import Future

from ..background import worker
from .state import State, check_covariance


class CovarianceWatch:
    """One track's background check (:meth:`submit` every few frames, :meth:`raise_if_failed`
    every frame, :meth:`wait` at the end)."""

    def __init__(self) -> None:
        self._pending: Future | None = None

    def submit(self, state: State, where: str, psd_rel_tol: float) -> None:
        """Check ``state.P`` now for NaN/Inf and negative variances (symmetrising it), and start
        the factorisation of a copy; the previous one is collected first (it had frames to run)."""
        state.P = check_covariance(state.P, where, psd_rel_tol, False, state.describe)
        self.wait()
        self._pending = worker("slam-psd").submit(check_covariance, state.P.copy(), where, psd_rel_tol, True, state.describe)

    def raise_if_failed(self) -> None:
        """Raise the check's SlamNumericalError if a finished one failed."""
        if self._pending is not None and self._pending.done():
            f, self._pending = self._pending, None
            f.result()

    def wait(self) -> None:
        """Wait for the check in flight, raising its error."""
        if self._pending is not None:
            f, self._pending = self._pending, None
            f.result()
