"""ASGI middleware of the web edge: safe response headers, the Host and Origin checks, and the
request body limits (per request and for all bodies being received at once)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from fastapi import HTTPException
from starlette.responses import JSONResponse, PlainTextResponse

from server.settings import ServerSettings
from server.web.auth import host_allowed, origin_allowed
from server.web.spool import SPOOL, Spool

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Any]]
Send = Callable[[Any], Awaitable[None]]

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
"""Methods that change nothing on this server; every other one is checked for its Origin."""


class UploadLimit:
    """Refuses request bodies over the upload limit while they stream in (413), so an oversized
    upload is never spooled to disk whole; and bodies that would take the bytes being received
    at once past the spool's total (503 with `Retry-After`), a declared length from its start.
    The spool rides in the scope for `server.web.spool.SpoolingRequest`."""

    def __init__(self, app: Any, spool: Spool) -> None:
        self.app = app
        self.spool = spool

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        spool = self.spool
        scope[SPOOL] = spool
        headers = dict(scope.get("headers") or [])
        raw = headers.get(b"content-length")
        declared = int(raw) if raw is not None and raw.isdigit() and len(raw) < 19 else 0
        if declared > spool.limit:
            await _too_large(spool.limit)(scope, receive, send)
            return
        if not spool.take(declared):
            await _spool_full(spool)(scope, receive, send)
            return
        held = declared
        seen = 0

        async def counted() -> Any:
            nonlocal seen, held
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > spool.limit:
                    raise _BodyTooLargeError(spool.limit)
                if seen > held:  # past its declared length (or sent without one)
                    if not spool.take(seen - held):
                        raise _SpoolFullError(spool)
                    held = seen
            return message

        try:
            await self.app(scope, counted, send)
        except _BodyTooLargeError:
            await _too_large(spool.limit)(scope, receive, send)
        except _SpoolFullError:
            await _spool_full(spool)(scope, receive, send)
        finally:
            spool.give_back(held)


def _too_large(limit: int) -> PlainTextResponse:
    return PlainTextResponse(f"request body exceeds the upload limit of {limit} bytes", 413)


def _spool_full(spool: Spool) -> PlainTextResponse:
    return PlainTextResponse(
        f"the server is receiving {spool.held} bytes of uploads already, its limit is "
        f"{spool.total} (max_spool_bytes); try again later",
        503,
        headers={"Retry-After": "5"},
    )


class _BodyTooLargeError(HTTPException):
    """Raised while a body streams in; FastAPI answers it as the 413 it is."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body exceeds the upload limit of {limit} bytes")


class _SpoolFullError(HTTPException):
    """Raised while a body streams in past what the spool has left; answered as a 503."""

    def __init__(self, spool: Spool) -> None:
        super().__init__(
            503,
            f"the server is receiving {spool.held} bytes of uploads already, its limit is "
            f"{spool.total} (max_spool_bytes); try again later",
            headers={"Retry-After": "5"},
        )


class HostCheck:
    """Refuses HTTP requests and WebSocket handshakes whose Host header is not this server's."""

    def __init__(self, app: Any, settings: ServerSettings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
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


class OriginCheck:
    """Refuses state-changing HTTP requests (POST, PUT, PATCH, DELETE) sent by a page of another
    origin, as the WebSocket endpoints do: without it, in the no-token loopback mode any web
    page the user opens could start recordings, jobs and replays. Scripts send no Origin."""

    def __init__(self, app: Any, settings: ServerSettings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] not in SAFE_METHODS:
            headers = dict(scope.get("headers") or [])
            origin = headers.get(b"origin")
            host = headers.get(b"host")
            text = origin.decode("latin-1") if origin is not None else None
            if not origin_allowed(
                self.settings, text, host.decode("latin-1") if host is not None else None
            ):
                detail = (
                    f"origin {text!r} may not {scope['method']} on this server: only its own "
                    "pages and --allow-origin origins may change its state"
                )
                await JSONResponse({"detail": detail}, 403)(scope, receive, send)
                return
        await self.app(scope, receive, send)


SECURITY_HEADERS: tuple[tuple[bytes, bytes], ...] = (
    (b"referrer-policy", b"no-referrer"),
    (b"x-content-type-options", b"nosniff"),
)
"""Sent with every HTTP response: the dashboard's URL carries its token, which no page it links
to may see in a `Referer`; and a response is what its type says, never sniffed as another."""


class SecurityHeaders:
    """Adds `SECURITY_HEADERS`, and a `Content-Security-Policy` that lets only this server's own
    pages and the `--allow-origin` origins frame the dashboard, to every HTTP response."""

    def __init__(self, app: Any, settings: ServerSettings) -> None:
        self.app = app
        ancestors = " ".join(["'self'", *(o for o in settings.allowed_origins if o != "*")])
        if "*" in settings.allowed_origins:
            ancestors = "*"
        self.headers = [
            *SECURITY_HEADERS,
            (b"content-security-policy", f"frame-ancestors {ancestors}".encode("latin-1")),
        ]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Any) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                extra = [(n, v) for n, v in self.headers if n not in present]
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        await self.app(scope, receive, with_headers)
