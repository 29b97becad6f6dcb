"""The transports under the app: uvicorn's protocols, with the limits uvicorn lacks.

HTTP: uvicorn's h11 protocol with a deadline for a request's headers and a size limit on them
(`guarded_http`).

WebSocket: uvicorn's sans-I/O protocol with a small message limit until the peer has said who
it is, and an answer to an upgrade request websockets cannot parse.

uvicorn applies one `ws_max_size` to every connection before the application sees a byte; with
the simulations' limit (64 MiB) anyone could make the server buffer that much per socket without
a token. Here the limit starts at the viewers' (256 KiB) and the application raises it, through a
scope extension, only for a simulation whose `hello` was accepted. Frames over the limit are
refused from their header, before their payload is read (close code 1009).
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Callable, MutableMapping
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

MAX_HEAD_BYTES = 64 * 1024
"""The most a request's line and headers may take: a long query string or many cookies fit."""
_HEAD_END = re.compile(rb"\n\r?\n")  # h11's own: lines may end in a bare newline
MAX_FRAGMENTS = 1024
"""Fragments one WebSocket message may come in: a simulation's largest (64 MiB) comes in 256 of
256 KiB (`protocol.fragments`), a browser's in one."""
MESSAGE_LIMIT = "scalesteer.message_limit"
"""Scope extension: `{"set": callable(int)}` sets this connection's incoming message limit."""


def guarded_protocol(pre_hello_bytes: int, stall_s: float = 30.0) -> type[WebSocketsSansIOProtocol]:
    """A protocol class whose connections accept at most `pre_hello_bytes` per message until
    the application raises the limit, and are cut (`transport.abort`) once closed or unable to
    write for `stall_s` while their peer does not read.

    asyncio's `close()` waits for the bytes already written to drain. A peer that stops
    reading never lets them: its connection stayed open after every timeout had closed it,
    its handler waited on the write for ever, and it kept its place among `max_connections`,
    so enough such peers locked everyone else out."""

    class GuardedWebSocketProtocol(WebSocketsSansIOProtocol):
        _watch: asyncio.TimerHandle | None = None
        _stuck_since: float | None = None
        _refused = False

        def handle_cont(self, event: Any) -> None:
            # websockets counts a message's payload against its limit, not its fragments:
            # endless empty ones grew the list uvicorn keeps them in without bound
            if self._refused:
                return
            if len(self.frames) >= MAX_FRAGMENTS:
                self._refused = True
                self.frames = []
                self.conn.fail(1009, f"a message in more than {MAX_FRAGMENTS} fragments")
                self.transport.write(b"".join(self.conn.data_to_send()))
                self.close_sent = True
                self.transport.close()
                return
            super().handle_cont(event)

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.conn.max_message_size = min(pre_hello_bytes, self.config.ws_max_size)

        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._watch = self.loop.call_later(stall_s / 4, self._check_stall)

        def connection_lost(self, exc: Exception | None) -> None:
            if self._watch is not None:
                self._watch.cancel()
                self._watch = None
            super().connection_lost(exc)

        def _check_stall(self) -> None:
            """Every quarter of `stall_s`: cut a connection that has been closing, or unable
            to write, for `stall_s` (its peer reads nothing)."""
            self._watch = None
            stuck = self.transport.is_closing() or not self.writable.is_set()
            now = self.loop.time()
            if not stuck:
                self._stuck_since = None
            elif self._stuck_since is None:
                self._stuck_since = now
            elif now - self._stuck_since >= stall_s:
                client = f"{self.client[0]}:{self.client[1]}" if self.client else "a client"
                self.logger.warning(
                    "%s: a WebSocket whose peer read nothing for %g s cut", client, stall_s
                )
                self.transport.abort()
                return
            self._watch = self.loop.call_later(stall_s / 4, self._check_stall)

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            # websockets refuses an upgrade whose request it cannot parse (a line over 8 KiB,
            # over 128 headers) with an answer uvicorn never writes: the connection stayed
            # open, unanswered and untimed, for as long as the peer liked
            if (
                not self.handshake_initiated
                and self.conn.handshake_exc is not None
                and not self.transport.is_closing()
            ):
                self.transport.write(b"".join(self.conn.data_to_send()))
                self.transport.close()

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
    """uvicorn's h11 protocol with a deadline for a request's headers and a limit on their size.

    uvicorn times out only an idle keep-alive connection, after a response; a connection that
    opens and sends nothing, or part of a request's headers and then nothing, is held for as
    long as its peer likes (500 such connections were all still open after 20 s). Here a
    connection must complete a request's headers within `header_timeout_s` of opening, or of
    the first byte after its last response; one that sent part of them is answered 408, one
    that sent nothing is closed. A request's body and a WebSocket are not timed by this.

    h11 refuses an unfinished head once its buffer passes a size, so whether a long request
    was served depended on how the network cut it: one of 60 KB was answered when it came in
    one piece and reset when it came in two. Here a head is served whole up to `MAX_HEAD_BYTES`
    however it arrives, alone or after others on a kept-alive connection (h11's own limit is
    set to the same size, and the check here comes before its parse). One past it is answered
    414 (the request line) or 431 (the line and headers); what the peer still sends is read
    and dropped, so that the client sees the answer, until it closes or the deadline does."""

    class HeaderTimedProtocol(H11Protocol):
        _header_deadline: asyncio.TimerHandle | None = None
        _partial = False
        _refused = False

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._header_deadline = self.loop.call_later(header_timeout_s, self._headers_late)

        def data_received(self, data: bytes) -> None:
            if self._refused:
                return  # read and dropped until the peer closes or the deadline does
            super().data_received(data)
            waiting = self.conn.their_state is h11.IDLE and not self.transport.is_closing()
            self._partial = waiting
            if not waiting:
                self._stop_deadline()
            elif self._header_deadline is None:
                self._header_deadline = self.loop.call_later(header_timeout_s, self._headers_late)

        def handle_events(self) -> None:
            # every way to a parse passes here: a read, and the next request of a pipeline
            # once a response is done (its head came with the request before it)
            if self._refused:
                return
            if self.conn.their_state is h11.IDLE and _buffered(self.conn) > MAX_HEAD_BYTES:
                pending = self.conn.trailing_data[0]
                if _too_long(pending):
                    self._refuse_head(pending)
                    return
            super().handle_events()

        def connection_lost(self, exc: Exception | None) -> None:
            self._stop_deadline()
            super().connection_lost(exc)

        def _stop_deadline(self) -> None:
            if self._header_deadline is not None:
                self._header_deadline.cancel()
                self._header_deadline = None

        def _headers_late(self) -> None:
            self._header_deadline = None
            if self._refused:
                self.transport.close()
                return
            if self.conn.their_state is not h11.IDLE or self.transport.is_closing():
                return
            if self._partial:
                self.transport.write(_late_headers(header_timeout_s))
            self.transport.close()

        def _refuse_head(self, head: bytes) -> None:
            """Answer, stop writing, and drop what the peer still sends: closing at once
            would reset the connection and lose the answer at the client."""
            self._refused = True
            self._unset_keepalive_if_required()  # armed by a response before a pipelined head
            line_done = b"\n" in head.lstrip(b"\r\n")[: MAX_HEAD_BYTES + 1]
            status, message = _head_too_large(MAX_HEAD_BYTES, line_done)
            peer = f"{self.client[0]}:{self.client[1]}" if self.client else "a client"
            self.logger.warning("%s: %s (%d)", peer, message, status)
            self.transport.write(_plain(status, message))
            if self.transport.can_write_eof():
                self.transport.write_eof()
            self._stop_deadline()
            self._header_deadline = self.loop.call_later(header_timeout_s, self._headers_late)

    return HeaderTimedProtocol


def _too_long(pending: bytes) -> bool:
    """Whether the head of the request that `pending` starts with passes `MAX_HEAD_BYTES`,
    whole or not yet."""
    end = _HEAD_END.search(pending)
    return (end.end() if end else len(pending)) > MAX_HEAD_BYTES


def _buffered(conn: h11.Connection) -> int:
    """Bytes h11 holds unparsed, without the copy `trailing_data` makes (a check on every read
    of a head sent a byte at a time must not cost its whole length each time)."""
    return len(conn._receive_buffer)


def _head_too_large(limit: int, line_done: bool) -> tuple[int, str]:
    if line_done:
        return 431, f"the request's line and headers passed {limit:,} bytes, the most read"
    return 414, f"the request line passed {limit:,} bytes, the most read"


def _plain(status: int, message: str) -> bytes:
    reason = {408: "Request Timeout", 414: "URI Too Long", 431: "Request Header Fields Too Large"}
    body = (message + "\n").encode()
    return (
        f"HTTP/1.1 {status} {reason[status]}\r\n".encode()
        + b"content-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
        + b"content-length: "
        + str(len(body)).encode()
        + b"\r\n\r\n"
        + body
    )


def _late_headers(timeout_s: float) -> bytes:
    return _plain(408, f"the request's headers did not arrive within {timeout_s:g} s")
