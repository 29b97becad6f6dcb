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
from typing import Any, cast

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.protocol import State

from server.web.fairfeed import FairFeed, Usage
from server.web.sendqueue import SEND_QUEUE, Counted, scope_extension

MAX_HEAD_BYTES = 64 * 1024
"""The most a request's line and headers may take: a long query string or many cookies fit."""
_HEAD_END = re.compile(rb"\n\r?\n")  # h11's own: lines may end in a bare newline
MAX_FRAGMENTS = 1024
"""Fragments one WebSocket message may come in: a simulation's largest (64 MiB) comes in 256 of
256 KiB (`protocol.fragments`), a browser's in one."""
FEED_BYTES = 1024
"""What a connection's parser takes in one turn of the event loop until the application set
its limit (`raise_limit`: a peer holding the server token): a 256 KiB read holds up to 43,000
empty frames, about 0.2 s of parsing in one step."""
MIN_READ_BPS = 512
"""The slowest a peer may read and count as reading: slower, a ping queued behind what it has
not read yet does not wait for it, and the stall cut takes it for a peer that reads nothing
(one byte a second would otherwise hold a place for days behind 300 KB of images)."""
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
        _raised = False
        _held: bytearray | None = None
        """Read and not yet parsed (`fairfeed` gives it its turns)."""
        _pong_due: bytes | None = None
        _ping_at_byte = 0
        """Bytes written up to and with the keep-alive ping in flight."""
        _taken = 0
        """Bytes the peer had taken when the keep-alive last looked."""
        _seen_taken = 0
        """Bytes the peer had taken when the stall watch last looked."""

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
            self.usage = Usage()
            self.conn.max_message_size = min(pre_hello_bytes, self.config.ws_max_size)

        def connection_lost(self, exc: Exception | None) -> None:
            if self._watch is not None:
                self._watch.cancel()
                self._watch = None
            self._held = self._pong_due = None
            super().connection_lost(exc)

        def _check_stall(self) -> None:
            """Every quarter of `stall_s`: cut a connection that has been closing, or unable
            to write, for `stall_s` (its peer reads nothing)."""
            self._watch = None
            taken = cast(Counted, self.transport).delivered()
            reading = taken - self._seen_taken >= MIN_READ_BPS * stall_s / 4
            self._seen_taken = taken
            # a slow reader's buffer is refilled past its high-water mark as soon as it
            # drains: only a peer that took nothing since the last look is stuck
            stuck = (self.transport.is_closing() or not self.writable.is_set()) and not reading
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

        # ------------------------------------------------------------ reading in pieces
        # websockets parses every frame of a read at once: a read of tiny frames held the
        # event loop, and every other connection, for as long as it took (a ping flood from
        # one socket took a viewer's round trip from 1 ms to 0.6 s). Until the application
        # set its limit (the hello of a simulation or a steerer, holding the server token), a
        # connection's reads are parsed `FEED_BYTES` at a time within one budget a turn for
        # every connection (`fairfeed`), and the next piece waits for the app to take the
        # messages the last one gave.

        def data_received(self, data: bytes) -> None:
            if self._held is None:
                if self._raised:
                    self._parse(data)
                    return
                fair = FairFeed.of(self.loop)
                if len(data) <= FEED_BYTES and not self.read_paused and fair.try_now(len(data)):
                    self.usage.add(len(data), self.loop.time())
                    self._parse(data)
                    return
                self._held = bytearray()
            self._held += data  # what came first is parsed first
            self.transport.pause_reading()
            self._offer()

        def _offer(self) -> None:
            if self.wants_feed():
                FairFeed.of(self.loop).submit(self, self.usage.at_time(self.loop.time()))

        def wants_feed(self) -> bool:
            return (
                self._held is not None and not self.read_paused and not self.transport.is_closing()
            )

        def feed_piece(self) -> int:
            held = self._held
            if held is None:
                return 0
            size = len(held) if self._raised else FEED_BYTES
            piece = bytes(held[:size])
            del held[:size]
            if not held:
                self._held = None
            self.usage.add(len(piece), self.loop.time())
            self._parse(piece)
            if self._held is None and not self.read_paused and not self.transport.is_closing():
                self.transport.resume_reading()
            return len(piece)

        async def receive(self) -> Any:
            message = await self.queue.get()
            if self.read_paused and self.queue.empty():
                self.read_paused = False
                if self._held is not None:
                    self._offer()
                elif not self.transport.is_closing():
                    self.transport.resume_reading()
            return message

        def _parse(self, data: bytes) -> None:
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

        # ------------------------------------------------------------ keep-alive
        # uvicorn's pong deadline ran from the moment the ping was written, so a ping queued
        # behind images a slow reader had not read yet timed out: a script viewer reading
        # 15-20 KB/s was closed at 40-70 s. Here the deadline runs from when the ping left
        # the server: while it is still queued and the peer keeps taking bytes, it waits.

        def connection_made(self, transport: Any) -> None:
            counted = Counted(transport)
            super().connection_made(cast(asyncio.Transport, counted))
            self._watch = self.loop.call_later(stall_s / 4, self._check_stall)

        def send_keepalive_ping(self) -> None:
            super().send_keepalive_ping()
            counted = cast(Counted, self.transport)
            self._ping_at_byte = counted.written
            self._taken = counted.delivered()

        def keepalive_timeout(self) -> None:
            counted = cast(Counted, self.transport)
            taken = counted.delivered()
            queued = self._taken < self._ping_at_byte  # the ping had not left at the last look
            timeout = self.ping_timeout or 0.0
            reading = taken - self._taken >= MIN_READ_BPS * timeout
            if queued and reading and timeout > 0 and not counted.is_closing():
                self._taken = taken  # the peer is reading what came before the ping: wait on
                self.pong_timer = self.loop.call_later(timeout, self.keepalive_timeout)
                return
            super().keepalive_timeout()

        # ------------------------------------------------------------ pongs
        # A peer that pings and never reads grew the write buffer by a pong a ping (about
        # 1 GB before the stall cut it). While the buffer is over its high-water mark only
        # the latest ping is answered, once it drains (RFC 6455 5.5.3 allows that).

        def handle_ping(self) -> None:
            pong = b"".join(self.conn.data_to_send())
            # a close from the peer parsed with the ping has its answer in the same bytes
            if self.writable.is_set() or self.conn.state is not State.OPEN:
                self.transport.write(pong)
            else:
                self._pong_due = pong

        def resume_writing(self) -> None:
            super().resume_writing()
            pong, self._pong_due = self._pong_due, None
            if pong and not self.transport.is_closing():
                self.transport.write(pong)

        async def send(self, message: Any) -> None:
            await super().send(message)
            # uvicorn writes an upgrade's refusal (`send_denial_response`, the 503 of a full
            # server) but does not count it as the handshake's end, so it logged every such
            # refusal as an error of the app's ("returned without completing handshake")
            if message["type"] == "websocket.http.response.body" and not message.get("more_body"):
                self.handshake_complete = True

        def handle_connect(self, event: Any) -> None:
            super().handle_connect(event)
            scope = getattr(self, "scope", None)
            if scope is not None:
                scope["extensions"][MESSAGE_LIMIT] = {"set": self._set_limit}
                scope["extensions"][SEND_QUEUE] = {"queued": cast(Counted, self.transport).queued}

        def _set_limit(self, size: int) -> None:
            self._raised = True  # its reads are parsed whole from now on
            self.conn.max_message_size = min(int(size), self.config.ws_max_size)

    return GuardedWebSocketProtocol


def raise_limit(scope: MutableMapping[str, Any], size: int) -> None:
    """Let this connection send messages of up to `size` bytes, its reads parsed whole, not in
    `FEED_BYTES` pieces (a no-op on other servers): for a peer holding the server token."""
    setter: Callable[[int], None] | None = scope_extension(scope, MESSAGE_LIMIT, "set")
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

        def handle_websocket_upgrade(self, event: h11.Request) -> None:
            # uvicorn hands the WebSocket protocol the request alone: a message sent in the
            # same write (a hello right behind the upgrade) was dropped unread, and the
            # connection waited out the hello timeout
            trailing, _ = self.conn.trailing_data
            super().handle_websocket_upgrade(event)
            protocol = self.transport.get_protocol()
            if trailing and isinstance(protocol, asyncio.Protocol):
                protocol.data_received(trailing)

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
