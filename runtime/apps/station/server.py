"""The station's one public port: the token gate, the JSON API, the operator's page (the 3D view
and the live camera view side by side), the wearer's page, and a tunnel to viser.

Why a stdlib ``http.server`` beside viser rather than inside it: viser's server (websockets)
serves its page and websocket but has no hook for HTTP bodies (POST) or for checking a request
before its scene starts streaming (its ``on_client_connect`` runs after the scene's backlog is
sent). So viser listens on loopback only (the next port up) and every request reaches it through
this gate, which checks the token first: the page and the websocket carry it as a cookie set
from ``/?token=T``, the API as ``Authorization: Bearer T``. Without it: 401, and nothing else.

Two tokens: the operator's (T) opens everything; the wearer's (W, derived from T, see
:func:`wearer_token_for`) opens the wearer's page and reads the prompt, nothing more (403 on
every other endpoint), so the page handed to the wearer can neither stop nor steer the head.

Routes (token: C = the cookie or ``?token=``, B = the bearer header)::

    GET  /?token=T           sets the cookie, redirects to /          (C, T)
    GET  /                   the operator's page                      (C, T)
    GET  /viser/, websocket  the 3D view (viser), tunnelled           (C, T)
    GET  /wearer?token=W     the wearer's page: the prompt, spoken    (C, W or T)
    GET  /api/prompt         the wearer's prompt, mode and stop       (B, W or T)
    GET  /api/state          the station's state, JSON                (B, T)
    GET  /api/frame.jpg      the augmented camera view, newest frame  (B, T)
    GET  /api/stream         the camera view pushed frame by frame    (B, T)
    POST /api/fixate | label | object | mode | stop | reset          (B, T)

Hostile or busy clients: the token is checked before a body is read; bodies are capped
(:data:`MAX_BODY`, 413) and must arrive within :data:`BODY_TIMEOUT_S` (408); a length that is
not a number, JSON nested deeper than :data:`MAX_JSON_DEPTH` or a malformed request line get a
JSON 400; other methods than GET and POST a JSON 405. Every refusal is JSON, never a traceback.
The listen backlog (:data:`LISTEN_BACKLOG`) holds a burst of a hundred clients while the
accepting thread catches up.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import math
import re
import socket
import threading
import time
from http import HTTPStatus
from http.cookies import SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import numpy as np

from . import actions as A
from .geometry import EXPLORE_OBJECTIVE
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
#: The largest request body the API reads, bytes (an action's is a few hundred).
MAX_BODY = 64 * 1024
#: How deep a body's JSON may nest (an action's nests 2 deep); checked before it is parsed.
MAX_JSON_DEPTH = 32
#: How long a whole request body may take to arrive, s.
BODY_TIMEOUT_S = 10.0
#: How long a connection may stay silent (between requests, or inside a request's head), s.
IDLE_TIMEOUT_S = 30.0
#: How long the camera stream may wait on a reader that takes nothing, s, before dropping it
#: (the page's worker reconnects).
STREAM_SEND_TIMEOUT_S = 60.0
#: Connections the kernel holds while the accepting thread is busy (socketserver's default is 5,
#: which reset a third of 40 concurrent requests).
LISTEN_BACKLOG = 1024
#: The actions a POST may name.
ACTIONS = ("fixate", "label", "object", "mode", "stop", "reset")
#: What the wearer's token may read.
WEARER_PATHS = ("/api/prompt",)

_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)


def wearer_token_for(token: str) -> str:
    """The wearer's token for an operator's token: an HMAC of it, so the same ``--token`` gives
    the same wearer's address, and the wearer's token tells nothing of the operator's."""
    mac = hmac.new(token.encode(), b"wvr station: the wearer's page", hashlib.sha256).digest()
    return base64.urlsafe_b64encode(mac[:18]).decode()


def json_depth(raw: bytes) -> int:
    """How deep the arrays and objects of a JSON text nest, without parsing it (so a body
    nested 30,000 deep is refused before a recursive parser sees it). Brackets inside strings
    do not count; an unterminated string counts its brackets (over, never under)."""
    a = np.frombuffer(_JSON_STRING.sub(b'""', raw), np.uint8)
    step = np.isin(a, (0x5B, 0x7B)).astype(np.int64) - np.isin(a, (0x5D, 0x7D))
    return int(np.cumsum(step).max(initial=0))


def prompt_json(s: Snapshot | None, station: LiveStation) -> dict:
    """GET /api/prompt: what the wearer's page shows (the prompt, the mode, the stop)."""
    running = not station.finished.is_set()
    if s is None:
        return {"t": None, "prompt": "", "mode": "starting", "estop": False, "running": running}
    return {"t": s.t, "prompt": s.prompt, "mode": s.mode, "estop": s.estop, "running": running}


def state_json(s: Snapshot | None, station: LiveStation) -> dict:
    """GET /api/state: the contract's fields (t, mode, T_world_cam, features, joints_deg) and more.

    ``explore`` : null unless the loop explores; then ``{"objective": str, "chosen": int | null,
    "candidates": [{"xyz": [x, y, z] m, "score": nats, "pose_info": nats, "novelty": nats,
    "visible": int}]}``: the reachable candidate views of its last choice (none before the
    first), ``chosen`` the index of the one it saccaded to."""
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
        "explore": None if s.explore is None else {
            "objective": EXPLORE_OBJECTIVE, "chosen": s.explore.chosen if s.explore.chosen >= 0 else None,
            "candidates": [{"xyz": [float(c) for c in p], "score": float(sc), "pose_info": float(pi),
                            "novelty": float(nv), "visible": int(vis)}
                           for p, sc, pi, nv, vis in zip(s.explore.points_world, s.explore.score, s.explore.pose_info,
                                                         s.explore.novelty, s.explore.visible)]},
    }


class StationServer(ThreadingHTTPServer):
    """The public port. token : the operator's; wearer_token : the wearer's (None: derived from
    ``token``). body_timeout_s : how long a request body may take to arrive."""

    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = LISTEN_BACKLOG

    def __init__(self, host: str, port: int, token: str, station: LiveStation, viser_port: int | None,
                 gate_secret: str = "", wearer_token: str | None = None, body_timeout_s: float = BODY_TIMEOUT_S):
        self.token = token
        self.wearer_token = wearer_token if wearer_token is not None else wearer_token_for(token)
        self.station = station
        self.viser_port = viser_port
        self.gate_secret = gate_secret
        self.body_timeout_s = body_timeout_s
        if ":" in host:
            self.address_family = socket.AF_INET6
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
    timeout = IDLE_TIMEOUT_S                 # a silent connection is dropped, never held
    server: StationServer

    def log_message(self, fmt, *args):       # quiet: the station prints its own summary
        pass

    # ------------------------------------------------------------------ tokens
    def _ok(self, given: str | None, token: str | None = None) -> bool:
        token = self.server.token if token is None else token
        return given is not None and hmac.compare_digest(given.encode(), token.encode())

    def _bearer(self) -> str | None:
        h = self.headers.get("Authorization", "")
        return h[len("Bearer "):].strip() if h.startswith("Bearer ") else None

    def _bearer_role(self) -> str | None:
        """"operator", "wearer", or None (no token or a wrong one)."""
        given = self._bearer()
        if self._ok(given):
            return "operator"
        if self._ok(given, self.server.wearer_token):
            return "wearer"
        return None

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
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, code: int, doc: dict, headers: dict | None = None) -> None:
        self._send(code, json.dumps(doc, allow_nan=False).encode(), "application/json", headers)

    def _refuse(self, code: int, error: str, headers: dict | None = None) -> None:
        """A JSON refusal; the connection is closed after it when a request body was left
        unread (its bytes would otherwise be taken for the next request)."""
        if getattr(self, "_body_unread", False):
            self.close_connection = True
        self._json(code, {"error": error}, headers)

    def _unauthorised_api(self) -> None:
        self._refuse(401, "unauthorized", {"WWW-Authenticate": "Bearer"})

    def _forbidden_wearer(self) -> None:
        self._refuse(403, "forbidden: the wearer's token only reads the prompt (GET /api/prompt)")

    def _unauthorised_page(self) -> None:
        self._send(401, refused_page().encode(), "text/html; charset=utf-8")

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """Every error the HTTP layer finds (a malformed request line or header, a method this
        server has no handler for) as JSON; an unknown method is a 405 naming the two it takes."""
        headers = {}
        if getattr(self, "request_version", "") == "HTTP/0.9":
            self.request_version = "HTTP/1.0"      # so that the reply has a status line and headers
        if code == HTTPStatus.NOT_IMPLEMENTED:
            code, message = HTTPStatus.METHOD_NOT_ALLOWED, \
                f"method {str(self.command)[:20]!r} is not allowed; the station takes GET and POST"
            headers["Allow"] = "GET, POST"
        self.close_connection = True
        try:
            phrase = HTTPStatus(code).phrase
        except ValueError:
            phrase = "error"
        # The stdlib's messages quote the request line: up to 64 KiB of whatever was sent.
        self._json(int(code), {"error": f"{phrase}: {str(message)[:200]}" if message else phrase}, headers)

    def parse_request(self) -> bool:
        """As the stdlib's, but an HTTP/0.9 request (no version, so no headers either way) is a
        400: its reply could carry no status."""
        if not super().parse_request():
            return False
        if self.request_version == "HTTP/0.9":
            self.send_error(HTTPStatus.BAD_REQUEST, "HTTP/0.9 is not served; send HTTP/1.1")
            return False
        return True

    def handle_expect_100(self) -> bool:
        """``Expect: 100-continue``: the token and the length are checked before the client is
        told to send its body."""
        if self.command == "POST":
            self._body_unread = True
            refused = self._post_refusal()
            if refused is not None:
                self._refuse(*refused)
                return False
        return super().handle_expect_100()

    # ------------------------------------------------------------------ routes
    def do_GET(self):
        url = urlsplit(self.path)
        path = url.path
        self._body_unread = False
        if self.headers.get("Content-Length", "0").strip() not in ("", "0") or "Transfer-Encoding" in self.headers:
            self.close_connection = True       # a GET's body is never read: close after the reply
        if path.startswith("/api/"):
            role = self._bearer_role()
            if role is None:
                return self._unauthorised_api()
            if path in WEARER_PATHS:
                return self._json(200, prompt_json(self.server.station.latest(), self.server.station))
            if role != "operator":
                return self._forbidden_wearer()
            if path == "/api/state":
                return self._json(200, state_json(self.server.station.latest(), self.server.station))
            if path == "/api/frame.jpg":
                return self._frame(parse_qs(url.query))
            if path == "/api/stream":
                return self._stream()
            return self._refuse(404, f"no such endpoint {path[:100]}")
        if path in ("/", "/index.html") and self._ok(self._query_token()):
            return self._send(303, b"", "text/plain", {
                "Location": "/", "Set-Cookie": f"{COOKIE}={self.server.token}; HttpOnly; SameSite=Strict; Path=/"})
        if path == "/wearer" and (self._ok(self._query_token(), self.server.wearer_token)
                                  or self._ok(self._query_token()) or self._cookie_ok()):
            return self._send(200, wearer_page(self.server.wearer_token).encode(), "text/html; charset=utf-8")
        if not self._cookie_ok():
            return self._unauthorised_page()
        if path in ("/", "/index.html"):
            return self._send(200, operator_page(self.server.token, self.server.wearer_token).encode(),
                              "text/html; charset=utf-8")
        if (path == "/viser" or path.startswith("/viser/")) and self.server.viser_port is not None:
            return self._tunnel("/" + path[len("/viser"):].lstrip("/") + (f"?{url.query}" if url.query else ""))
        return self._send(404, b"not found", "text/plain")

    def _post_refusal(self) -> tuple | None:
        """Why a POST is refused from its head alone (the token, the endpoint, the length), as
        ``_refuse``'s arguments; None if its body may be read."""
        path = urlsplit(self.path).path
        if not path.startswith("/api/"):
            return 401, "unauthorized", {"WWW-Authenticate": "Bearer"}
        role = self._bearer_role()
        if role is None:
            return 401, "unauthorized", {"WWW-Authenticate": "Bearer"}
        if role != "operator":
            return 403, "forbidden: the wearer's token only reads the prompt (GET /api/prompt)"
        if path[len("/api/"):] not in ACTIONS:
            return 404, f"no such endpoint {path[:100]}"
        if "Transfer-Encoding" in self.headers:
            return 411, "send the body with a Content-Length (no chunked transfer)"
        text = self.headers.get("Content-Length", "0").strip() or "0"
        if not (text.isascii() and text.isdigit()):
            return 400, f"Content-Length {text[:40]!r} is not a number of bytes"
        if len(text) > 9 or int(text) > MAX_BODY:
            return 413, f"the body is {text[:40]} bytes; an action's is at most {MAX_BODY}"
        return None

    def _read_body(self, n: int) -> bytes:
        """``n`` bytes of body, all of them within ``body_timeout_s`` (TimeoutError otherwise,
        ConnectionError if the client went away first)."""
        deadline = time.monotonic() + self.server.body_timeout_s
        parts, got = [], 0
        try:
            while got < n:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError
                self.connection.settimeout(left)
                part = self.rfile.read1(n - got)
                if not part:
                    raise ConnectionError("the client closed the connection mid-body")
                parts.append(part)
                got += len(part)
        finally:
            self.connection.settimeout(self.timeout)
        return b"".join(parts)

    def do_POST(self):
        self._body_unread = True
        refused = self._post_refusal()
        if refused is not None:
            return self._refuse(*refused)
        kind = urlsplit(self.path).path[len("/api/"):]
        try:
            raw = self._read_body(int(self.headers.get("Content-Length", "0").strip() or "0"))
        except TimeoutError:
            return self._refuse(408, f"the body did not arrive within {self.server.body_timeout_s:g} s")
        except (ConnectionError, OSError):
            self.close_connection = True
            return
        self._body_unread = False
        depth = json_depth(raw)
        if depth > MAX_JSON_DEPTH:
            return self._refuse(400, f"the body's JSON nests {depth} deep; an action's nests at most {MAX_JSON_DEPTH}")
        try:
            body = json.loads(raw.decode() or "{}")
            action = A.from_json(kind, body)
        except (ValueError, UnicodeDecodeError, RecursionError) as e:
            reason = str(e) if isinstance(e, A.BadAction) else f"the body is not JSON: {str(e)[:200]}"
            return self._json(422, {"accepted": False, "reason": reason})
        source = self.headers.get("X-Wvr-Source", "api")
        res = self.server.station.request(action, source if source in SOURCES else "api")
        if res.accepted:
            return self._json(200, res.as_json())
        code = 409 if res.reason.startswith("stopped") else 422
        return self._json(code, res.as_json())

    def _method_not_allowed(self):
        self._body_unread = True
        self.send_error(HTTPStatus.NOT_IMPLEMENTED)

    do_PUT = do_DELETE = do_PATCH = do_HEAD = do_OPTIONS = do_TRACE = do_CONNECT = _method_not_allowed

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
            self.connection.settimeout(STREAM_SEND_TIMEOUT_S)
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
        banner = f"t {s.t:5.2f} s  {'explore: ' if s.explore is not None else ''}{s.mode}" + ("  E-STOP" if s.estop else "") + (f"  | {s.prompt}" if s.prompt else "")
        return camera_view(s.image, self.server.station.camera, s.view, list(s.labels), list(s.objects), banner,
                           s.explore)

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
        client.settimeout(None)                # a websocket may be quiet for as long as it likes
        if upgrade:
            t = threading.Thread(target=_pipe, args=(up, client), daemon=True)
            t.start()
            _pipe(client, up)
            t.join()
        else:
            _pipe(up, client)          # a page request has no body: viser answers and closes
        up.close()
        self.close_connection = True
