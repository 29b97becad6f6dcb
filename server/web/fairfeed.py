"""One turn's parse budget, shared by every WebSocket connection read in pieces, lightest first.

websockets parses every frame of a read at once, so the transport parses the reads of a
connection not yet trusted a piece at a time (`transport.FEED_BYTES`). A piece a turn for each
connection still let N flooding sockets parse N pieces a turn: 200 sockets of empty pings took
another viewer's round trip to 0.6 s. Here all of them together parse at most `TURN_BYTES` a
turn of the event loop, and the connection that parsed least lately goes first, so a viewer's
message waits about one turn whatever the others send.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import math
import weakref
from typing import ClassVar, Protocol

TURN_BYTES = 4096
"""Bytes parsed in pieces per turn of the loop, every connection together (a few ms of tiny
frames at most)."""
USAGE_TAU_S = 1.0
"""How long a connection's parsing counts against its place in the queue (decay time)."""


class Fed(Protocol):
    """A connection with bytes to parse in pieces."""

    usage: Usage

    def wants_feed(self) -> bool:
        """Whether it holds bytes it may parse now (its app took what the last piece gave)."""
        ...

    def feed_piece(self) -> int:
        """Parse its next piece; the bytes parsed."""
        ...


class Usage:
    """Bytes a connection parsed lately, decaying with `USAGE_TAU_S`."""

    def __init__(self) -> None:
        self.value = 0.0
        self.at = 0.0

    def at_time(self, now: float) -> float:
        return self.value * math.exp(-(now - self.at) / USAGE_TAU_S)

    def add(self, n: int, now: float) -> None:
        self.value = self.at_time(now) + n
        self.at = now


class FairFeed:
    """The budget of one event loop (`of`)."""

    _loops: ClassVar[weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, FairFeed]] = (
        weakref.WeakKeyDictionary()
    )

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._left = TURN_BYTES
        self._waiting: list[tuple[float, int, Fed]] = []
        self._queued: set[int] = set()
        self._order = itertools.count()
        self._turn_due = False

    @classmethod
    def of(cls, loop: asyncio.AbstractEventLoop) -> FairFeed:
        feed = cls._loops.get(loop)
        if feed is None:
            feed = cls._loops[loop] = cls(loop)
        return feed

    def try_now(self, n: int) -> bool:
        """Whether `n` bytes may be parsed at once: no connection waits and this turn has room
        (then they are counted)."""
        if self._waiting or n > self._left:
            return False
        self._left -= n
        self._schedule()
        return True

    def submit(self, fed: Fed, usage: float) -> None:
        """Queue `fed` for a piece in a coming turn, behind connections that parsed less."""
        if id(fed) in self._queued:
            return
        self._queued.add(id(fed))
        heapq.heappush(self._waiting, (usage, next(self._order), fed))
        self._schedule()

    def _schedule(self) -> None:
        if not self._turn_due:
            self._turn_due = True
            self._loop.call_soon(self._turn)

    def _turn(self) -> None:
        self._turn_due = False
        self._left = TURN_BYTES
        again: list[Fed] = []
        while self._left > 0 and self._waiting:
            _, _, fed = heapq.heappop(self._waiting)
            self._queued.discard(id(fed))
            if fed.wants_feed():
                self._left -= fed.feed_piece()
                again.append(fed)
        for fed in again:
            if fed.wants_feed():
                self.submit(fed, fed.usage.at_time(self._loop.time()))
        if self._waiting:
            self._schedule()
