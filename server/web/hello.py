"""A WebSocket connection's first steps: its `hello`, read within a timeout and checked, and
the session's claim by a simulation. What ends a connection here is a `RefusedError`: the coded
error to send, and the close code."""

from __future__ import annotations

import asyncio
import contextlib
from typing import Literal

from starlette.websockets import WebSocket, WebSocketDisconnect

import protocol as p
from server.session.session import Session
from server.web.state import AppState

Endpoint = Literal["sim", "view"]


class RefusedError(Exception):
    """Ends a connection: the error to send and the close code."""

    def __init__(self, error: p.ProtocolError, close_code: int) -> None:
        super().__init__(error.message)
        self.error = error
        self.close_code = close_code


async def receive_message(ws: WebSocket, limits: p.Limits) -> bytes | None:
    """The next binary message, None when the peer left; oversized frames refuse the peer."""
    event = await ws.receive()
    if event["type"] == "websocket.disconnect":
        return None
    data = event.get("bytes")
    if data is None:
        raise p.ProtocolError(p.ErrorCode.INVALID_MESSAGE, "send binary msgpack frames, not text")
    if len(data) > limits.max_message_bytes:
        raise RefusedError(
            p.ProtocolError(
                p.ErrorCode.TOO_LARGE,
                f"message of {len(data)} bytes exceeds the limit of {limits.max_message_bytes}",
            ),
            1009,
        )
    return bytes(data)


def claim_session(session: Session, hello: p.Hello) -> None:
    """A session has one simulation. The same adapter instance reconnecting replaces its old
    connection; another one is refused (it must not flap with the first) unless it asks to
    take over."""
    current = session.sim
    if current is None or hello.takeover:
        return
    if hello.instance is not None and hello.instance == current.instance:
        return
    raise RefusedError(
        p.ProtocolError(
            p.ErrorCode.CONFLICT,
            f"session {session.id!r} already has a simulation ({current.name}); "
            "connect to another session, stop that one, or take over (hello.takeover)",
            "hello.session",
            hello.seq,
        ),
        1008,
    )


async def read_hello(
    ws: WebSocket, state: AppState, endpoint: Endpoint, notice: asyncio.Future[None]
) -> p.Hello:
    """The peer's `hello`, checked; refused when it does not come within the timeout, or when
    a newcomer to a full server took this connection's place first (`notice`)."""
    settings = state.settings
    receive = asyncio.ensure_future(receive_message(ws, settings.viewer_limits))
    try:
        done, _ = await asyncio.wait(
            (receive, notice), timeout=settings.hello_timeout_s, return_when="FIRST_COMPLETED"
        )
    finally:
        if not receive.done():
            receive.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await receive
    if receive not in done:
        why = (
            "the server is full and this connection had not said hello: it made room for "
            "a newer one; say hello as soon as you connect"
            if notice.done()
            else "no hello within the timeout"
        )
        code = p.ErrorCode.CAPACITY if notice.done() else p.ErrorCode.NOT_READY
        raise RefusedError(p.ProtocolError(code, why), 1013 if notice.done() else 1008)
    try:
        raw = receive.result()
    except p.ProtocolError as err:
        raise RefusedError(err, 1008) from None
    if raw is None:
        raise WebSocketDisconnect(1000)
    try:
        message = p.decode(raw, settings.viewer_limits)
    except p.ProtocolError as err:
        raise RefusedError(err, 1008) from None
    if not isinstance(message, p.Hello):
        raise RefusedError(
            p.ProtocolError(
                p.ErrorCode.NOT_READY,
                f"the first message must be hello, got {message.type}",
                "type",
                message.seq,
            ),
            1008,
        )
    wanted = {"sim": ("simulation",), "view": ("steerer", "viewer")}[endpoint]
    if message.role not in wanted:
        raise RefusedError(
            p.ProtocolError(
                p.ErrorCode.FORBIDDEN,
                f"role {message.role!r} does not belong on /ws/{endpoint}",
                "hello.role",
                message.seq,
            ),
            1008,
        )
    return message
