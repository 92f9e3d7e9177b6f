"""ABB Robot Web Services 1.0 client (IRC5 / RobotWare 6, what YuMi runs): Digest auth, JSON replies.

Uses the standard library's HTTP Digest handler and keeps the session cookie, so only the first
request authenticates (RWS limits the number of sessions; 503 means too many). Joint targets come
back in degrees as rax_1..rax_6 and eax_a (YuMi's axis 7) and are returned in radians, chain order.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request
from http.cookiejar import CookieJar

import numpy as np

from hardware.rws.protocol import MECHUNITS, START_FORM, jointtarget_to_chain


class RwsError(RuntimeError):
    """An RWS request failed: HTTP status (0 when the controller could not be reached) and a message."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(f"RWS {status}: {message}" if status else f"RWS unreachable: {message}")
        self.status = status


class RwsClient:
    """Talk to the controller at `http://host:port` as `user` (factory default "Default User"/"robotics")."""

    def __init__(
        self, host: str, port: int = 80, user: str = "Default User", password: str = "robotics", timeout_s: float = 5.0
    ) -> None:
        self.base = f"http://{host}:{port}/"
        self.timeout_s = timeout_s
        passwords = urllib.request.HTTPPasswordMgrWithDefaultRealm()
        passwords.add_password(None, self.base, user, password)
        self._opener = urllib.request.build_opener(
            urllib.request.HTTPDigestAuthHandler(passwords), urllib.request.HTTPCookieProcessor(CookieJar())
        )

    def _request(self, path: str, query: dict[str, str] | None = None, form: dict[str, str] | None = None) -> dict:
        url = self.base + path + "?" + urllib.parse.urlencode({**(query or {}), "json": "1"})
        data = urllib.parse.urlencode(form).encode() if form is not None else None
        try:
            with self._opener.open(urllib.request.Request(url, data=data), timeout=self.timeout_s) as reply:
                body = reply.read()
        except urllib.error.HTTPError as exc:
            detail = exc.read().decode(errors="replace")
            if exc.code == 401:
                detail = "authentication failed (check rws.user / rws.password)"
            elif exc.code == 503:
                detail = "too many connections/sessions on the controller; close other RWS clients and retry"
            raise RwsError(exc.code, f"{path}: {_message(detail)}") from exc
        except (urllib.error.URLError, OSError) as exc:
            raise RwsError(0, f"{self.base}{path}: {exc}") from exc
        if not body:
            return {}
        try:
            return json.loads(body)["_embedded"]["_state"][0]
        except (ValueError, KeyError, IndexError, TypeError) as exc:
            raise RwsError(200, f"{path}: unexpected reply {body[:200]!r}") from exc

    def _field(self, path: str, key: str) -> str:
        state = self._request(path)
        if key not in state:
            raise RwsError(200, f"{path}: reply has no {key!r}: {state}")
        return str(state[key])

    def ctrlstate(self) -> str:
        """Controller state: "motoron", "motoroff", "guardstop", "emergencystop", ..."""
        return self._field("rw/panel/ctrlstate", "ctrlstate")

    def set_motors(self, on: bool) -> None:
        """Switch the motors on or off (AUTO mode only)."""
        form = {"ctrl-state": "motoron" if on else "motoroff"}
        self._request("rw/panel/ctrlstate", {"action": "setctrlstate"}, form)

    def opmode(self) -> str:
        """Operating mode: "AUTO", "MANR", "MANF", ..."""
        return self._field("rw/panel/opmode", "opmode")

    def rapid_running(self) -> bool:
        """Whether RAPID execution is running."""
        return self._field("rw/rapid/execution", "ctrlexecstate") == "running"

    def start_rapid(self) -> None:
        """Start RAPID in all tasks (continue from the program pointer, run once)."""
        self._request("rw/rapid/execution", {"action": "start"}, START_FORM)

    def stop_rapid(self) -> None:
        """Stop RAPID execution."""
        self._request("rw/rapid/execution", {"action": "stop"}, {"stopmode": "stop"})

    def reset_program_pointer(self) -> None:
        """Move the program pointer to main (RAPID must be stopped)."""
        self._request("rw/rapid/execution", {"action": "resetpp"}, {})

    def joints(self, arm: str) -> np.ndarray:
        """`arm`'s joint target from the motion system (rad, chain order 1-2-7-3-4-5-6)."""
        state = self._request(f"rw/motionsystem/mechunits/{MECHUNITS[arm]}/jointtarget")
        try:
            return jointtarget_to_chain(state)
        except (KeyError, ValueError) as exc:
            raise RwsError(200, f"jointtarget of {MECHUNITS[arm]}: unexpected reply {state}") from exc

    def read_symbol(self, task: str, name: str) -> str:
        """The value (a RAPID literal) of data `name` in `task` (e.g. "T_ROB_L")."""
        return self._field(f"rw/rapid/symbol/data/RAPID/{task}/{name}", "value")

    def write_symbol(self, task: str, name: str, value: str) -> None:
        """Set data `name` in `task` to the RAPID literal `value`."""
        self._request(f"rw/rapid/symbol/data/RAPID/{task}/{name}", {"action": "set"}, {"value": value})


def _message(detail: str) -> str:
    """The `status.msg` of an RWS JSON error body, else the body itself (shortened)."""
    try:
        return str(json.loads(detail)["status"]["msg"])
    except (ValueError, KeyError, TypeError):
        return detail[:200]
