"""The station's one public port: the token gate, the JSON API, the operator's page (the 3D view
and the live camera view side by side), the wearer's page, and a tunnel to viser.

Why a stdlib ``http.server`` beside viser rather than inside it: viser's server (websockets)
serves its page and websocket but has no hook for HTTP bodies (POST) or for checking a request
before its scene starts streaming (its ``on_client_connect`` runs after the scene's backlog is
sent). So viser listens on loopback only (the next port up) and every request reaches it through
this gate, which checks the token first: the page and the websocket carry it as a cookie set
from ``/?token=T``, the API as ``Authorization: Bearer T``. Without it: 401, and nothing else.

Routes (token: C = the cookie or ``?token=``, B = the bearer header)::

    GET  /?token=T           sets the cookie, redirects to /          (C)
    GET  /                   the operator's page                      (C)
    GET  /viser/, websocket  the 3D view (viser), tunnelled           (C)
    GET  /wearer?token=T     the wearer's page: the prompt, spoken    (C)
    GET  /api/state          the station's state, JSON                (B)
    GET  /api/frame.jpg      the augmented camera view, newest frame  (B)
    GET  /api/stream         the camera view pushed frame by frame    (B)
    POST /api/fixate | label | object | mode | stop | reset          (B)
"""

from __future__ import annotations

import hmac
import json
import math
import socket
import threading
from http.cookies import SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import numpy as np

from . import actions as A
from .live import LiveStation, Snapshot
from .overlay import camera_view, encode_jpeg
from .pages import operator_page, refused_page, wearer_page
from .view3d import GATE_HEADER

COOKIE = "wvr_station"
#: What events.csv may name as an action's source (the page's camera view says which it is).
SOURCES = ("api", "camera-view", "page")
#: How long a camera-view request waits for a frame newer than the one it has, s.
FRAME_WAIT_S = 1.0
#: The camera stream's socket send buffer, bytes: about two frames, so a slow reader holds few.
STREAM_SNDBUF = 96 * 1024


def state_json(s: Snapshot | None, station: LiveStation) -> dict:
    """GET /api/state: the contract's fields (t, mode, T_world_cam, features, joints_deg) and more."""
    if s is None:
        return {"t": None, "mode": "starting", "T_world_cam": None, "features": [], "joints_deg": None,
                "seq": 0, "estop": False, "running": not station.finished.is_set()}
    v = s.view

    def fin(x):
        return [None if not math.isfinite(float(e)) else float(e) for e in np.asarray(x, float).ravel()]

    return {
        "t": s.t, "seq": s.seq, "mode": s.mode, "localised": v.localised,
        "T_world_cam": v.T_world_cam.tolist() if v.localised else None,
        "features": [{"id": int(i), "xyz": [float(c) for c in p], "known": bool(k), "kind": kind}
                     for i, p, k, kind in zip(v.ids, v.xyz, v.known, v.kinds)],
        "initialising": [int(i) for i in v.ray_ids],
        "joints_deg": np.degrees(s.q).round(4).tolist(),
        "target": fin(s.target), "estop": s.estop, "estop_reason": s.estop_reason, "prompt": s.prompt,
        "labels": [{"id": lb.id, "text": lb.text, "xyz": lb.xyz.tolist()} for lb in s.labels],
        "objects": [{"id": ob.id, "kind": ob.kind, "xyz": ob.xyz.tolist(), "size": ob.size.tolist()} for ob in s.objects],
        "loop_hz": round(s.loop_hz, 2), "running": not station.finished.is_set(),
    }


class StationServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, host: str, port: int, token: str, station: LiveStation, viser_port: int | None,
                 gate_secret: str = ""):
        self.token = token
        self.station = station
        self.viser_port = viser_port
        self.gate_secret = gate_secret
        super().__init__((host, port), _Handler)

    @property
    def port(self) -> int:
        return self.server_address[1]

    def start(self) -> "StationServer":
        self._serving = threading.Thread(target=self.serve_forever, name="station-http", daemon=True)
        self._serving.start()
        return self

    def close(self) -> None:
        # shutdown() waits for serve_forever to end: it would wait forever for one never started.
        serving = getattr(self, "_serving", None)
        if serving is not None and serving.is_alive():
            self.shutdown()
            serving.join(5.0)
        self.server_close()

    def handle_error(self, request, client_address) -> None:
        """A browser that went away mid-reply is no error; anything else is printed as usual."""
        import sys

        if isinstance(sys.exc_info()[1], (BrokenPipeError, ConnectionResetError)):
            return
        super().handle_error(request, client_address)


def _pipe(src: socket.socket, dst: socket.socket) -> None:
    try:
        while True:
            data = src.recv(65536)
            if not data:
                break
            dst.sendall(data)
    except OSError:
        pass
    finally:
        try:
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            pass


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server: StationServer

    def log_message(self, fmt, *args):       # quiet: the station prints its own summary
        pass

    # ------------------------------------------------------------------ tokens
    def _ok(self, given: str | None) -> bool:
        return given is not None and hmac.compare_digest(given.encode(), self.server.token.encode())

    def _bearer_ok(self) -> bool:
        h = self.headers.get("Authorization", "")
        return h.startswith("Bearer ") and self._ok(h[len("Bearer "):].strip())

    def _cookie_ok(self) -> bool:
        c = SimpleCookie()
        try:
            c.load(self.headers.get("Cookie", ""))
        except Exception:  # noqa: BLE001 - a malformed cookie is no token
            return False
        return COOKIE in c and self._ok(c[COOKIE].value)

    def _query_token(self) -> str | None:
        q = parse_qs(urlsplit(self.path).query)
        return q.get("token", [None])[0]

    # ------------------------------------------------------------------ replies
    def _send(self, code: int, body: bytes, ctype: str, headers: dict | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, code: int, doc: dict) -> None:
        self._send(code, json.dumps(doc, allow_nan=False).encode(), "application/json")

    def _unauthorised_api(self) -> None:
        self._send(401, b'{"error": "unauthorized"}', "application/json", {"WWW-Authenticate": "Bearer"})

    def _unauthorised_page(self) -> None:
        self._send(401, refused_page().encode(), "text/html; charset=utf-8")

    # ------------------------------------------------------------------ routes
    def do_GET(self):
        url = urlsplit(self.path)
        path = url.path
        if path.startswith("/api/"):
            if not self._bearer_ok():
                return self._unauthorised_api()
            if path == "/api/state":
                return self._json(200, state_json(self.server.station.latest(), self.server.station))
            if path == "/api/frame.jpg":
                return self._frame(parse_qs(url.query))
            if path == "/api/stream":
                return self._stream()
            return self._json(404, {"error": f"no such endpoint {path}"})
        if path in ("/", "/index.html") and self._ok(self._query_token()):
            return self._send(303, b"", "text/plain", {
                "Location": "/", "Set-Cookie": f"{COOKIE}={self.server.token}; HttpOnly; SameSite=Strict; Path=/"})
        if path == "/wearer" and (self._ok(self._query_token()) or self._cookie_ok()):
            return self._send(200, wearer_page(self.server.token).encode(), "text/html; charset=utf-8")
        if not self._cookie_ok():
            return self._unauthorised_page()
        if path in ("/", "/index.html"):
            return self._send(200, operator_page(self.server.token).encode(), "text/html; charset=utf-8")
        if (path == "/viser" or path.startswith("/viser/")) and self.server.viser_port is not None:
            return self._tunnel("/" + path[len("/viser"):].lstrip("/") + (f"?{url.query}" if url.query else ""))
        return self._send(404, b"not found", "text/plain")

    def do_POST(self):
        path = urlsplit(self.path).path
        n = int(self.headers.get("Content-Length") or 0)
        raw = self.rfile.read(n) if n > 0 else b""
        if not path.startswith("/api/") or not self._bearer_ok():
            return self._unauthorised_api()
        kind = path[len("/api/"):]
        if kind not in ("fixate", "label", "object", "mode", "stop", "reset"):
            return self._json(404, {"error": f"no such endpoint {path}"})
        try:
            body = json.loads(raw.decode() or "{}")
            action = A.from_json(kind, body)
        except (ValueError, UnicodeDecodeError) as e:
            reason = str(e) if isinstance(e, A.BadAction) else f"the body is not JSON: {e}"
            return self._json(422, {"accepted": False, "reason": reason})
        source = self.headers.get("X-Wvr-Source", "api")
        res = self.server.station.request(action, source if source in SOURCES else "api")
        if res.accepted:
            return self._json(200, res.as_json())
        code = 409 if res.reason.startswith("stopped") else 422
        return self._json(code, res.as_json())

    # ------------------------------------------------------------------ the camera view
    def _frame(self, q: dict) -> None:
        st = self.server.station
        try:
            after = int(q.get("after", ["-1"])[0])
        except ValueError:
            after = -1
        s = st.wait_newer(after, FRAME_WAIT_S)
        if s is None:
            return self._send(204, b"", "image/jpeg")
        self._send(200, encode_jpeg(self._render(s)), "image/jpeg", {"X-Seq": str(s.seq), "X-T": f"{s.t:.4f}",
                                                         "Access-Control-Expose-Headers": "X-Seq, X-T"})

    def _stream(self) -> None:
        """The camera view pushed as it comes: a chunked response of frames, each
        ``b"WVRF" + seq (u32) + t_ms (u32) + length (u32) + JPEG`` (big-endian). Each frame is the
        newest when the previous one has been written: a slow browser gets fewer frames, never
        older ones, and the loop never waits for it (a small send buffer keeps the queue short)."""
        import struct

        st = self.server.station
        try:
            self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, STREAM_SNDBUF)
        except OSError:
            pass
        self.send_response(200)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Transfer-Encoding", "chunked")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        seq = -1
        try:
            while not st.finished.is_set():
                s = st.wait_newer(seq, FRAME_WAIT_S)
                if s is None:
                    continue
                seq = s.seq
                jpg = encode_jpeg(self._render(s))
                part = b"WVRF" + struct.pack(">III", s.seq, int(round(s.t * 1000)) & 0xFFFFFFFF, len(jpg)) + jpg
                self.wfile.write(f"{len(part):X}\r\n".encode() + part + b"\r\n")
                self.wfile.flush()
            self.wfile.write(b"0\r\n\r\n")
        except OSError:
            pass                               # the browser went away
        self.close_connection = True

    def _render(self, s: Snapshot):
        banner = f"t {s.t:5.2f} s  {s.mode}" + ("  E-STOP" if s.estop else "") + (f"  | {s.prompt}" if s.prompt else "")
        return camera_view(s.image, self.server.station.camera, s.view, list(s.labels), list(s.objects), banner)

    # ------------------------------------------------------------------ the 3D view (viser)
    def _tunnel(self, upstream_path: str) -> None:
        """Hand this connection to viser: the request head (path rewritten) then raw bytes both
        ways, for its page and for its websocket."""
        try:
            up = socket.create_connection(("127.0.0.1", self.server.viser_port), timeout=5)
        except OSError:
            return self._send(502, b"the 3D view is not running", "text/plain")
        up.settimeout(None)
        upgrade = self.headers.get("Upgrade", "").lower() == "websocket"
        lines = [f"{self.command} {upstream_path} HTTP/1.1"]
        for k, v in self.headers.items():
            if k.lower() in ("cookie", GATE_HEADER.lower()) or (not upgrade and k.lower() == "connection"):
                continue                                   # the token stays here
            lines.append(f"{k}: {v}")
        lines.append(f"{GATE_HEADER}: {self.server.gate_secret}")
        if not upgrade:
            lines.append("Connection: close")
        up.sendall(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1"))
        client = self.connection
        if upgrade:
            t = threading.Thread(target=_pipe, args=(up, client), daemon=True)
            t.start()
            _pipe(client, up)
            t.join()
        else:
            _pipe(up, client)          # a page request has no body: viser answers and closes
        up.close()
        self.close_connection = True
