"""ASGI middleware of the web edge: safe response headers, the Host and Origin checks, the
request body limits (per request and for all bodies being received at once), and the answer to
a request the server's stop cut off."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from fastapi import HTTPException
from starlette.requests import Request
from starlette.responses import JSONResponse, PlainTextResponse

from server.settings import ServerSettings
from server.web.access import request_token
from server.web.auth import host_allowed, origin_allowed, token_role
from server.web.spool import SPOOL, Spool

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Any]]
Send = Callable[[Any], Awaitable[None]]

FORM_BYTES = 1024 * 1024
"""What a request body may hold beyond `max_upload_bytes`: the form's own fields and part
headers around its files."""
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
"""Methods that change nothing on this server; every other one is checked for its Origin."""
CLOSE = {"Connection": "close"}
"""Sent with a refusal that comes before the request's body is read: the connection closes,
where kept open the server would read (and throw away) the rest of a body it refused."""


class UploadLimit:
    """Refuses request bodies over the upload limit while they stream in (413), so an oversized
    upload is never spooled to disk whole; and bodies that would take the bytes being received
    at once past the spool's total, or past the share of requests without the server token
    (503 with `Retry-After`), a declared length from its start. A body that pauses longer than
    `body_timeout_s` is answered 408 and lets go of its share: four uploads with the viewer
    token that declared 512 MiB each and then sent a byte now and then had held the whole
    spool, and every other upload was refused, for as long as they stayed open. The spool
    rides in the scope for `server.web.spool.SpoolingRequest`."""

    def __init__(self, app: Any, spool: Spool, settings: ServerSettings) -> None:
        self.app = app
        self.spool = spool
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        spool = self.spool
        scope[SPOOL] = spool
        headers = dict(scope.get("headers") or [])
        raw = headers.get(b"content-length")
        # h11 refuses a length that is not a number; 19 digits or more are past any limit
        digits = b"" if raw is None or not raw.strip().isdigit() else raw.strip()
        declared = 0 if not digits else int(digits) if len(digits) < 19 else spool.limit + 1
        if declared > spool.limit:
            await _too_large(spool.limit)(scope, receive, send)
            return
        viewer = token_role(self.settings, request_token(Request(scope))) != "steerer"
        if (refused := spool.take(declared, viewer)) is not None:
            await _spool_full(refused)(scope, receive, send)
            return
        held = declared
        seen = 0
        ended = False
        timeout = self.settings.body_timeout_s
        has_body = declared > 0 or b"transfer-encoding" in headers
        closed = _ClosingDelimiter.of(headers.get(b"content-type", b""))

        async def closing(message: Any) -> None:
            # a refusal sent before the body is in closes the connection (`CLOSE`)
            start = message["type"] == "http.response.start"
            if start and has_body and not ended and message["status"] >= 400:
                close = [(b"connection", b"close")]  # CLOSE
                message = {**message, "headers": [*message.get("headers", []), *close]}
            await send(message)

        async def counted() -> Any:
            nonlocal seen, held, ended
            if ended:  # the body is in; what follows (a disconnect) may wait as long as it likes
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), timeout)
            except TimeoutError:
                raise _BodyStalledError(timeout) from None
            if message["type"] == "http.request":
                ended = not message.get("more_body", False)
                seen += len(message.get("body", b""))
                if seen > spool.limit:
                    raise _BodyTooLargeError(spool.limit)
                if seen > held:  # past its declared length (or sent without one)
                    if (refused := spool.take(seen - held, viewer)) is not None:
                        raise _SpoolFullError(refused)
                    held = seen
                if closed is not None and not closed.feed(message.get("body", b""), ended):
                    raise _MultipartCutError(closed.mark)
            else:
                ended = True
            return message

        try:
            await self.app(scope, counted, closing)
        except _BodyTooLargeError:
            await _too_large(spool.limit)(scope, receive, send)
        except _SpoolFullError as exc:
            await _spool_full(exc.detail)(scope, receive, send)
        except _BodyStalledError as exc:
            await JSONResponse({"detail": exc.detail}, 408, headers=CLOSE)(scope, receive, send)
        finally:
            spool.give_back(held, viewer)


def _too_large(limit: int) -> JSONResponse:
    # as every other refusal of the API: {"detail": ...}
    return JSONResponse({"detail": _too_large_text(limit)}, 413, headers=CLOSE)


def _too_large_text(limit: int) -> str:
    files = limit - FORM_BYTES
    return (
        f"request body exceeds the upload limit of {limit} bytes ({files / 2**20:g} MiB of "
        f"files, max_upload_bytes, and {FORM_BYTES // 2**20} MiB for the form's other fields)"
    )


def _spool_full(reason: str) -> JSONResponse:
    return JSONResponse({"detail": reason}, 503, headers={"Retry-After": "5", **CLOSE})


class _BodyTooLargeError(HTTPException):
    """Raised while a body streams in; FastAPI answers it as the 413 it is."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, _too_large_text(limit))


class _SpoolFullError(HTTPException):
    """Raised while a body streams in past what the spool has left; answered as a 503."""

    def __init__(self, reason: str) -> None:
        super().__init__(503, reason, headers={"Retry-After": "5"})


class _ClosingDelimiter:
    """Watches a multipart body for its closing delimiter (`--boundary--`), across chunks.

    A body cut off before it (a client that died mid-upload, a proxy that truncated it) parses
    without error: the parts that ended are kept and the cut one is dropped. The request
    then ran without its file (answered as if none had been sent) or, cut inside a later
    field, with that field's default in silence."""

    def __init__(self, boundary: bytes) -> None:
        self.mark = b"--" + boundary + b"--"
        self._tail = b""
        self.seen = False

    @classmethod
    def of(cls, content_type: bytes) -> _ClosingDelimiter | None:
        """The watcher for a multipart content type with a boundary, else None."""
        kind, _, options = content_type.partition(b";")
        if kind.strip().lower() != b"multipart/form-data":
            return None
        for option in options.split(b";"):
            key, _, value = option.strip().partition(b"=")
            if key.strip().lower() == b"boundary" and value.strip().strip(b'"'):
                return cls(value.strip().strip(b'"'))
        return None

    def feed(self, chunk: bytes, last: bool) -> bool:
        """Take the next chunk; False once the body has ended without its closing delimiter
        (RFC 2046: it may be followed by an epilogue, so it is looked for anywhere)."""
        if not self.seen:
            keep = len(self.mark) - 1  # a delimiter split across chunks shows in tail + head
            self.seen = self.mark in self._tail + chunk[:keep] or self.mark in chunk
            self._tail = (self._tail + chunk)[-keep:] if len(chunk) < keep else chunk[-keep:]
        return self.seen or not last


class _MultipartCutError(HTTPException):
    """Raised when a multipart body ends before its closing delimiter; answered as a 400."""

    def __init__(self, mark: bytes) -> None:
        super().__init__(
            400,
            f"the multipart body ended before its closing boundary {mark.decode('latin-1')!r}: "
            "the upload was "
            "cut off or is malformed, and nothing was done with it",
        )


class _BodyStalledError(HTTPException):
    """Raised when a body pauses past its time; answered as a 408 (the connection closes)."""

    def __init__(self, timeout: float) -> None:
        super().__init__(
            408,
            f"the request's body stopped arriving for {timeout:g} s (body_timeout_s)",
            headers=CLOSE,
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
                refusal = PlainTextResponse(f"host {host!r} not allowed", 403, headers=CLOSE)
                await refusal(scope, receive, send)
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
                await JSONResponse({"detail": detail}, 403, headers=CLOSE)(scope, receive, send)
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


class StopAnswer:
    """A request whose handler is cancelled before its response began is answered 503, as JSON,
    saying the server is stopping. Only a stop cancels a request here (uvicorn, after giving
    open ones 5 s): a REST render cut off so was a plain-text 500 and a traceback in the log."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def watched(message: Any) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, watched)
        except asyncio.CancelledError:
            if started:
                raise
            detail = "the server is stopping and this request was cut off; send it again later"
            # the task ends here, answered: what cancelled it waits for nothing more from it
            headers = {"Retry-After": "30", **CLOSE}
            await JSONResponse({"detail": detail}, 503, headers=headers)(scope, receive, send)
