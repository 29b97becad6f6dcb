"""The interpreter's heap in a long-running server, and the cyclic garbage collector's pauses.

A full collection (generation 2) walks every container object alive, and while it runs no
thread runs Python: not the event loop, not the device thread, not the encoders. With the
server's own modules loaded (about 190,000 objects) and a 1M-atom topology (its per-atom lists
of names, elements, residues) one such collection took 135 ms on the H200's host, once or twice
a minute at 60 frames/s, and a steering change that met it waited that long
(benchmarks/HISTORY.md, "Collector pauses").

`settle` collects once and moves every object still alive into the collector's permanent
generation (`gc.freeze`): later collections walk only what is newer, frames, messages and
images, which die young. Reference counting still frees frozen objects once nothing refers to
them (a topology replaced by the next); only a reference cycle among them would outlive its use,
until the process ends.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import time
from typing import Any

log = logging.getLogger("scalesteer.heap")

LARGE_TOPOLOGY = 100_000
"""Atoms from which a new topology settles the heap (its lists are then worth taking out of
the collector's walk; a smaller one costs a full collection more than it saves)."""


def settle() -> float:
    """Collect what is garbage now, then freeze the rest; returns the milliseconds it took (a
    full collection, once per large topology: `Session.on_topology` calls it)."""
    t0 = time.perf_counter()
    gc.collect()
    gc.freeze()
    ms = (time.perf_counter() - t0) * 1e3
    log.info("heap settled: %d objects frozen in %.0f ms", gc.get_freeze_count(), ms)
    return ms


def give_back_memory() -> None:
    """Return the heap freed since to the system (glibc keeps freed memory in its arenas: after
    ten 640x480 SVT-AV1 encoders closed, the process kept 117 of their 171 MB until this ran,
    and 23 after). Called from a thread when video encoders close; a no-op without glibc."""
    global _TRIM
    if _TRIM is None:
        try:
            _TRIM = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _TRIM = False
    if _TRIM:
        _TRIM(0)


_TRIM: Any = None
"""glibc's `malloc_trim`, False where there is none."""
