"""ASGI middleware of the web edge: the upload size cap and the Host header check."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from fastapi import HTTPException
from starlette.responses import PlainTextResponse

from server.settings import ServerSettings
from server.web.auth import host_allowed


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
