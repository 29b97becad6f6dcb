"""Work tied to the page that started it: recordings and movies of a live session end when
that page has left the session, so nothing a closed tab started runs on unseen.

A dashboard names itself in `hello.instance` (random per browser tab, kept across its
reconnections and reloads) and names that instance as the `owner` of what it starts. When the
last connection of an owner leaves the session, its work ends after `grace_s` (a reconnection
within it keeps the work going); a recording stops and keeps what it recorded, a movie takes
no more frames and finishes. Work started without an owner (scripts, or a page asked to keep
it running) is nobody's, and runs until it is stopped or reaches its bounds.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from server.session.session import Session

log = logging.getLogger("scalesteer.owners")

End = Callable[[str], Awaitable[None]]
"""Ends one piece of work, with the reason."""


@dataclass
class _Owned:
    session: Session
    instance: str
    ends: dict[str, End] = field(default_factory=dict)
    timer: asyncio.TimerHandle | None = None


@dataclass
class Owners:
    """The owned work of every session, by (session, instance)."""

    grace_s: float
    _owned: dict[tuple[str, str], _Owned] = field(default_factory=dict)
    _ending: set[asyncio.Task[None]] = field(default_factory=set)

    def own(self, session: Session, instance: str, work_id: str, end: End) -> None:
        """Tie `work_id` to `instance` in `session`: `end` runs once the instance has been
        gone from the session for `grace_s` (counted from now if it is not there now)."""
        key = (session.id, instance)
        owned = self._owned.setdefault(key, _Owned(session, instance))
        owned.ends[work_id] = end
        if not self._present(session, instance):
            self._arm(owned)

    def done(self, work_id: str) -> None:
        """`work_id` ended by itself (stopped, capped, finished): nothing to end any more."""
        for key, owned in list(self._owned.items()):
            owned.ends.pop(work_id, None)
            if not owned.ends:
                self._drop(key)

    def joined(self, session: Session, instance: str | None) -> None:
        owned = self._owned.get((session.id, instance)) if instance else None
        if owned is not None and owned.timer is not None:
            owned.timer.cancel()
            owned.timer = None

    def left(self, session: Session, instance: str | None) -> None:
        owned = self._owned.get((session.id, instance)) if instance else None
        if owned is not None and not self._present(session, owned.instance):
            self._arm(owned)

    @staticmethod
    def _present(session: Session, instance: str) -> bool:
        return any(c.instance == instance for c in session.clients.values())

    def _arm(self, owned: _Owned) -> None:
        if owned.timer is None:
            owned.timer = asyncio.get_running_loop().call_later(
                self.grace_s, self._start_expiry, owned
            )

    def _start_expiry(self, owned: _Owned) -> None:
        task = asyncio.get_running_loop().create_task(self._expire(owned))
        self._ending.add(task)
        task.add_done_callback(self._ending.discard)

    async def _expire(self, owned: _Owned) -> None:
        owned.timer = None
        if self._present(owned.session, owned.instance):
            return
        self._drop((owned.session.id, owned.instance))
        why = f"the page that started it left session {owned.session.id!r}"
        for work_id, end in list(owned.ends.items()):
            log.info("%s ends: %s", work_id, why)
            try:
                await end(why)
            except Exception:
                log.exception("ending %s failed", work_id)

    def _drop(self, key: tuple[str, str]) -> None:
        owned = self._owned.pop(key, None)
        if owned is not None and owned.timer is not None:
            owned.timer.cancel()

    def close(self) -> None:
        for key in list(self._owned):
            self._drop(key)
