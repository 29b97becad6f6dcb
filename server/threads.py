"""The server's threads named for the operating system too (`top -H`, `ps -L`, /proc), so the
CPU each one takes can be told apart: Python 3.11 keeps a thread's name to itself."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import threading

_PR_SET_NAME = 15


@functools.cache
def _libc() -> ctypes.CDLL:
    """The C library, loaded once: `find_library` runs a subprocess, which a pool's threads
    starting together beside warp's CPU kernels must not each do (two device threads doing so
    crashed the process)."""
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def name_thread(name: str | None = None) -> None:
    """Give the calling thread its Python name (`gpu_0`, `encode_1`, `uvicorn`), or `name`
    first, as its native name, cut to the 15 bytes Linux keeps; nothing where `prctl` is
    missing. Meant as a thread pool's `initializer` or the first call of a thread's target."""
    if name is not None:
        threading.current_thread().name = name
    with contextlib.suppress(OSError, AttributeError, TypeError):
        libc = _libc()
        native = threading.current_thread().name.encode("utf-8", "replace")[:15]
        libc.prctl(_PR_SET_NAME, ctypes.c_char_p(native), 0, 0, 0)
