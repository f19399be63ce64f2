"""A small client of the station's JSON API, for scripts (the demo's operator, the benchmarks):
each call returns an :class:`ApiReply` (the HTTP status and the decoded JSON)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from dataclasses import dataclass


@dataclass(frozen=True)
class ApiReply:
    status: int
    body: dict

    @property
    def accepted(self) -> bool:
        return self.status == 200 and bool(self.body.get("accepted", True))


class StationClient:
    """base : the station's address (``http://host:port/``). token : its bearer token."""

    def __init__(self, base: str, token: str, timeout: float = 10.0):
        self.base = base.rstrip("/")
        self.token = token
        self.timeout = timeout

    def _call(self, method: str, path: str, body: dict | None = None) -> ApiReply:
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers={"Authorization": f"Bearer {self.token}",
                                              **({"Content-Type": "application/json"} if data else {})})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                return ApiReply(r.status, json.loads(r.read() or b"{}"))
        except urllib.error.HTTPError as e:
            raw = e.read()
            try:
                return ApiReply(e.code, json.loads(raw or b"{}"))
            except ValueError:
                return ApiReply(e.code, {"reason": raw.decode(errors="replace")})

    def state(self) -> dict:
        r = self._call("GET", "/api/state")
        if r.status != 200:
            raise ValueError(f"GET /api/state answered {r.status}: {r.body}")
        return r.body

    def fixate(self, **target) -> ApiReply:
        """``feature=id``, ``xyz=[x, y, z]`` or ``uv=[u, v]``."""
        return self._call("POST", "/api/fixate", target)

    def label(self, text: str, **target) -> ApiReply:
        return self._call("POST", "/api/label", {"text": text, **target})

    def add_object(self, kind: str, **fields) -> ApiReply:
        return self._call("POST", "/api/object", {"kind": kind, **fields})

    def mode(self, mode: str) -> ApiReply:
        return self._call("POST", "/api/mode", {"mode": mode})

    def stop(self, reason: str = "script") -> ApiReply:
        return self._call("POST", "/api/stop", {"reason": reason})

    def reset(self) -> ApiReply:
        return self._call("POST", "/api/reset", {})

    def raw(self, method: str, path: str, body=None) -> ApiReply:
        return self._call(method, path, body)
