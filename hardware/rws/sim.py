"""A simulated IRC5 Robot Web Services 1.0 server: Digest auth, sessions, RAPID execution, joints.

HTTP Digest (MD5, qop=auth, realm "validusers@robapi.abb") opens a session whose cookie later
requests reuse; beyond `max_sessions` sessions a new one gets 503, as on the real controller. Replies
are JSON shaped `{"_embedded": {"_state": [...]}}` whatever `?json=1` says.

A Digest answer counts only with a nonce this server issued less than `nonce_ttl_s` ago, a nonce
count (nc) above any earlier one for that nonce (a captured header does not replay), and a `uri`
equal to the request's target. Sessions idle for `session_idle_s` expire (the client logs in
again). Before authentication nothing a stranger sends holds resources: at most `max_nonces`
nonces are kept (the oldest go first), at most `max_connections` connections are served at once
(more are closed at once), every read times out after `request_timeout_s`, and a Content-Length
that is not a number gets 400, one over 64 KiB 413, before any body is read. Resources served:

- GET  rw/panel/ctrlstate, POST rw/panel/ctrlstate?action=setctrlstate (ctrl-state=motoron|motoroff)
- GET  rw/panel/opmode
- GET  rw/rapid/execution, POST rw/rapid/execution?action=start|stop|resetpp
- GET  rw/motionsystem/mechunits/{unit}/jointtarget (degrees: rax_1..rax_6, eax_a = YuMi axis 7)
- GET  rw/rapid/symbol/data/RAPID/{task}/{name}, POST ...?action=set (value=...)

Starting RAPID needs motors on and AUTO mode (else 400); it calls `on_rapid_start`, which is where
the simulated EGM arms begin streaming.
"""

from __future__ import annotations

import hashlib
import json
import re
import secrets
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import numpy as np

from hardware.rws.protocol import REALM, SESSION_COOKIE, chain_to_jointtarget

_DIGEST_PARAM = re.compile(r'(\w+)=(?:"([^"]*)"|([^,\s]*))')
_CONTENT_LENGTH = re.compile(r"[0-9]+")
MAX_BODY_BYTES = 65536


def _md5(text: str) -> str:
    return hashlib.md5(text.encode()).hexdigest()


class _Request(Exception):
    """An HTTP error reply (status, message) raised inside a route."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass
class _Nonce:
    issued: float
    """When the challenge carrying it was sent (s, monotonic)."""
    last_nc: int = 0
    """The highest nonce count accepted with it so far."""


class _BoundedHTTPServer(ThreadingHTTPServer):
    """A threading HTTP server that serves at most `max_connections` connections at once."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler], max_connections: int) -> None:
        self._slots = threading.BoundedSemaphore(max_connections)
        super().__init__(address, handler)

    def process_request(self, request: socket.socket, client_address: tuple[str, int]) -> None:
        if not self._slots.acquire(blocking=False):
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: socket.socket, client_address: tuple[str, int]) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


class SimRwsServer:
    """RWS 1.0 on `host:port` (port 0 picks one) for the mechanical units in `joints` (rad, chain order)."""

    def __init__(
        self,
        joints: dict[str, Callable[[], np.ndarray]],
        host: str = "127.0.0.1",
        port: int = 80,
        user: str = "Default User",
        password: str = "robotics",
        max_sessions: int = 70,
        session_idle_s: float = 300.0,
        nonce_ttl_s: float = 60.0,
        max_nonces: int = 1024,
        max_connections: int = 16,
        request_timeout_s: float = 5.0,
        on_rapid_start: Callable[[], None] = lambda: None,
        on_rapid_stop: Callable[[], None] = lambda: None,
        symbols: dict[str, str] | None = None,
    ) -> None:
        self.joints = joints
        self.user, self.password = user, password
        self.max_sessions, self.session_idle_s = max_sessions, session_idle_s
        self.nonce_ttl_s, self.max_nonces = nonce_ttl_s, max_nonces
        self.max_connections, self.request_timeout_s = max_connections, request_timeout_s
        self.on_rapid_start, self.on_rapid_stop = on_rapid_start, on_rapid_stop
        self.symbols = dict(symbols or {})  # "TASK/name" -> RAPID literal
        self.ctrlstate = "motoron"
        self.opmode = "AUTO"
        self.rapid_running = False
        self.sessions: dict[str, float] = {}  # session id -> when last used (s, monotonic)
        self.challenges = 0  # 401 replies sent (how often a client had to authenticate)
        self._nonces: dict[str, _Nonce] = {}  # in the order issued
        self._lock = threading.Lock()
        self._httpd = _BoundedHTTPServer((host, port), self._handler_class(), max_connections)
        self._thread = threading.Thread(target=self._httpd.serve_forever, args=(0.05,), name="rws-sim", daemon=True)
        self._thread.start()

    @property
    def pending_nonces(self) -> int:
        """How many issued nonces the server still remembers (bounded by `max_nonces`)."""
        with self._lock:
            self._prune(time.monotonic())
            return len(self._nonces)

    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return self._httpd.server_address[1]

    def close(self) -> None:
        """Stop serving; safe to call twice."""
        if self._thread.is_alive():
            self._httpd.shutdown()
        self._httpd.server_close()

    # -- auth ------------------------------------------------------------------------------------
    def _authorize(self, method: str, target: str, cookie: str, authorization: str) -> str | None:
        """Return a new session id to set (or "" when the cookie's session is valid); None -> 401.

        `target` is the request's target as sent (path and query), which the Digest `uri` must equal.
        """
        with self._lock:
            now = time.monotonic()
            self._prune(now)
            for part in cookie.split(";"):
                name, _, value = part.strip().partition("=")
                if name == SESSION_COOKIE and value in self.sessions:
                    self.sessions[value] = now
                    return ""
            if not authorization.startswith("Digest ") or not self._digest_valid(method, target, authorization):
                return None
            if len(self.sessions) >= self.max_sessions:
                raise _Request(503, "too many sessions")
            session = secrets.token_hex(16)
            self.sessions[session] = now
            return session

    def _digest_valid(self, method: str, target: str, authorization: str) -> bool:
        """RFC 2617 Digest (MD5, qop=auth) with a fresh nonce of ours, a new nonce count and our URI."""
        p = {m[0]: m[1] or m[2] for m in _digest_params(authorization)}
        nonce = self._nonces.get(p.get("nonce", ""))
        fields = (p.get("username"), p.get("realm"), p.get("qop"), p.get("uri"))
        if nonce is None or fields != (self.user, REALM, "auth", target):
            return False
        try:
            nc = int(p.get("nc", ""), 16)
        except ValueError:
            return False
        ha1 = _md5(f"{self.user}:{REALM}:{self.password}")
        ha2 = _md5(f"{method}:{target}")
        expected = _md5(f"{ha1}:{p['nonce']}:{p['nc']}:{p.get('cnonce', '')}:auth:{ha2}")
        if nc <= nonce.last_nc or not secrets.compare_digest(expected.encode(), p.get("response", "").encode()):
            return False
        nonce.last_nc = nc
        return True

    def _prune(self, now: float) -> None:
        """Forget expired nonces, nonces beyond `max_nonces` (oldest first) and idle sessions."""
        while self._nonces and (
            len(self._nonces) > self.max_nonces or now - next(iter(self._nonces.values())).issued > self.nonce_ttl_s
        ):
            del self._nonces[next(iter(self._nonces))]
        for session in [s for s, used in self.sessions.items() if now - used > self.session_idle_s]:
            del self.sessions[session]

    def _challenge(self) -> str:
        with self._lock:
            nonce = secrets.token_hex(16)
            self._nonces[nonce] = _Nonce(time.monotonic())
            self._prune(time.monotonic())
            self.challenges += 1
        return f'Digest realm="{REALM}", qop="auth", nonce="{nonce}", algorithm=MD5'

    # -- resources -------------------------------------------------------------------------------
    def _get(self, path: str) -> dict:
        if path == "rw/panel/ctrlstate":
            return {"_type": "pnl-ctrlstate", "ctrlstate": self.ctrlstate}
        if path == "rw/panel/opmode":
            return {"_type": "pnl-opmode", "opmode": self.opmode}
        if path == "rw/rapid/execution":
            return {"_type": "rap-execution", "ctrlexecstate": "running" if self.rapid_running else "stopped"}
        if m := re.fullmatch(r"rw/motionsystem/mechunits/(\w+)/jointtarget", path):
            if m[1] not in self.joints:
                raise _Request(404, f"no mechanical unit {m[1]}")
            extra = {f"eax_{x}": "9E+09" for x in "bcdef"}  # unused external axes, as RWS reports them
            return {"_type": "ms-jointtarget", **chain_to_jointtarget(self.joints[m[1]]()), **extra}
        if m := re.fullmatch(r"rw/rapid/symbol/data/RAPID/(\w+)/(\w+)", path):
            return {"_type": "rap-data", "value": self._symbol(m[1], m[2])}
        raise _Request(404, f"no resource {path}")

    def _post(self, path: str, action: str, form: dict[str, str]) -> None:
        if path == "rw/panel/ctrlstate" and action == "setctrlstate":
            state = form.get("ctrl-state", "")
            if state not in ("motoron", "motoroff"):
                raise _Request(400, f"bad ctrl-state {state!r}")
            if self.opmode != "AUTO":
                raise _Request(403, "motors can only be switched remotely in AUTO")
            self.ctrlstate = state
        elif path == "rw/rapid/execution" and action == "start":
            if self.ctrlstate != "motoron" or self.opmode != "AUTO":
                raise _Request(400, f"cannot start RAPID: controller {self.ctrlstate}, mode {self.opmode}")
            if not self.rapid_running:
                self.rapid_running = True
                self.on_rapid_start()
        elif path == "rw/rapid/execution" and action == "stop":
            if self.rapid_running:
                self.rapid_running = False
                self.on_rapid_stop()
        elif path == "rw/rapid/execution" and action == "resetpp":
            if self.rapid_running:
                raise _Request(400, "cannot reset the program pointer while RAPID runs")
        elif (m := re.fullmatch(r"rw/rapid/symbol/data/RAPID/(\w+)/(\w+)", path)) and action == "set":
            self._symbol(m[1], m[2])
            self.symbols[f"{m[1]}/{m[2]}"] = form.get("value", "")
        else:
            raise _Request(404, f"no action {action!r} on {path}")

    def _symbol(self, task: str, name: str) -> str:
        key = f"{task}/{name}"
        if key not in self.symbols:
            raise _Request(400, f"unknown RAPID symbol {key}")
        return self.symbols[key]

    def _handler_class(self) -> type[BaseHTTPRequestHandler]:
        server = self

        class Handler(BaseHTTPRequestHandler):
            timeout = server.request_timeout_s  # every read and write of the connection

            def log_message(self, *args: object) -> None:  # keep test and CLI output clean
                pass

            def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
                self._serve("GET")

            def do_POST(self) -> None:  # noqa: N802
                self._serve("POST")

            def _serve(self, method: str) -> None:
                url = urlsplit(self.path)
                try:
                    body = self._body()
                    session = server._authorize(
                        method, self.path, self.headers.get("Cookie", ""), self.headers.get("Authorization", "")
                    )
                    if session is None:
                        self._reply(401, None, {"WWW-Authenticate": server._challenge()})
                        return
                    headers = {"Set-Cookie": f"{SESSION_COOKIE}={session}; Path=/"} if session else {}
                    path = url.path.strip("/")
                    with server._lock:
                        if method == "GET":
                            self._reply(200, {"_embedded": {"_state": [server._get(path)]}}, headers)
                        else:
                            action = parse_qs(url.query).get("action", [""])[0]
                            form = {k: v[0] for k, v in parse_qs(body).items()}
                            server._post(path, action, form)
                            self._reply(204, None, headers)
                except _Request as exc:
                    self.close_connection = True  # an unread body must not be taken for the next request
                    self._reply(exc.status, {"status": {"code": exc.status, "msg": str(exc)}}, {})

            def _body(self) -> str:
                """The request body, read only when Content-Length is a number up to MAX_BODY_BYTES."""
                text = self.headers.get("Content-Length", "0").strip()
                if not _CONTENT_LENGTH.fullmatch(text):
                    raise _Request(400, f"bad Content-Length {text[:20]!r}")
                if len(text) > len(str(MAX_BODY_BYTES)) or int(text) > MAX_BODY_BYTES:
                    raise _Request(413, f"body over {MAX_BODY_BYTES} bytes")
                return self.rfile.read(int(text)).decode(errors="replace")

            def _reply(self, status: int, payload: dict | None, headers: dict[str, str]) -> None:
                data = json.dumps(payload).encode() if payload is not None else b""
                self.send_response(status)
                for key, value in headers.items():
                    self.send_header(key, value)
                if data:
                    self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        return Handler


def _digest_params(header: str) -> list[tuple[str, str, str]]:
    return _DIGEST_PARAM.findall(header[len("Digest ") :])
