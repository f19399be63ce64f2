"""The station, put together: the live loop, the 3D view (viser, on loopback), the gate with the
JSON API and the pages on the public port, and the recording when it stops.

    st = Station(robot, start_target, out="session", truth=twin).open()
    print(st.url)            # http://127.0.0.1:8080/?token=...
    st.wait()                # until --seconds, the robot's session ends, or st.stop()
    st.close()               # writes the recording
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import secrets
import socket
import time
from pathlib import Path

from ...gaze import ControllerSettings
from . import record
from .live import LiveStation
from .server import StationServer
from .view3d import View3D

MIN_TOKEN = 8


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(socket.gethostbyname(host)).is_loopback
    except (OSError, ValueError):
        return False


def resolve_token(token: str | None) -> tuple[str, bool]:
    """The token (given, or a new random one) and whether it was generated. Every station has
    one, loopback or not: the page, its websocket and the API all need it."""
    if token is None:
        return secrets.token_urlsafe(18), True
    if len(token) < MIN_TOKEN or any(c.isspace() for c in token):
        raise ValueError(f"--token must be at least {MIN_TOKEN} characters without spaces; or leave it out and "
                         "the station makes one")
    return token, False


class Station:
    """robot, start_target : as for :class:`LiveStation`. host, port : the public address
    (loopback by default; port 0: any free one). token : None makes one. out : the recording's
    folder (None: no recording). truth : the twin, for groundtruth.txt. seconds : robot time.
    on_finish : run in the loop's thread as it ends (see :class:`LiveStation`)."""

    def __init__(self, robot, start_target, host: str = "127.0.0.1", port: int = 8080, token: str | None = None,
                 out: str | Path | None = None, truth=None, seconds: float | None = None,
                 settings: ControllerSettings = ControllerSettings(), pace: bool = True, view_rate_hz: float = 2.0,
                 notes: dict | None = None, on_finish=None):
        self.token, self.token_generated = resolve_token(token)
        self.host = host
        self.loopback = is_loopback(host)
        # Locked from here to close(): a second station into this folder is refused.
        self._folder = record.claim_out(out) if out is not None else None
        self.out = self._folder.path if self._folder is not None else None
        self.notes = dict(notes or {})
        self.live = LiveStation(robot, start_target, settings=settings, truth=truth, seconds=seconds, pace=pace,
                                on_finish=on_finish)
        self._port = port
        self._view_rate = view_rate_hz
        self.view: View3D | None = None
        self.http: StationServer | None = None
        self.written: list[str] = []

    def open(self) -> "Station":
        """Start serving (the public port first, so that a busy one fails before anything runs),
        then the loop."""
        try:
            self.http = StationServer(self.host, self._port, self.token, self.live, None)
        except OSError as e:
            raise ValueError(f"cannot listen on {self.host}:{self._port} ({e.strerror}); choose another --port "
                             "or --host") from None
        self.view = View3D(self.live, port=self.http.port + 1 if self._port else 0, rate_hz=self._view_rate)
        self.http.viser_port = self.view.port
        self.http.gate_secret = self.view.gate_secret
        if self.out is not None:
            record.begin(self.out, {"address": self.public_url, **self.notes})
        self.http.start()
        self.live.start()
        self.view.start()
        return self

    @property
    def port(self) -> int:
        return self.http.port

    @property
    def public_url(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        return f"http://{host}:{self.port}/"

    @property
    def url(self) -> str:
        """The page's address with the token (what the operator opens)."""
        return f"{self.public_url}?token={self.token}"

    def wait(self, timeout: float | None = None) -> bool:
        """Until the loop ends (or ``timeout`` s); True if it ended."""
        return self.live.finished.wait(timeout)

    def wait_started(self, timeout: float = 120.0) -> None:
        t0 = time.time()
        while not self.live.started.is_set():
            if self.live.finished.is_set():
                raise RuntimeError(f"the station's loop ended before starting: {self.live.run.ended}")
            if time.time() - t0 > timeout:
                raise TimeoutError("the station's loop did not start")
            time.sleep(0.05)

    def stop(self, reason: str = "stopped") -> None:
        self.live.stop(reason)

    def close(self) -> list[str]:
        """Stop the loop, the servers, and write the recording (if an out folder was given)."""
        self.live.stop("stopped")
        self.live.join(30.0)
        if self.view is not None:
            with contextlib.redirect_stdout(io.StringIO()):
                self.view.close()
        if self.http is not None:
            self.http.close()
        if self.out is not None and self.live.started.is_set():
            self.written = record.finish(self.out, self.live.run, self.notes)
        if self._folder is not None:
            self._folder.close(complete=self.live.started.is_set())
        return self.written

    def __enter__(self) -> "Station":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()


def serve(station: Station, on_ready=None, handle_signals: bool = True) -> dict:
    """Open the station, call ``on_ready(station)``, run until its loop ends (``seconds``, the
    robot's session, or SIGINT / SIGTERM when ``handle_signals``), then close it (writing the
    recording). Returns a summary."""
    import signal
    import threading

    old = {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, lambda signum, _f: station.stop(f"stopped by {signal.Signals(signum).name}"))
    try:
        station.open()
        if on_ready is not None:
            on_ready(station)
        while not station.wait(0.2):
            pass
    finally:
        written = station.close()
        for sig, h in old.items():
            signal.signal(sig, h)
    run = station.live.run
    if run.fault is not None:
        raise run.fault
    return {"ended": run.ended, "frames": len(run.times), "events": len(run.events),
            "accepted": sum(e.accepted for e in run.events), "labels": len(run.labels), "written": written}
