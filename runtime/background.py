"""Slow work beside a control or tracking loop, on worker threads at the lowest CPU priority.

A loop that must keep its period hands a snapshot of its inputs to a worker and takes the
result later. :class:`DelayedResult` takes it a fixed loop time after the snapshot: on a robot
whose clock waits for the loop (the twin) it waits for the work then, so a run does not depend on
the threads' timing; on hardware it takes the result at the first period after it is ready.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable

_POOLS: dict[str, ThreadPoolExecutor] = {}
_LOCK = threading.Lock()


def _lowest_priority() -> None:
    """The worker at the lowest CPU priority (Linux: a thread's own nice value): on one core it
    takes the time the loop leaves (waiting for the next image), not the loop's."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    except (AttributeError, OSError):
        pass


def worker(name: str) -> ThreadPoolExecutor:
    """The process's one low-priority worker thread called ``name`` (made on first use)."""
    with _LOCK:
        pool = _POOLS.get(name)
        if pool is None:
            pool = _POOLS[name] = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name,
                                                     initializer=_lowest_priority)
        return pool


class DelayedResult:
    """One job at a time on the worker ``name``: :meth:`submit` at loop time ``t`` with the
    inputs' snapshot (and a ``context`` kept beside it), :meth:`collect` every period; the result
    comes back ``delay_s`` of loop time after the submission, or later if not done and
    ``clock_waits`` is False (hardware: the loop never blocks on it)."""

    def __init__(self, name: str, delay_s: float, clock_waits: bool) -> None:
        self.name, self.delay_s, self.clock_waits = name, float(delay_s), bool(clock_waits)
        self._job: tuple[float, Future, Any] | None = None

    @property
    def busy(self) -> bool:
        return self._job is not None

    def submit(self, t: float, fn: Callable, *args, context: Any = None, **kwargs) -> None:
        if self._job is not None:
            raise RuntimeError(f"{self.name}: a job is in flight; collect it first")
        self._job = (float(t), worker(self.name).submit(fn, *args, **kwargs), context)

    def collect(self, t: float) -> tuple[Any, Any] | None:
        """``(result, context)`` once the job's delay has passed (and, without ``clock_waits``,
        the job is done), else None. The job's exception is raised here."""
        if self._job is None:
            return None
        t0, future, context = self._job
        if t - t0 < self.delay_s or not (self.clock_waits or future.done()):
            return None
        self._job = None
        return future.result(), context
