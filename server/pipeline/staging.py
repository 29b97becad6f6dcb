"""Frames copied into page-locked host memory as they arrive, off the device thread.

A simulation's frame sits in ordinary (pageable) memory, and a CUDA copy from there runs through
a bounce buffer and holds the calling thread for all of it: about 3.4 ms of the device thread
per 12 MB frame (1M atoms) on an H200 host, time that every render, and so every steering
change, waits behind. A `FrameStager` copies each new frame into one of a few page-locked
buffers on a thread of its own as the frame arrives (numpy copies without the interpreter
lock), so when the frame's render comes the device reads it from there asynchronously.

One thread copied a 100M-atom frame (1.2 GB) in 106-129 ms on an H200 host, three to four
frames' worth of render: a large frame is copied in slices by several threads (`COPY_THREADS`;
33-55 ms on 8), each slice a plain memory copy.

A buffer goes free -> writing (the stage thread copies into it) -> ready -> in use (a render
uploads from it) -> free. A ready buffer whose frame was superseded before any render took it
is reused for a newer frame; a buffer in use is never written.
"""

from __future__ import annotations

import enum
import itertools
import logging
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from server.threads import name_thread

log = logging.getLogger("scalesteer.gpu")

BUFFERS = 3
"""One a render uploads from, the newest frame ready, the next one being copied."""

COPY_THREADS = max(1, min(8, len(os.sched_getaffinity(0)) // 2))
"""Threads that copy one large frame's slices at once (half the cores this process may run
on, at most 8; one below 4 cores, where nothing is sliced)."""
SLICE_BYTES = 32 << 20
"""A frame is cut into slices of at least this size: one under two slices (64 MiB, 5.6M atoms)
is copied by the stage thread alone."""
_slicers: ThreadPoolExecutor | None = None
_slicers_lock = threading.Lock()


@dataclass(frozen=True)
class Staging:
    """How frames are staged: the threads that copy a large one, and how long a render waits
    for its frame's copy before it uploads from the frame itself."""

    copy_threads: int | None = None
    """None: `COPY_THREADS`."""
    min_wait_s: float = 0.005
    """Least a render waits for its frame's copy (a 12 MB copy takes 2-3 ms), and the most it
    waits for a copy not yet begun (the stage thread is busy elsewhere)."""
    pageable_bytes_per_s: float = 5e9
    """Below what an upload from pageable memory reaches (6.9 GB/s measured for 1.2 GB on an
    H200 host): a copy under way finishes sooner than such an upload of the whole frame would.
    `math.inf`: never wait longer than `min_wait_s` (the staging of before 2026-11-29)."""

    def wait_s(self, n_atoms: int) -> float:
        """How long a render waits for a copy of `n_atoms` under way: as long as an upload
        from the frame itself would take. A 100M-atom frame gave up after 5 ms and uploaded
        from pageable memory for 145-175 ms while its copy went on beside it."""
        return max(self.min_wait_s, n_atoms * 12 / self.pageable_bytes_per_s)


def copy_rows(
    dst: npt.NDArray[np.float32], src: npt.NDArray[np.float32], threads: int | None = None
) -> None:
    """`dst[:] = src`, in slices copied by up to `threads` threads (None: `COPY_THREADS`) when
    it is large (numpy copies without the interpreter lock); returns once every slice is
    copied."""
    slices = min(COPY_THREADS if threads is None else threads, src.nbytes // SLICE_BYTES)
    if slices < 2:
        np.copyto(dst, src, casting="same_kind")
        return
    global _slicers
    with _slicers_lock:
        if _slicers is None:
            _slicers = ThreadPoolExecutor(
                COPY_THREADS, thread_name_prefix="stage-slice", initializer=name_thread
            )
        pool = _slicers
    cuts = np.linspace(0, len(src), slices + 1).astype(int)
    jobs = [
        pool.submit(np.copyto, dst[a:b], src[a:b], casting="same_kind")
        for a, b in itertools.pairwise(cuts.tolist())
    ]
    wait(jobs)  # every slice has stopped writing before a failed one is reported
    for job in jobs:
        job.result()


Allocate = Callable[[int], tuple[object, npt.NDArray[np.float32]]]
"""n atoms -> (the allocation to keep alive, its (n, 3) float32 view)."""


def pinned(n: int) -> tuple[object, npt.NDArray[np.float32]]:
    """A page-locked (n, 3) float32 host buffer (warp allocates it for the CUDA driver)."""
    import warp

    wp: Any = warp  # warp's host API is unannotated
    owner = wp.empty(max(n, 1), dtype=wp.vec3, device="cpu", pinned=True)
    view: npt.NDArray[np.float32] = owner.numpy().view(np.float32).reshape(-1, 3)[:n]
    return owner, view


class State(enum.Enum):
    FREE = "free"
    WRITING = "writing"
    READY = "ready"
    IN_USE = "in use"


@dataclass(eq=False)
class _Buffer:
    owner: object
    array: npt.NDArray[np.float32]
    positions_id: int = -1
    state: State = State.FREE
    done: threading.Event = field(default_factory=threading.Event)
    started: threading.Event = field(default_factory=threading.Event)
    """Set once the stage thread begins the copy (a copy may queue behind others)."""


class FrameStager:
    """Page-locked copies of one slot's newest frames of `n` atoms; `offer` is called as
    frames arrive, `take` and `release` by the render that uploads one."""

    def __init__(
        self,
        n: int,
        pool: Executor,
        allocate: Allocate = pinned,
        count: int = BUFFERS,
        policy: Staging = Staging(),
    ) -> None:
        self.n = n
        self._pool = pool
        self.policy = policy
        self._lock = threading.Lock()
        self._buffers = [_Buffer(*allocate(n)) for _ in range(count)]

    def offer(self, positions_id: int, positions: npt.NDArray[np.float32]) -> bool:
        """Copy frame `positions_id` into a buffer on the stage thread; False (and nothing
        copied) when every buffer is being written or uploaded from."""
        if positions.shape != (self.n, 3):
            raise ValueError(f"a frame of shape {positions.shape} offered to a stager of {self.n}")
        with self._lock:
            buf = self._pick()
            if buf is None:
                return False
            buf.state, buf.positions_id = State.WRITING, positions_id
            buf.done, buf.started = threading.Event(), threading.Event()
        try:
            self._pool.submit(self._copy, buf, positions)
        except RuntimeError:  # the pool is shut down: the server is stopping
            with self._lock:
                buf.state = State.FREE
            return False
        return True

    def _pick(self) -> _Buffer | None:
        for buf in self._buffers:
            if buf.state is State.FREE:
                return buf
        ready = [b for b in self._buffers if b.state is State.READY]
        return min(ready, key=lambda b: b.positions_id) if ready else None

    def _copy(self, buf: _Buffer, positions: npt.NDArray[np.float32]) -> None:
        buf.started.set()
        ok = False
        try:
            copy_rows(buf.array, positions, self.policy.copy_threads)
            ok = True
        except Exception:  # the render then uploads the frame from where it is
            log.exception("staging a frame in page-locked memory failed")
        with self._lock:
            buf.state = State.READY if ok else State.FREE
            buf.done.set()

    def take(
        self, positions_id: int, wait_s: float | None = None, start_wait_s: float | None = None
    ) -> npt.NDArray[np.float32] | None:
        """The page-locked copy of frame `positions_id`, now in use until `release`; waits up
        to `wait_s` for a copy under way, and at most `start_wait_s` of that for a copy still
        queued to begin (the stage thread is busy elsewhere: a long wait would be spent on
        another copy); both None: the policy's. None when there is no copy of that frame (it
        came while every buffer was busy) or it is not done in time."""
        if wait_s is None:
            wait_s = self.policy.wait_s(self.n)
            start_wait_s = self.policy.min_wait_s if start_wait_s is None else start_wait_s
        with self._lock:
            buf = next(
                (
                    b
                    for b in self._buffers
                    if b.positions_id == positions_id and b.state in (State.WRITING, State.READY)
                ),
                None,
            )
            if buf is None:
                return None
            done, started = buf.done, buf.started
        t0 = time.monotonic()
        if start_wait_s is not None and not started.wait(min(wait_s, start_wait_s)):
            return None
        if not done.wait(max(0.0, wait_s - (time.monotonic() - t0))):
            return None
        with self._lock:
            if buf.state is not State.READY or buf.positions_id != positions_id:
                return None  # reused for a newer frame meanwhile
            buf.state = State.IN_USE
            return buf.array

    def newest(self, after: int) -> tuple[int, npt.NDArray[np.float32]] | None:
        """The newest ready copy of a frame after `after` (its id and array), now in use until
        `release`; None when no copy newer than that is ready (a copy still being written is not
        waited for)."""
        with self._lock:
            ready = [b for b in self._buffers if b.state is State.READY and b.positions_id > after]
            if not ready:
                return None
            buf = max(ready, key=lambda b: b.positions_id)
            buf.state = State.IN_USE
            return buf.positions_id, buf.array

    def release(self, array: npt.NDArray[np.float32]) -> None:
        """The upload from `array` is complete: its buffer may take a new frame."""
        with self._lock:
            for buf in self._buffers:
                if buf.array is array:
                    buf.state = State.FREE

    def states(self) -> list[State]:
        with self._lock:
            return [b.state for b in self._buffers]
