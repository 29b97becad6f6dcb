"""One asyncio event loop on a daemon thread: every WebSocket of the client lives on it.

The notebook's own thread (and its own event loop, which Jupyter runs) never waits on a socket:
links read and write on this loop, and the blocking API hands it coroutines (`run`) and waits
for their result with a timeout.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

T = TypeVar("T")

_lock = threading.Lock()
_loop: asyncio.AbstractEventLoop | None = None


def loop() -> asyncio.AbstractEventLoop:
    """The client's event loop, started on first use."""
    global _loop
    with _lock:
        if _loop is None or _loop.is_closed():
            ready = threading.Event()
            new = asyncio.new_event_loop()

            def main() -> None:
                asyncio.set_event_loop(new)
                new.call_soon(ready.set)
                new.run_forever()

            threading.Thread(target=main, name="scalesteer-client", daemon=True).start()
            ready.wait()
            _loop = new
        return _loop


def submit(coroutine: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
    """Run `coroutine` on the client's loop; its result arrives in the returned future."""
    return asyncio.run_coroutine_threadsafe(coroutine, loop())


def run(coroutine: Coroutine[Any, Any, T], timeout: float | None) -> T:
    """Run `coroutine` on the client's loop and wait for its result (any thread but the
    loop's own). A timeout cancels it and raises `TimeoutError`."""
    if in_loop():
        coroutine.close()
        raise RuntimeError("a blocking scalesteer call was made on the client's own thread")
    future = submit(coroutine)
    try:
        return future.result(timeout)
    except concurrent.futures.TimeoutError:
        future.cancel()
        raise TimeoutError(f"no answer from the scalesteer server within {timeout} s") from None


def call_soon(callback: Callable[..., Any], *args: Any) -> None:
    """Call `callback(*args)` on the client's loop (from any thread)."""
    loop().call_soon_threadsafe(callback, *args)


def in_loop() -> bool:
    """Whether the caller runs on the client's loop thread."""
    try:
        return asyncio.get_running_loop() is _loop
    except RuntimeError:
        return False
