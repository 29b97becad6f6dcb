"""Which work a device's thread takes next: live sessions first, one-off renders and jobs
in turn.

A device's thread had taken its work in submission order, so a few large REST renders queued
by one client (five with the viewer token, its burst) held every live view on that device until
all of them were drawn: a steerer's image of a session waited 33 s behind three 1920x1080
volume renders on the CPU device, and a 64x48 render 193 s behind six. Now each piece of work
has a rank by its slot (`rank_of`: a live session's work 0, a one-off REST render 1, a batch
job 2) and the thread takes the oldest of the lowest rank, so a live view waits for at most the
render already under way. So that a session that keeps its device busy does not starve the
rest, the oldest work takes the next turn once it has waited `AGE_S` and work of a better rank
ran for `SHARE` of its wait: a device that live work leaves idle at times takes the rest then,
and one that live work fills gives the rest a fifth of its time. (Taking turns piece by piece
had let each live render be followed by a one-off one: on the CPU device, where those take
seconds, a steerer's image that needed two live renders waited for two of them.) Within a rank,
and so within a slot (a slot's work has one rank), the order is submission order: a slot's
renderer is dropped after its last render. A release (`GpuQueue.release`) is taken in the live
turn: its caller has awaited the slot's work.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any

AGE_S = 0.5
"""Least wait (s) after which work takes its turn ahead of better work (`SHARE`)."""
SHARE = 0.8
"""...once better work ran for this share of its wait."""
LIVE, ONE_OFF, JOB = 0, 1, 2


def rank_of(slot: str | None) -> int:
    """A slot's rank: live sessions (and work for no slot) first, one-off renders, then jobs."""
    if slot is None or slot.startswith("session:") or slot == "warm-up":
        return LIVE
    if slot.startswith("job:"):
        return JOB
    return ONE_OFF


class _Item:
    __slots__ = ("args", "better_then", "fn", "future", "rank", "seq", "since")

    def __init__(
        self,
        rank: int,
        seq: int,
        since: float,
        better_then: float,
        fn: Callable[..., Any],
        args: tuple[Any, ...],
    ) -> None:
        self.rank, self.seq, self.since = rank, seq, since
        self.better_then = better_then
        """Seconds work of a better rank had run in all when this was queued."""
        self.fn, self.args = fn, args
        self.future: Future[Any] = Future()


class TurnExecutor(Executor):
    """One worker thread taking its work by rank (`submit_ranked`), with the turns of work
    that waited long (module docstring). `submit` is rank 0 (`LIVE`). `clock` is for tests."""

    def __init__(
        self,
        initializer: Callable[[], None] | None = None,
        age_s: float = AGE_S,
        share: float = SHARE,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._initializer = initializer
        self._age_s = age_s
        self._share = share
        self._clock = clock
        self._ran: dict[int, float] = {}  # seconds each rank's work has run in all
        self._lock = threading.Condition()
        self._heap: list[tuple[int, int, _Item]] = []
        self._waiting: dict[int, _Item] = {}  # seq -> item, for the oldest by submission
        self._seq = itertools.count()
        self._shutdown = False
        self._thread: threading.Thread | None = None

    def submit_ranked(self, rank: int, fn: Callable[..., Any], /, *args: Any) -> Future[Any]:
        with self._lock:
            if self._shutdown:
                raise RuntimeError("cannot schedule new work after shutdown")
            item = _Item(rank, next(self._seq), self._clock(), self._better(rank), fn, args)
            heapq.heappush(self._heap, (rank, item.seq, item))
            self._waiting[item.seq] = item
            if self._thread is None:
                self._thread = threading.Thread(target=self._work, daemon=True)
                self._thread.start()
            self._lock.notify()
        return item.future

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        if kwargs:
            return self.submit_ranked(LIVE, lambda: fn(*args, **kwargs))
        return self.submit_ranked(LIVE, fn, *args)

    def _next(self) -> _Item:
        """The item to run now (the lock held, something waiting)."""
        while self._heap[0][2].seq not in self._waiting:  # taken out of turn before
            heapq.heappop(self._heap)
        first = self._heap[0][2]
        oldest = self._waiting[min(self._waiting)]
        waited = self._clock() - oldest.since
        aged = (
            oldest.rank > first.rank
            and waited >= self._age_s
            and self._better(oldest.rank) - oldest.better_then >= self._share * waited
        )
        item = oldest if aged else first
        del self._waiting[item.seq]
        if item is first:
            heapq.heappop(self._heap)
        return item

    def _work(self) -> None:
        if self._initializer is not None:
            self._initializer()
        while True:
            with self._lock:
                self._lock.wait_for(lambda: self._waiting or self._shutdown)
                if not self._waiting:
                    return
                item = self._next()
            if not item.future.set_running_or_notify_cancel():
                continue
            started = self._clock()
            try:
                result = item.fn(*item.args)
            except BaseException as exc:
                item.future.set_exception(exc)
            else:
                item.future.set_result(result)
            finally:
                with self._lock:
                    ran = self._clock() - started
                    self._ran[item.rank] = self._ran.get(item.rank, 0.0) + ran

    def _better(self, rank: int) -> float:
        """Seconds work of a better rank than `rank` has run in all (the lock held)."""
        return sum(t for r, t in self._ran.items() if r < rank)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._lock:
            self._shutdown = True
            if cancel_futures:
                for item in self._waiting.values():
                    item.future.cancel()
                self._waiting.clear()
                self._heap.clear()
            self._lock.notify_all()
            thread = self._thread
        if wait and thread is not None:
            thread.join()
