"""The transports under the app: uvicorn's protocols, with the limits uvicorn lacks.

HTTP: uvicorn's h11 protocol with a deadline for a request's headers (`guarded_http`).

WebSocket: uvicorn's sans-I/O protocol with a small message limit until the peer has said who
it is.

uvicorn applies one `ws_max_size` to every connection before the application sees a byte; with
the simulations' limit (64 MiB) anyone could make the server buffer that much per socket without
a token. Here the limit starts at the viewers' (256 KiB) and the application raises it, through a
scope extension, only for a simulation whose `hello` was accepted. Frames over the limit are
refused from their header, before their payload is read (close code 1009).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, MutableMapping
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

MESSAGE_LIMIT = "scalesteer.message_limit"
"""Scope extension: `{"set": callable(int)}` sets this connection's incoming message limit."""


def guarded_protocol(pre_hello_bytes: int) -> type[WebSocketsSansIOProtocol]:
    """A protocol class whose connections accept at most `pre_hello_bytes` per message until
    the application raises the limit."""

    class GuardedWebSocketProtocol(WebSocketsSansIOProtocol):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.conn.max_message_size = min(pre_hello_bytes, self.config.ws_max_size)

        def handle_connect(self, event: Any) -> None:
            super().handle_connect(event)
            scope = getattr(self, "scope", None)
            if scope is not None:
                scope["extensions"][MESSAGE_LIMIT] = {"set": self._set_limit}

        def _set_limit(self, size: int) -> None:
            self.conn.max_message_size = min(int(size), self.config.ws_max_size)

    return GuardedWebSocketProtocol


def raise_limit(scope: MutableMapping[str, Any], size: int) -> None:
    """Let this connection send messages of up to `size` bytes (a no-op on other servers)."""
    extension = scope.get("extensions", {}).get(MESSAGE_LIMIT)
    setter: Callable[[int], None] | None = extension.get("set") if extension else None
    if setter is not None:
        setter(size)


def guarded_http(header_timeout_s: float) -> type[H11Protocol]:
    """uvicorn's h11 protocol with a deadline for a request's headers.

    uvicorn times out only an idle keep-alive connection, after a response; a connection that
    opens and sends nothing, or part of a request's headers and then nothing, is held for as
    long as its peer likes (500 such connections were all still open after 20 s). Here a
    connection must complete a request's headers within `header_timeout_s` of opening, or of
    the first byte after its last response; one that sent part of them is answered 408, one
    that sent nothing is closed. A request's body and a WebSocket are not timed by this."""

    class HeaderTimedProtocol(H11Protocol):
        _header_deadline: asyncio.TimerHandle | None = None
        _partial = False

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._header_deadline = self.loop.call_later(header_timeout_s, self._headers_late)

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            waiting = self.conn.their_state is h11.IDLE and not self.transport.is_closing()
            self._partial = waiting
            if not waiting:
                self._stop_deadline()
            elif self._header_deadline is None:
                self._header_deadline = self.loop.call_later(header_timeout_s, self._headers_late)

        def connection_lost(self, exc: Exception | None) -> None:
            self._stop_deadline()
            super().connection_lost(exc)

        def _stop_deadline(self) -> None:
            if self._header_deadline is not None:
                self._header_deadline.cancel()
                self._header_deadline = None

        def _headers_late(self) -> None:
            self._header_deadline = None
            if self.conn.their_state is not h11.IDLE or self.transport.is_closing():
                return
            if self._partial:
                self.transport.write(_late_headers(header_timeout_s))
            self.transport.close()

    return HeaderTimedProtocol


def _late_headers(timeout_s: float) -> bytes:
    body = f"the request's headers did not arrive within {timeout_s:g} s\n".encode()
    return (
        b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
        b"connection: close\r\ncontent-length: " + str(len(body)).encode() + b"\r\n\r\n" + body
    )
