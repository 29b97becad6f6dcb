"""The FastAPI application: wiring of sessions, the GPU queue, encoders, jobs and routes."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import time
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import FastAPI, HTTPException, WebSocket
from fastapi.staticfiles import StaticFiles
from starlette.responses import PlainTextResponse

from protocol.messages import SESSION_NAME
from server import ws as ws_endpoints
from server.api import router
from server.auth import host_allowed
from server.encoder import ImageEncoder, select_encoder
from server.gpu import GpuQueue
from server.jobs import JobManager
from server.metrics import Metrics
from server.session import Session
from server.settings import ServerSettings
from server.steering_log import SteeringLog

log = logging.getLogger("scalesteer.app")
_SESSION_NAME = re.compile(SESSION_NAME)


@dataclass
class SessionRegistry:
    """Live sessions by name; a session outlives its clients and its simulation."""

    factory: Callable[[str], Session]
    limit: int
    _sessions: dict[str, Session] = field(default_factory=dict)
    _lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    async def get_or_create(self, name: str, create: bool = True) -> Session:
        from protocol import ErrorCode, ProtocolError

        if not _SESSION_NAME.match(name):
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE, f"invalid session name {name!r}", "hello.session"
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
class AppState:
    settings: ServerSettings
    gpu: GpuQueue
    encoders: ThreadPoolExecutor
    encoder: ImageEncoder
    metrics: Metrics
    steering_log: SteeringLog
    sessions: SessionRegistry
    jobs: JobManager
    upload_dir: Path


class UploadLimit:
    """Refuses request bodies over the upload limit while they stream in (413), so an oversized
    upload is never spooled to disk whole."""

    def __init__(self, app: Any, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(
        self,
        scope: MutableMapping[str, Any],
        receive: Callable[[], Awaitable[Any]],
        send: Callable[[Any], Awaitable[None]],
    ) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            await PlainTextResponse(
                f"request body exceeds the upload limit of {self.limit} bytes", 413
            )(scope, receive, send)
            return
        seen = 0

        async def counted() -> Any:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise _BodyTooLargeError(self.limit)
            return message

        try:
            await self.app(scope, counted, send)
        except _BodyTooLargeError:
            await PlainTextResponse(
                f"request body exceeds the upload limit of {self.limit} bytes", 413
            )(scope, receive, send)


class _BodyTooLargeError(HTTPException):
    """Raised while a body streams in; FastAPI answers it as the 413 it is."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body exceeds the upload limit of {limit} bytes")


class HostCheck:
    """Refuses HTTP requests and WebSocket handshakes whose Host header is not this server's."""

    def __init__(self, app: Any, settings: ServerSettings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(
        self,
        scope: MutableMapping[str, Any],
        receive: Callable[[], Awaitable[Any]],
        send: Callable[[Any], Awaitable[None]],
    ) -> None:
        if scope["type"] in ("http", "websocket"):
            host = dict(scope.get("headers") or []).get(b"host", b"").decode("latin-1")
            if not host_allowed(self.settings, host):
                if scope["type"] == "websocket":
                    await send(
                        {"type": "websocket.close", "code": 1008, "reason": "host not allowed"}
                    )
                    return
                await PlainTextResponse(f"host {host!r} not allowed", 403)(scope, receive, send)
                return
        await self.app(scope, receive, send)


def create_app(settings: ServerSettings) -> FastAPI:
    """Build the app; resources start with the app's lifespan and stop with it."""
    state_dir = settings.state_dir
    state_dir.mkdir(parents=True, exist_ok=True)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        metrics = Metrics()
        gpu = GpuQueue(
            device=settings.device,
            max_atoms=settings.limits.max_atoms,
            max_pixels=settings.limits.max_image_pixels,
        )
        encoders = ThreadPoolExecutor(
            max_workers=settings.encode_workers, thread_name_prefix="encode"
        )
        encoder = await asyncio.to_thread(select_encoder, settings.device)
        # shared by all sessions: encodes in flight never outnumber the encoder threads
        encode_slots = asyncio.Semaphore(settings.encode_workers)
        steering_log = SteeringLog(state_dir / "logs")
        upload_dir = state_dir / "uploads"
        upload_dir.mkdir(parents=True, exist_ok=True)

        def new_session(name: str) -> Session:
            return Session(
                name, settings, gpu, encoders, metrics, steering_log, encoder, encode_slots
            )

        state = AppState(
            settings=settings,
            gpu=gpu,
            encoders=encoders,
            encoder=encoder,
            metrics=metrics,
            steering_log=steering_log,
            sessions=SessionRegistry(new_session, settings.max_sessions),
            jobs=JobManager(state_dir / "jobs", gpu, encoders, metrics, settings.limits.max_atoms),
            upload_dir=upload_dir,
        )
        app.state.scalesteer = state
        await state.sessions.get_or_create("default")

        async def reaper() -> None:
            while True:
                await asyncio.sleep(min(30.0, settings.session_idle_s / 4))
                await state.sessions.reap(settings.session_idle_s)

        reaping = asyncio.create_task(reaper(), name="session-reaper")
        try:
            yield
        finally:
            reaping.cancel()
            await state.jobs.close()
            await state.sessions.close()
            await asyncio.to_thread(gpu.close)
            encoders.shutdown(wait=True)
            steering_log.close()

    app = FastAPI(
        title="scalesteer",
        description="Interactive multiscale visualization and steering of molecular simulations.",
        version="0.1.0",
        lifespan=lifespan,
    )
    app.include_router(router)

    @app.websocket("/ws/sim")
    async def ws_sim(websocket: WebSocket) -> None:
        await ws_endpoints.handle(websocket, app.state.scalesteer, "sim")

    @app.websocket("/ws/view")
    async def ws_view(websocket: WebSocket) -> None:
        await ws_endpoints.handle(websocket, app.state.scalesteer, "view")

    if (settings.client_dir / "index.html").is_file():
        app.mount("/", StaticFiles(directory=settings.client_dir, html=True), name="client")
    app.add_middleware(UploadLimit, limit=settings.max_upload_bytes + 1024 * 1024)
    app.add_middleware(HostCheck, settings=settings)
    return app
