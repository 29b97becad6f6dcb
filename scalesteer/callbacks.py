"""Calling the user's callbacks off the client's loop: on a thread of their own, newest first.

A callback that is slow (decoding every image into numpy, plotting) must neither stall the
WebSocket nor queue up a backlog: each subscription keeps one waiting value, and a newer one
replaces it (latest wins), as the server does for a slow viewer.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger("scalesteer.client")
FAILURE_LOG_S = 10.0
"""Least time between two log lines about a callback that keeps failing."""


class Subscription:
    """A callback subscribed to a session's images, observables, state or events; `close()`
    ends it (also as a context manager). `delivered` and `dropped` count values passed to the
    callback and values replaced before it could take them."""

    def __init__(self, callback: Callable[[Any], None], on_close: Callable[[Subscription], None]):
        if not callable(callback):
            raise TypeError(f"a subscription's callback must be callable, not {callback!r}")
        self.callback = callback
        self._on_close = on_close
        self._lock = threading.Lock()
        self._waiting: list[Any] = []  # at most one value
        self._ready = threading.Condition(self._lock)
        self._closed = False
        self.delivered = 0
        self.dropped = 0
        self.failures = 0
        """Calls of the callback that raised: the first is logged with its traceback, later
        ones at most every `FAILURE_LOG_S` as a count (ten images a second had printed ten
        tracebacks a second)."""
        self._failures_logged = 0
        self._failure_logged_at = float("-inf")
        self._thread = threading.Thread(target=self._run, name="scalesteer-callback", daemon=True)
        self._thread.start()

    def offer(self, value: Any) -> None:
        """Hand a value over (any thread); replaces one not yet taken."""
        with self._lock:
            if self._closed:
                return
            if self._waiting:
                self.dropped += 1
            self._waiting[:] = [value]
            self._ready.notify()

    def _run(self) -> None:
        while True:
            with self._lock:
                self._ready.wait_for(lambda: self._waiting or self._closed)
                if self._closed:
                    return
                value = self._waiting.pop()
            try:
                self.callback(value)
            except Exception as exc:
                self._failed(exc)
            with self._lock:
                self.delivered += 1

    def _failed(self, exc: Exception) -> None:
        self.failures += 1
        now = time.monotonic()
        if self.failures == 1:
            log.exception("scalesteer: a subscribed callback failed")
        elif now - self._failure_logged_at >= FAILURE_LOG_S:
            log.error(
                "scalesteer: a subscribed callback failed %d more times, the last with %s: %s",
                self.failures - self._failures_logged,
                type(exc).__name__,
                exc,
            )
        else:
            return
        self._failures_logged = self.failures
        self._failure_logged_at = now

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._ready.notify_all()
        self._on_close(self)
        if threading.current_thread() is not self._thread:
            self._thread.join(5.0)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
