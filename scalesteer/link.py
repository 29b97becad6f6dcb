"""One WebSocket to a session's `/ws/view` endpoint, as a steerer or a viewer.

A link lives on the client's background loop (`scalesteer.background`). It keeps the session's
state as the server describes it (`SessionState`), answers requests by their `seq` (a
`render_params` is answered by the `state` naming it, `sim_params` and `control` by the
simulation's `params_ack`, `pick` by `picked`, `select` by `selected`, anything by an `error`
naming it), and hands images, events and statistics to listeners. Listeners run on the loop's
thread: they must be quick (hand work to a thread of their own).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, WebSocketException

import protocol
from protocol import (
    Error,
    ErrorCode,
    Event,
    FrameAck,
    Hello,
    Image,
    Message,
    ParamsAck,
    Picked,
    Ping,
    Pong,
    Role,
    Selected,
    State,
    Stats,
    Tracked,
    View,
    Welcome,
)
from scalesteer.errors import ScalesteerError
from scalesteer.state import SessionState

log = logging.getLogger("scalesteer.client")

MAX_IMAGE_BYTES = 64 * 1024 * 1024
"""The largest message accepted from the server (a 4K PNG is far below it)."""
OPEN_TIMEOUT_S = 15.0

Listener = Callable[[Any], None]


class ViewLink:
    """A steerer's (or viewer's) connection to one session. Create with `await open(...)`.

    `on_image`, `on_state`, `on_event`, `on_stats`, `on_tracked`, `on_error` and `on_close`
    are lists of listeners; each is called with the message (`on_state` with the merged
    `SessionState`, `on_close` with the reason)."""

    def __init__(self, url: str, token: str | None, session: str, role: Role, client: str) -> None:
        parts = urlsplit(url)
        if parts.scheme not in ("ws", "wss") or not parts.hostname:
            raise ValueError(f"a /ws/view URL must start with ws:// or wss://, got {url!r}")
        self.url = url
        self.hello = Hello(role=role, token=token, client=client[:128], session=session)
        self.welcome: Welcome | None = None
        self.state = SessionState()
        self.closed: str | None = None
        """Why the link is closed (None while it is open)."""
        self.on_image: list[Listener] = []
        self.on_state: list[Listener] = []
        self.on_event: list[Listener] = []
        self.on_stats: list[Listener] = []
        self.on_tracked: list[Listener] = []
        self.on_error: list[Listener] = []
        self.on_close: list[Listener] = []
        self._seq = itertools.count(1)
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._barriers: dict[int, int] = {}  # ping seq -> the seq it vouches for
        self._ws: ClientConnection | None = None
        self._reader: asyncio.Task[None] | None = None
        self.view_seq = 0
        self._closing = False
        """The seq of the last `view` sent."""
        self._loopback = parts.hostname in ("127.0.0.1", "localhost", "::1")

    @property
    def session_id(self) -> str:
        return self.welcome.session_id if self.welcome else (self.hello.session or "default")

    @property
    def client_id(self) -> str:
        return self.welcome.client_id if self.welcome else ""

    async def open(self) -> ViewLink:
        """Connect, say hello and wait for `welcome` and the session's first state; a refusal
        raises `ScalesteerError` with the server's code."""
        try:
            self._ws = await connect(
                self.url,
                compression=None,
                max_size=MAX_IMAGE_BYTES,
                open_timeout=OPEN_TIMEOUT_S,
                close_timeout=2.0,
                proxy=None if self._loopback else True,
                user_agent_header="scalesteer-python",
            )
        except (OSError, WebSocketException, TimeoutError) as exc:
            raise ScalesteerError(
                ErrorCode.NOT_READY, f"cannot reach {self.url}: {exc}", "url"
            ) from None
        try:
            await self._ws.send(protocol.encode(self.hello))
            first = await asyncio.wait_for(self._receive(), OPEN_TIMEOUT_S)
            if isinstance(first, Error):
                raise ScalesteerError.of(first)
            if not isinstance(first, Welcome):
                raise ScalesteerError(
                    ErrorCode.INVALID_MESSAGE, f"expected welcome, got {first.type}", "type"
                )
            self.welcome = first
            # the full state follows the welcome at once; the link is usable from then on
            state = await asyncio.wait_for(self._receive(), OPEN_TIMEOUT_S)
            self._dispatch(state)
        except BaseException:
            await self._ws.close()
            raise
        self._reader = asyncio.get_running_loop().create_task(self._read())
        return self

    async def _receive(self) -> Message:
        assert self._ws is not None
        raw = await self._ws.recv()
        if not isinstance(raw, bytes):
            raise ScalesteerError(ErrorCode.INVALID_MESSAGE, "the server sent a text frame")
        return protocol.decode(raw, protocol.Limits(max_message_bytes=MAX_IMAGE_BYTES))

    async def _read(self) -> None:
        reason = "closed"
        try:
            while True:
                try:
                    message = await self._receive()
                except protocol.ProtocolError as exc:
                    log.warning("scalesteer: undecodable message from the server: %s", exc)
                    continue
                self._dispatch(message)
        except ConnectionClosed as exc:
            if self._closing:
                return self._finish("closed")
            reason = f"the server closed the connection ({exc.rcvd.code if exc.rcvd else 1006})"
            if exc.rcvd and exc.rcvd.reason:
                reason += f": {exc.rcvd.reason}"
        except asyncio.CancelledError:
            reason = "closed"
        except Exception as exc:  # a listener's bug must not leave the link half open
            log.exception("scalesteer: the link to %s failed", self.url)
            reason = f"failed: {exc}"
        finally:
            self._finish(reason)

    def _finish(self, reason: str) -> None:
        if self.closed is not None:
            return
        self.closed = reason
        error = ScalesteerError(ErrorCode.NOT_READY, _ended(reason))
        for future in self._pending.values():
            if not future.done():
                future.set_exception(error)
        self._pending.clear()
        self._notify(self.on_close, reason)

    def _notify(self, listeners: list[Listener], value: Any) -> None:
        for listener in list(listeners):
            try:
                listener(value)
            except Exception:
                log.exception("scalesteer: a listener failed")

    def _resolve(
        self, ref: int | None, value: Any = None, error: BaseException | None = None
    ) -> bool:
        future = self._pending.pop(ref, None) if ref is not None else None
        if future is None or future.done():
            return False
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(value)
        return True

    def _dispatch(self, message: Message) -> None:
        match message:
            case Image():
                self._notify(self.on_image, message)
            case State():
                self.state = self.state.merged(message)
                self._notify(self.on_state, self.state)
                self._resolve(message.ref, self.state)
            case ParamsAck():
                if message.ok:
                    self._resolve(message.ref, message)
                else:
                    refusal = ScalesteerError(
                        ErrorCode.INVALID_MESSAGE,
                        f"the simulation refused it: {message.detail or 'no reason given'}",
                        ref=message.ref,
                    )
                    self._resolve(message.ref, error=refusal)
            case Picked() | Selected():
                self._resolve(message.ref, message)
            case Pong():
                vouched = self._barriers.pop(message.ref, None) if message.ref else None
                self._resolve(vouched)
                self._resolve(message.ref, message)
            case Error():
                if not self._resolve(message.ref, error=ScalesteerError.of(message)):
                    self._notify(self.on_error, message)
            case Event():
                self._notify(self.on_event, message)
            case Stats():
                self._notify(self.on_stats, message)
            case Tracked():
                self._notify(self.on_tracked, message)
            case _:
                log.debug("scalesteer: ignoring %s", message.type)

    # ------------------------------------------------------------------ sending (on the loop)

    def check_open(self) -> None:
        """Raise `not_ready`, saying why, once the link has ended (any thread)."""
        self._check_open()

    def _check_open(self) -> ClientConnection:
        if self.closed is not None or self._ws is None:
            raise ScalesteerError(
                ErrorCode.NOT_READY,
                _ended(self.closed) if self.closed else "the link to the session is not open",
            )
        return self._ws

    async def send(self, message: Message) -> int:
        """Send `message` numbered with a new `seq`; returns the seq."""
        ws = self._check_open()
        seq = next(self._seq)
        try:
            await ws.send(protocol.encode(message.model_copy(update={"seq": seq})))
        except ConnectionClosed:
            raise ScalesteerError(ErrorCode.NOT_READY, "the link to the session closed") from None
        return seq

    async def request(self, message: Message, timeout: float) -> Any:
        """Send `message` and wait for its answer (see the module docstring); an `error`
        naming it raises `ScalesteerError`. Messages the server answers only when they fail
        (`pull`, `forces`, `view`) are followed by a ping: its pong says they were taken."""
        ws = self._check_open()
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        seq = next(self._seq)
        self._pending[seq] = future
        try:
            await ws.send(protocol.encode(message.model_copy(update={"seq": seq})))
            if message.type in ("pull", "forces", "view", "frame_ack"):
                ping = next(self._seq)
                self._barriers[ping] = seq
                await ws.send(protocol.encode(Ping(seq=ping, client_time=time.time())))
            return await asyncio.wait_for(future, timeout)
        except TimeoutError:
            raise TimeoutError(
                f"no answer to {message.type} from the server within {timeout:g} s"
            ) from None
        except ConnectionClosed:
            raise ScalesteerError(ErrorCode.NOT_READY, "the link to the session closed") from None
        finally:
            self._pending.pop(seq, None)

    def reserve_view(self) -> int:
        """The seq of the next view, taken now on the caller's thread: from here on no image
        of the views before it passes (`view_seq`), though the view goes out later."""
        seq = next(self._seq)
        self.view_seq = seq
        return seq

    async def view(self, view: View, seq: int | None = None) -> int:
        """Send this link's view (camera, size, codecs) as `seq` (`reserve_view`; default: a
        new one); not answered unless refused. Images answering it (and later messages) carry
        a `ref` of at least its seq (`view_seq`)."""
        ws = self._check_open()
        if seq is None:
            seq = self.reserve_view()  # before the send: no image of the old view passes after
        try:
            await ws.send(protocol.encode(view.model_copy(update={"seq": seq})))
        except ConnectionClosed:
            raise ScalesteerError(ErrorCode.NOT_READY, "the link to the session closed") from None
        return seq

    async def ack(self, frame_id: int, decode_ms: float = 0.0) -> None:
        """Tell the server an image reached its screen (it paces the link by these)."""
        with contextlib.suppress(ScalesteerError):
            await self.send(FrameAck(frame_id=frame_id, decode_ms=decode_ms))

    async def close(self) -> None:
        self._closing = True
        if self._ws is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._ws.close(), 3.0)
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
        self._finish("closed")


def _ended(reason: str) -> str:
    """Why the link ended, as a sentence ("closed", "failed: ...", or the server's words)."""
    if reason == "closed":
        return "the link to the session is closed"
    if reason.startswith("failed"):
        return f"the link to the session {reason}"
    return f"the link to the session ended: {reason}"
