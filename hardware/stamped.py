"""A thread-safe "latest value" slot with its arrival time, the basis of every driver's watchdog."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class StaleDataError(RuntimeError):
    """A stream's latest value is missing or older than its watchdog allows."""


class Latest(Generic[T]):
    """The most recent value of a stream, stamped with `time.monotonic()` (s) when it arrived."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._lock = threading.Condition()
        self._value: T | None = None
        self._stamp = float("-inf")
        self._count = 0

    def put(self, value: T) -> None:
        """Store `value` as the newest reading and wake anyone waiting for one."""
        with self._lock:
            self._value, self._stamp = value, time.monotonic()
            self._count += 1
            self._lock.notify_all()

    @property
    def count(self) -> int:
        """How many values have arrived so far."""
        with self._lock:
            return self._count

    def age(self) -> float:
        """Seconds since the newest value arrived (inf when none has)."""
        with self._lock:
            return time.monotonic() - self._stamp

    def get(self, max_age_s: float) -> T:
        """The newest value; StaleDataError when none has arrived or it is older than `max_age_s` (s)."""
        with self._lock:
            value, age = self._value, time.monotonic() - self._stamp
        if value is None:
            raise StaleDataError(f"no {self.name} data received yet")
        if age > max_age_s:
            limit = f"limit {max_age_s * 1e3:.0f} ms"
            raise StaleDataError(f"{self.name} data is stale: last one {age * 1e3:.0f} ms ago ({limit})")
        return value

    def wait(self, timeout_s: float, after: int = 0) -> T:
        """Block until more than `after` values have arrived (at most `timeout_s` s); return the newest."""
        with self._lock:
            if not self._lock.wait_for(lambda: self._count > after, timeout=timeout_s):
                raise StaleDataError(f"no {self.name} data within {timeout_s:g} s")
            return self._value


def wait_for(condition: Callable[[], bool], timeout_s: float, poll_s: float = 0.005) -> bool:
    """Poll `condition` every `poll_s` s until it holds (True) or `timeout_s` s have passed (False)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)
    return True
