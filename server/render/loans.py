"""Device results read back into page-locked host buffers that are lent, not copied.

A frame shown to a viewer lives on in several places on the host (the session's newest
positions, the frames a temporal filter smooths over, a recording's or a movie's queue), so a
read-back must give an array nobody writes again. A fresh pageable array per frame makes the
CUDA driver copy through a bounce buffer (about 2 ms for 1M atoms on an H200 host); a buffer
page-locked once is read at the link's speed. `HostLoans` keeps a few such buffers and lends
each as a numpy array: the buffer comes back to the pool only when the last array that views
it (slices and reshapes included) is gone, so a lent frame is never overwritten.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

import numpy as np
import numpy.typing as npt
import warp

wp: Any = warp  # warp's host API is unannotated


class _Loan:
    """Owns nothing; exposes a pooled buffer's memory to numpy so that every array viewing
    it keeps this object (and so the loan) alive."""

    __slots__ = ("__array_interface__", "__weakref__")

    def __init__(self, interface: dict[str, Any]) -> None:
        self.__array_interface__ = interface


class HostLoans:
    """Page-locked (n, 3) float32 host buffers for read-backs of one size, lent as arrays.

    `keep` buffers at most wait in the pool; more are made while more are out on loan (every
    one is page-locked once, then reused)."""

    def __init__(self, n: int, keep: int = 4) -> None:
        self.n = n
        self.keep = keep
        self._free: list[Any] = []
        self._lock = threading.Lock()
        self.made = 0
        """Buffers page-locked so far (a pool that keeps up makes few)."""

    def lend(self) -> tuple[Any, npt.NDArray[np.float32]]:
        """(the warp host array to copy into, the (n, 3) numpy array lent): write the first
        before handing the second out; it returns to the pool when the array is gone."""
        with self._lock:
            owner = self._free.pop() if self._free else None
        if owner is None:
            owner = wp.empty(max(self.n, 1), dtype=wp.vec3, device="cpu", pinned=True)
            self.made += 1
        interface = {
            "shape": (self.n, 3),
            "typestr": "<f4",
            "data": (int(owner.ptr), False),
            "version": 3,
        }
        loan = _Loan(interface)
        array: npt.NDArray[np.float32] = np.asarray(loan)
        weakref.finalize(loan, self._give_back, owner)
        return owner, array

    def _give_back(self, owner: Any) -> None:
        with self._lock:
            if len(self._free) < self.keep:
                self._free.append(owner)

    @property
    def waiting(self) -> int:
        """Buffers in the pool now (not lent)."""
        with self._lock:
            return len(self._free)
