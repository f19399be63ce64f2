"""Camera sources: a live device read in its own thread keeping only the newest frame, and
replays (a video file, an image pattern, a sequence folder, followed as it grows).

Every source gives :class:`CameraFrame` s through ``read(timeout_s)``: the next frame newer than
the last one returned, RGB uint8, stamped with the driver's time where it is trustworthy (a
sequence folder's rgb.txt, a video file's position), else ``time.monotonic()`` at capture.
A source that stops delivering raises :class:`CameraStalled` (a one-line DriverError); a replay
that has run out raises :class:`runtime.robot.SessionEnded`.

``rig.toml [camera] source``: an integer (a V4L2 device index), a device path (``/dev/video0``),
a video file, an image pattern (``frames/%06d.png`` or ``frames/*.png``), or a sequence folder
with an rgb.txt (the hardware-in-the-loop camera: its rgb.txt grows as frames are rendered, and
a final ``# end`` line ends the stream).
"""

from __future__ import annotations

import glob
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..robot import SessionEnded
from . import DriverError

END_OF_STREAM = "# end"


class CameraStalled(DriverError):
    """The camera delivered no new frame in time."""


@dataclass(frozen=True)
class CameraFrame:
    t: float
    image: np.ndarray
    index: int


def _rgb(bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB) if bgr.ndim == 2 else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class LiveCapture:
    """OpenCV VideoCapture (V4L2 for devices) in a thread that keeps only the newest frame, so a
    slow consumer always gets the present, never a queue of the past."""

    def __init__(self, capture, name: str, clock=time.monotonic):
        self.cap = capture
        self.name = name
        self.clock = clock
        self._cond = threading.Condition()
        self._latest: CameraFrame | None = None
        self._returned = -1
        self._error: str | None = None
        self._stop = threading.Event()
        self.grabbed = 0
        self._thread = threading.Thread(target=self._run, name="camera", daemon=True)
        self._thread.start()

    @classmethod
    def open(cls, device) -> "LiveCapture":
        cap = cv2.VideoCapture(device, cv2.CAP_V4L2) if isinstance(device, int) or str(device).startswith("/dev/") \
            else cv2.VideoCapture(device)
        if not cap.isOpened():
            raise DriverError(f"camera {device!r}: cannot open it; check the device (v4l2-ctl --list-devices) and "
                              f"rig.toml [camera] source")
        return cls(cap, f"camera {device!r}")

    def _run(self) -> None:
        while not self._stop.is_set():
            ok, bgr = self.cap.read()
            t = self.clock()
            if not ok or bgr is None:
                with self._cond:
                    self._error = f"{self.name}: stopped delivering frames"
                    self._cond.notify_all()
                return
            with self._cond:
                self.grabbed += 1
                self._latest = CameraFrame(t, _rgb(bgr), self.grabbed - 1)
                self._cond.notify_all()

    def read(self, timeout_s: float = 1.0) -> CameraFrame:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._latest is None or self._latest.index <= self._returned:
                if self._error is not None:
                    raise CameraStalled(self._error + "; check the cable, then start again")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise CameraStalled(f"{self.name}: no new frame within {timeout_s:g} s; check the cable and "
                                        f"the device, then start again")
                self._cond.wait(left)
            f = self._latest
            self._returned = f.index
            return f

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.cap.release()


class ReplaySource:
    """A video file or an image pattern, read in order (no frame dropped), for replays and tests.
    Times: a video's own position (POS_MSEC), or index / fps for a pattern."""

    def __init__(self, source: str, fps: float = 30.0):
        self.name = f"camera {source!r}"
        self.fps = float(fps)
        self._k = 0
        self.cap = None
        if "%" in source or "*" in source or "?" in source:
            self.paths = sorted(glob.glob(source.replace("%06d", "*").replace("%d", "*")
                                          if "%" in source else source))
            if not self.paths:
                raise DriverError(f"camera pattern {source!r}: no image matches; check the path")
        else:
            self.paths = None
            self.cap = cv2.VideoCapture(source)
            if not self.cap.isOpened():
                raise DriverError(f"camera {source!r}: not a video OpenCV can open; check the file")

    def read(self, timeout_s: float = 1.0) -> CameraFrame:
        k = self._k
        if self.paths is not None:
            if k >= len(self.paths):
                raise SessionEnded(f"{self.name}: the last image was shown")
            bgr = cv2.imread(self.paths[k], cv2.IMREAD_COLOR)
            if bgr is None:
                raise CameraStalled(f"{self.name}: {self.paths[k]} is not a readable image")
            t = k / self.fps
        else:
            ok, bgr = self.cap.read()
            if not ok:
                raise SessionEnded(f"{self.name}: the video ended")
            t = self.cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            if k and t <= 0:
                t = k / self.fps              # containers without time stamps
        self._k += 1
        return CameraFrame(t, _rgb(bgr), k)

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()


class FolderSource:
    """A sequence folder whose rgb.txt grows as frames are written (``timestamp path`` lines);
    each frame is stamped with its rgb.txt time. A final ``# end`` line ends the stream."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.name = f"camera folder {self.folder}"
        self._fh = None
        self._pending = ""
        self._k = 0

    def _open(self):
        if self._fh is None and (self.folder / "rgb.txt").exists():
            self._fh = open(self.folder / "rgb.txt", encoding="utf-8")
        return self._fh

    def read(self, timeout_s: float = 1.0) -> CameraFrame:
        deadline = time.monotonic() + timeout_s
        while True:
            fh = self._open()
            if fh is not None:
                chunk = fh.readline()
                if chunk:
                    self._pending += chunk
                    if not self._pending.endswith("\n"):
                        continue
                    line, self._pending = self._pending.strip(), ""
                    if line == END_OF_STREAM:
                        raise SessionEnded(f"{self.name}: the stream ended")
                    if not line or line.startswith("#"):
                        continue
                    t_text, rel = line.split(maxsplit=1)
                    path = self.folder / rel
                    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
                    if bgr is None:
                        raise CameraStalled(f"{self.name}: {path} is listed but not readable")
                    self._k += 1
                    return CameraFrame(float(t_text), _rgb(bgr), self._k - 1)
            if time.monotonic() > deadline:
                raise CameraStalled(f"{self.name}: no new frame within {timeout_s:g} s; is the simulator running?")
            time.sleep(0.0005)

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()


def open_camera(source, base_dir: Path | None = None, fps: float = 30.0):
    """The source rig.toml names (see the module's docstring)."""
    if isinstance(source, int) and not isinstance(source, bool):
        return LiveCapture.open(source)
    if not isinstance(source, str) or not source:
        raise DriverError(f"rig.toml [camera] source = {source!r}: give a V4L2 device index, a device path, a video "
                          f"file, an image pattern or a sequence folder")
    if source.startswith("/dev/"):
        return LiveCapture.open(source)
    p = Path(source)
    if base_dir is not None and not p.is_absolute():
        p = base_dir / p
    if p.is_dir():
        return FolderSource(p)
    if any(c in source for c in "%*?"):
        return ReplaySource(str(p), fps)
    if not p.exists():
        raise DriverError(f"rig.toml [camera] source {str(p)!r}: no such file, device or folder")
    return ReplaySource(str(p), fps)
