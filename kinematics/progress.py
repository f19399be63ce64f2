"""Progress that suits where it goes: a tqdm bar on a terminal, a plain line every few seconds
in a log file.

tqdm redraws its bar with carriage returns; written to a file (CI, ``wvr ... 2> log``) that is
hundreds of updates on one line. :func:`progress_bar` takes tqdm's arguments and returns a tqdm
bar when standard error is a terminal, and otherwise a :class:`PlainProgress` that prints
``desc: n/total unit (elapsed)`` at most every :data:`INTERVAL_S` seconds, and once at the end.
``progress_bar.write(text)`` prints a message without breaking a bar.

This lives in ``kinematics`` only because every package may import it (the import rule).
"""

from __future__ import annotations

import sys
import time
from typing import Iterable, Iterator

from tqdm import tqdm

#: Seconds between two plain progress lines.
INTERVAL_S = 5.0


class PlainProgress:
    """tqdm's interface as used here (iterate, ``update``, ``close``, a context manager), printing
    whole lines to ``file`` (standard error by default): at most one per ``interval_s``, and a
    last one when closed."""

    def __init__(self, iterable: Iterable | None = None, total: float | None = None, desc: str = "",
                 unit: str = "it", initial: float = 0, disable: bool = False, interval_s: float = INTERVAL_S,
                 file=None, clock=time.monotonic, **_ignored):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self.disable, self.interval_s = disable, interval_s
        self._file, self._clock = file, clock
        self._t0 = self._last = clock()
        self._closed = False

    def _line(self, done: bool = False) -> str:
        of = f"/{self.total:g}" if self.total is not None else ""
        elapsed = self._clock() - self._t0
        return (f"{self.desc + ': ' if self.desc else ''}{self.n:g}{of} {self.unit}"
                f"{' done' if done else ''} ({elapsed:.0f} s)")

    def _print(self, text: str) -> None:
        print(text, file=self._file or sys.stderr, flush=True)

    def update(self, n: float = 1) -> None:
        self.n += n
        now = self._clock()
        if not self.disable and now - self._last >= self.interval_s:
            self._last = now
            self._print(self._line())

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if not self.disable:
                self._print(self._line(done=True))

    def __iter__(self) -> Iterator:
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> "PlainProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _on_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):      # a closed or replaced stream
        return False


def progress_bar(iterable: Iterable | None = None, **kwargs):
    """A tqdm bar on a terminal, a :class:`PlainProgress` otherwise; tqdm's keyword arguments
    (total, desc, unit, initial, disable)."""
    if _on_terminal():
        return tqdm(iterable, **kwargs)
    return PlainProgress(iterable, **kwargs)


def _write(text: str) -> None:
    """Print a message: through tqdm on a terminal (the bar is redrawn below it), plainly otherwise."""
    if _on_terminal():
        tqdm.write(text)
    else:
        print(text, flush=True)


progress_bar.write = _write
