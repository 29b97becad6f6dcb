"""The FastAPI application: wiring of sessions, the GPU queue, encoders, jobs and routes."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import FastAPI, WebSocket
from fastapi.staticfiles import StaticFiles
from starlette.responses import PlainTextResponse

from server import ws as ws_endpoints
from server.api import router
from server.gpu import GpuQueue
from server.jobs import JobManager
from server.metrics import Metrics
from server.session import Session
from server.settings import ServerSettings
from server.steering_log import SteeringLog

log = logging.getLogger("scalesteer.app")
_SESSION_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


@dataclass
class SessionRegistry:
    """Live sessions by name; a session outlives its clients and its simulation."""

    factory: Callable[[str], Session]
    limit: int
    _sessions: dict[str, Session] = field(default_factory=dict)
    _lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    async def get_or_create(self, name: str) -> Session:
        from protocol import ErrorCode, ProtocolError

        if not _SESSION_NAME.match(name):
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE, f"invalid session name {name!r}", "hello.session"
            )
        async with self._lock:
            session = self._sessions.get(name)
            if session is None:
                if len(self._sessions) >= self.limit:
                    raise ProtocolError(
                        ErrorCode.TOO_LARGE, f"the server holds its limit of {self.limit} sessions"
                    )
                session = self._sessions[name] = self.factory(name)
            return session

    def get(self, name: str) -> Session | None:
        return self._sessions.get(name)

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
                    raise _BodyTooLargeError()
            return message

        try:
            await self.app(scope, counted, send)
        except _BodyTooLargeError:
            await PlainTextResponse(
                f"request body exceeds the upload limit of {self.limit} bytes", 413
            )(scope, receive, send)


class _BodyTooLargeError(Exception):
    pass


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
        encoders = ThreadPoolExecutor(max_workers=4, thread_name_prefix="encode")
        steering_log = SteeringLog(state_dir / "logs")
        upload_dir = state_dir / "uploads"
        upload_dir.mkdir(parents=True, exist_ok=True)

        def new_session(name: str) -> Session:
            return Session(name, settings, gpu, encoders, metrics, steering_log)

        state = AppState(
            settings=settings,
            gpu=gpu,
            encoders=encoders,
            metrics=metrics,
            steering_log=steering_log,
            sessions=SessionRegistry(new_session, settings.max_sessions),
            jobs=JobManager(state_dir / "jobs", gpu, encoders, metrics, settings.limits.max_atoms),
            upload_dir=upload_dir,
        )
        app.state.scalesteer = state
        try:
            yield
        finally:
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
    return app
