"""The station, put together: the live loop, the 3D view (viser, on loopback), the gate with the
JSON API and the pages on the public port, and the recording when it stops.

    st = Station(robot, start_target, out="session", truth=twin).open()
    print(st.url)            # http://127.0.0.1:8080/?token=...
    print(st.wearer_url)     # http://127.0.0.1:8080/wearer?token=... (reads the prompt only)
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
from ...session_log import SESSION_FILE, LoopRecorder
from .live import LiveStation
from .server import StationServer, wearer_token_for
from .view3d import View3D

MIN_TOKEN = 8


def _addresses(host: str) -> list:
    try:
        return [ipaddress.ip_address(ai[4][0].split("%")[0]) for ai in socket.getaddrinfo(host, None)]
    except (OSError, ValueError):
        return []


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) reaches this machine only."""
    found = _addresses(host)
    return bool(found) and all(a.is_loopback for a in found)


def is_everywhere(host: str) -> bool:
    """Whether ``host`` is the unspecified address (0.0.0.0, ::): every interface."""
    try:
        return ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return False


def address_lines(url: str, wearer_url: str, host: str, remote: tuple[str, str] | None = None) -> list[str]:
    """What the station prints once it listens: the operator's address (with the token), the
    wearer's, where it listens when that is beyond loopback, and one warning that the token
    then travels in plain HTTP. ``remote``: the operator's and the wearer's addresses by this
    machine's name when ``host`` is every interface (None otherwise)."""
    lines = [f"station: open {url}", f"station: the wearer's page (it reads the prompt, nothing more): {wearer_url}"]
    if remote is not None:
        lines.append(f"station: listening on all interfaces ({host}); from another machine: {remote[0]} "
                     f"(the wearer's page: {remote[1]})")
    if not is_loopback(host):
        lines.append("station: warning: beyond loopback the token travels in plain HTTP, readable on the network's "
                     "path; serve only on a network you trust, or keep --host 127.0.0.1 and reach it through ssh -L")
    return lines


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
                 notes: dict | None = None, on_finish=None, session_log: bool = True):
        self.token, self.token_generated = resolve_token(token)
        self.wearer_token = wearer_token_for(self.token)
        self.host = host
        self.loopback = is_loopback(host)
        # Locked from here to close(): a second station into this folder is refused.
        self._folder = record.claim_out(out) if out is not None else None
        self.out = self._folder.path if self._folder is not None else None
        self.notes = dict(notes or {})
        self.live = LiveStation(robot, start_target, settings=settings, truth=truth, seconds=seconds, pace=pace,
                                on_finish=on_finish)
        if self.out is not None and session_log:
            self.live.recorder = LoopRecorder(self.out / SESSION_FILE)
        self._port = port
        self._view_rate = view_rate_hz
        self.view: View3D | None = None
        self.http: StationServer | None = None
        self.written: list[str] = []
        self._begun = False

    def open(self) -> "Station":
        """Start serving (the public port first, so that a busy one fails before anything runs),
        then the loop. If any part fails to start, what did start is closed (and the recording,
        if begun, marked failed) before the error goes on."""
        try:
            self.http = StationServer(self.host, self._port, self.token, self.live, None,
                                      wearer_token=self.wearer_token)
        except OSError as e:
            raise ValueError(f"cannot listen on {self.host}:{self._port} ({e.strerror or e}); choose another "
                             "--port or --host") from None
        try:
            self.view = View3D(self.live, port=self.http.port + 1 if self._port else 0, rate_hz=self._view_rate)
            self.http.viser_port = self.view.port
            self.http.gate_secret = self.view.gate_secret
            if self.out is not None:
                record.begin(self.out, {"address": self.public_url, **self.notes})
                self._begun = True
            self.http.start()
            self.live.start()
            self.view.start()
        except BaseException as e:
            self.live.stop(f"failed to start: {e}")
            self.close()
            raise
        return self

    @property
    def port(self) -> int:
        return self.http.port

    def _base(self, host: str) -> str:
        return f"http://{host if ':' not in host else f'[{host}]'}:{self.port}/"

    @property
    def public_url(self) -> str:
        """The station's address on this machine: ``--host``, or loopback when that is every
        interface (0.0.0.0 is no address a browser can open)."""
        if is_everywhere(self.host):
            return self._base("::1" if ":" in self.host else "127.0.0.1")
        return self._base(self.host)

    @property
    def remote_urls(self) -> tuple[str, str] | None:
        """The operator's and the wearer's addresses (with their tokens) by this machine's name,
        when serving on every interface; None otherwise."""
        if not is_everywhere(self.host):
            return None
        base = self._base(socket.gethostname())
        return f"{base}?token={self.token}", f"{base}wearer?token={self.wearer_token}"

    @property
    def url(self) -> str:
        """The page's address with the token (what the operator opens)."""
        return f"{self.public_url}?token={self.token}"

    @property
    def wearer_url(self) -> str:
        """The wearer's page with the wearer's token (it reads the prompt only)."""
        return f"{self.public_url}wearer?token={self.wearer_token}"

    def address_lines(self) -> list[str]:
        """What to print once it listens (see :func:`address_lines`)."""
        return address_lines(self.url, self.wearer_url, self.host, self.remote_urls)

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
        """Stop the loop, the servers, and write the recording (if an out folder was given).
        A second call does nothing."""
        if getattr(self, "_closed", False):
            return self.written
        self._closed = True
        self.live.stop("stopped")
        self.live.join(30.0)
        if self.view is not None:
            with contextlib.redirect_stdout(io.StringIO()):
                self.view.close()
        if self.http is not None:
            self.http.close()
        if self.out is not None and self.live.started.is_set():
            mcap = self.live.recorder is not None and \
                self.live.recorder.close(self.live.run.ended or "stopped")   # before station.json says complete
            self.written = record.finish(self.out, self.live.run, self.notes) + ([SESSION_FILE] if mcap else [])
        elif self._begun:                  # it never ran: say so, never "running"
            record.failed(self.out, self.live.run.ended or "failed to start", self.notes)
            self._begun = False
        if self.live.recorder is not None and not self.live.started.is_set():
            self.live.recorder.discard()   # it never ran: no session log
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
