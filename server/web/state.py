"""The application's state: the one object every route and endpoint reaches the server through.

`AppState` holds the shared resources (settings, GPU queue, encoders, metrics, steering log,
jobs) and the `SessionRegistry` of live sessions. It is built by `server.web.app.create_app`'s
lifespan and read by the routes (`rest.py`) and WebSocket endpoints (`ws.py`).
"""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path

from protocol.messages import SESSION_NAME
from server.metrics import Metrics
from server.pipeline.encoder import ImageEncoder
from server.pipeline.gpu import GpuQueue
from server.pipeline.jobs import JobManager
from server.pipeline.recordings import RecordingStore
from server.session.services import Services
from server.session.session import Session
from server.session.steering_log import SteeringLog
from server.settings import ServerSettings
from server.web.auth import ClientBudgets, RateLimiter
from server.web.children import ReplayManager
from server.web.owners import Owners
from structures.selection_pool import SelectionPool

_SESSION_NAME = re.compile(SESSION_NAME)


@dataclass
class SessionRegistry:
    """Live sessions by name; a session outlives its clients and its simulation."""

    factory: Callable[[str], Session]
    limit: int
    secrets: tuple[str, ...] = ()
    """The server's tokens: no session is named after one (names reach logs and file names)."""
    _sessions: dict[str, Session] = field(default_factory=dict)
    _lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    async def get_or_create(self, name: str, create: bool = True) -> Session:
        from protocol import ErrorCode, ProtocolError

        if not _SESSION_NAME.match(name):
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE, f"invalid session name {name!r}", "hello.session"
            )
        if name in self.secrets:
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE,
                "a session may not be named after a token (its name reaches logs and files)",
                "hello.session",
            )
        async with self._lock:
            session = self._sessions.get(name)
            if session is None and not create:
                raise ProtocolError(
                    ErrorCode.NOT_FOUND, f"no session named {name!r}", "hello.session"
                )
            if session is None:
                if len(self._sessions) >= self.limit:
                    raise ProtocolError(
                        ErrorCode.TOO_LARGE, f"the server holds its limit of {self.limit} sessions"
                    )
                session = self._sessions[name] = self.factory(name)
            return session

    def get(self, name: str) -> Session | None:
        return self._sessions.get(name)

    def full(self, name: str) -> bool:
        """Whether session `name` could not be made now (it does not exist and the server
        holds its limit of sessions)."""
        return name not in self._sessions and len(self._sessions) >= self.limit

    async def reap(self, idle_s: float, keep: str = "default") -> None:
        """Close sessions nobody has used for `idle_s` (their GPU scenes go with them)."""
        now = time.monotonic()
        async with self._lock:
            stale = [
                s
                for name, s in self._sessions.items()
                if name != keep and s.idle_since is not None and now - s.idle_since > idle_s
            ]
            for session in stale:
                self._sessions.pop(session.id, None)
        for session in stale:
            await session.close()

    def all(self) -> list[Session]:
        return list(self._sessions.values())

    async def close(self) -> None:
        for session in self._sessions.values():
            await session.close()
        self._sessions.clear()


@dataclass
class Connections:
    """Open WebSockets: all of them, and per token (the server's, the viewers')."""

    total: int = 0
    by_token: dict[str, int] = field(default_factory=lambda: {"server": 0, "viewer": 0})
    waiting: dict[int, asyncio.Future[None]] = field(default_factory=dict)
    """Connections that have not said `hello` yet, oldest first: each one's notice to leave."""

    def make_room(self) -> bool:
        """Tell the connection that has waited longest without saying `hello` to leave, so a
        newcomer can have its place; False when every open connection has said it.

        Refusing the newcomer instead let anyone without a token lock the server: silent
        sockets, reopened as the hello timeout closed them, held every place, and a steerer
        with the server token was refused in most of its tries."""
        key = next(iter(self.waiting), None)
        if key is None:
            return False
        self.waiting.pop(key).set_result(None)
        return True


@dataclass
class AppState:
    settings: ServerSettings
    gpu: GpuQueue
    services: Services
    """What every session shares (the GPU queue as its render backend, encoders, log)."""
    sessions: SessionRegistry
    jobs: JobManager
    recordings: RecordingStore
    """Recordings of live sessions (frames, topology and steering log of a span)."""
    upload_dir: Path
    readers: asyncio.Semaphore
    """Untrusted files read at once (each read is a child process)."""
    viewer_renders: RateLimiter
    """`/api/render` calls by viewer-token holders, together."""
    connections: Connections = field(default_factory=Connections)
    budgets: ClientBudgets = field(default_factory=ClientBudgets)
    """WebSocket rate limits per client (role and remote address), across its connections."""
    replays: ReplayManager = field(default_factory=ReplayManager)
    """Replays opened from the dashboard (child processes)."""
    owners: Owners = field(default_factory=lambda: Owners(15.0))
    """Recordings and movies tied to the page that started them (ended when it leaves)."""

    @property
    def selections(self) -> SelectionPool:
        """The worker processes that evaluate selections (sessions, REST renders, jobs)."""
        return self.services.selections

    @property
    def metrics(self) -> Metrics:
        return self.services.metrics

    @property
    def encoder(self) -> ImageEncoder:
        return self.services.encoder

    @property
    def encoders(self) -> Executor:
        return self.services.encoders

    @property
    def steering_log(self) -> SteeringLog:
        return self.services.steering_log
