"""A simulated IRC5 Robot Web Services 1.0 server: Digest auth, sessions, RAPID execution, joints.

HTTP Digest (MD5, qop=auth, realm "validusers@robapi.abb") opens a session whose cookie later
requests reuse; beyond `max_sessions` sessions a new one gets 503, as on the real controller. Replies
are JSON shaped `{"_embedded": {"_state": [...]}}` whatever `?json=1` says. Resources served:

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
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import numpy as np

REALM = "validusers@robapi.abb"
SESSION_COOKIE = "-http-session-"
_DIGEST_PARAM = re.compile(r'(\w+)=(?:"([^"]*)"|([^,\s]*))')


def _md5(text: str) -> str:
    return hashlib.md5(text.encode()).hexdigest()


class _Request(Exception):
    """An HTTP error reply (status, message) raised inside a route."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


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
        on_rapid_start: Callable[[], None] = lambda: None,
        on_rapid_stop: Callable[[], None] = lambda: None,
        symbols: dict[str, str] | None = None,
    ) -> None:
        self.joints = joints
        self.user, self.password = user, password
        self.max_sessions = max_sessions
        self.on_rapid_start, self.on_rapid_stop = on_rapid_start, on_rapid_stop
        self.symbols = dict(symbols or {})  # "TASK/name" -> RAPID literal
        self.ctrlstate = "motoron"
        self.opmode = "AUTO"
        self.rapid_running = False
        self.sessions: set[str] = set()
        self.challenges = 0  # 401 replies sent (how often a client had to authenticate)
        self._nonces: set[str] = set()
        self._lock = threading.Lock()
        self._httpd = ThreadingHTTPServer((host, port), self._handler_class())
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, args=(0.05,), name="rws-sim", daemon=True)
        self._thread.start()

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
    def _authorize(self, method: str, cookie: str, authorization: str) -> str | None:
        """Return a new session id to set (or "" when the cookie's session is valid); None -> 401."""
        with self._lock:
            for part in cookie.split(";"):
                name, _, value = part.strip().partition("=")
                if name == SESSION_COOKIE and value in self.sessions:
                    return ""
            if not authorization.startswith("Digest "):
                return None
            p = {m[0]: m[1] or m[2] for m in _digest_params(authorization)}
            if p.get("nonce") not in self._nonces or p.get("username") != self.user or p.get("realm") != REALM:
                return None
            ha1 = _md5(f"{self.user}:{REALM}:{self.password}")
            ha2 = _md5(f"{method}:{p.get('uri', '')}")
            expected = _md5(f"{ha1}:{p['nonce']}:{p.get('nc', '')}:{p.get('cnonce', '')}:{p.get('qop', '')}:{ha2}")
            if p.get("qop") != "auth" or not secrets.compare_digest(expected, p.get("response", "")):
                return None
            if len(self.sessions) >= self.max_sessions:
                raise _Request(503, "too many sessions")
            session = secrets.token_hex(16)
            self.sessions.add(session)
            return session

    def _challenge(self) -> str:
        with self._lock:
            nonce = secrets.token_hex(16)
            self._nonces.add(nonce)
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
            deg = np.degrees(self.joints[m[1]]())
            axes = {f"rax_{i + 1}": f"{deg[c]:.6f}" for i, c in enumerate((0, 1, 3, 4, 5, 6))}
            extra = {f"eax_{x}": "9E+09" for x in "bcdef"}  # unused external axes, as RWS reports them
            return {"_type": "ms-jointtarget", **axes, "eax_a": f"{deg[2]:.6f}", **extra}
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
            def log_message(self, *args: object) -> None:  # keep test and CLI output clean
                pass

            def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
                self._serve("GET")

            def do_POST(self) -> None:  # noqa: N802
                self._serve("POST")

            def _serve(self, method: str) -> None:
                url = urlsplit(self.path)
                length = min(int(self.headers.get("Content-Length") or 0), 65536)
                body = self.rfile.read(length).decode(errors="replace") if length else ""
                try:
                    session = server._authorize(
                        method, self.headers.get("Cookie", ""), self.headers.get("Authorization", "")
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
                    self._reply(exc.status, {"status": {"code": exc.status, "msg": str(exc)}}, {})

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
