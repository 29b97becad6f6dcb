"""The adapter's connection to the render server's `/ws/sim` endpoint.

An MD loop must never wait on the network, so all socket work runs on one background thread that
owns an asyncio event loop. The MD thread only hands over messages:

* `send_frame` puts a frame into a one-slot mailbox (latest wins; an unsent older frame is
  dropped) or, in lossless mode, into a short bounded queue that blocks when full;
* `poll_steering` drains the steering messages that arrived since the last call, so they are
  applied on the MD thread at a point the MD code chooses;
* `ack` queues the answer to a steering message, naming the step at which it took effect.

The thread reconnects with exponential backoff and re-sends the topology on every connection.
Only numpy, msgpack, pydantic and websockets are imported: this loads inside any MD run.

Kept whole: it loads inside any MD run on numpy, msgpack, pydantic and websockets alone, and one
class owns the background thread's state (mailbox, queue, reconnects) that the MD thread hands
messages to.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import math
import random
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, urlsplit, urlunsplit

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidURI, WebSocketException

import protocol
from protocol import (
    EngineInfo,
    Error,
    ErrorCode,
    Event,
    Frame,
    Hello,
    Limits,
    Message,
    ParamsAck,
    Ping,
    Pong,
    ProtocolError,
    SimSteering,
    Topology,
    Welcome,
)

log = logging.getLogger("scalesteer.connection")

#: error codes after which reconnecting with the same settings cannot succeed
FATAL_CODES = frozenset(
    {ErrorCode.UNAUTHORIZED, ErrorCode.FORBIDDEN, ErrorCode.VERSION_MISMATCH, ErrorCode.CONFLICT}
)


class ConnectionState(enum.Enum):
    """Where the connection stands; `FAILED` and `CLOSED` are final."""

    IDLE = "idle"  # created, start() not called
    CONNECTING = "connecting"  # opening the socket or waiting for `welcome`
    CONNECTED = "connected"  # welcomed: topology and frames flow
    BACKOFF = "backoff"  # lost or refused; waiting before the next attempt
    FAILED = "failed"  # the server refused us for good (bad token, version); see `.error`
    CLOSED = "closed"  # close() was called


@dataclass
class ConnectionStats:
    """Counters for tests and logs; written by the I/O thread, read anywhere."""

    connects: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0
    frames_rejected: int = 0
    topologies_sent: int = 0
    steering_received: int = 0
    acks_sent: int = 0


@dataclass
class _Outgoing:
    """A control message (ack, pong, error) tagged with the connection it belongs to."""

    message: Message
    generation: int | None  # None: valid on any connection


def sim_endpoint(url: str) -> tuple[str, str | None]:
    """The `/ws/sim` URL to connect to, and the token a dashboard link carries: the server
    prints its dashboard link (`http://HOST:PORT/?token=...`), and that link works here as it
    is, besides `ws://HOST:PORT/ws/sim` itself."""
    parts = urlsplit(url)
    if parts.scheme in ("http", "https") and parts.hostname:
        token = parse_qs(parts.query).get("token", [None])[0]
        scheme = "wss" if parts.scheme == "https" else "ws"
        return urlunsplit((scheme, parts.netloc, "/ws/sim", "", "")), token
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise ValueError(
            "server URL must look like ws://HOST:PORT/ws/sim (or the dashboard's "
            f"http://HOST:PORT/?token=... link), got {url!r}"
        )
    return url, None


class SimulationConnection:
    """A simulation's link to the render server (see the module docstring).

    `on_steer(message)` and `on_state(state)`, if given, are called on the I/O thread; keep them
    short (set an event, notify a condition) and thread-safe.
    """

    def __init__(
        self,
        url: str,
        token: str | None = None,
        session: str = "default",
        client: str = "scalesteer",
        lossless: bool = False,
        on_steer: Callable[[Message], None] | None = None,
        *,
        on_state: Callable[[ConnectionState], None] | None = None,
        lossless_depth: int = 8,
        backoff_initial: float = 0.2,
        backoff_max: float = 10.0,
        give_up_after: float | None = None,
        welcome_timeout: float = 10.0,
        takeover: bool = False,
    ) -> None:
        url, link_token = sim_endpoint(url)
        token = token if token is not None else link_token
        self.url = url
        self.token = token
        self.session = session
        self.client = client[:128]
        try:  # a bad session name or token must fail here, not later on the I/O thread
            self._hello = Hello(
                role="simulation",
                token=token,
                client=self.client,
                session=session,
                # one identity across reconnections: the server lets this process back in
                # but refuses a second simulation in the same session (unless it takes over)
                instance=secrets.token_hex(8),
                takeover=takeover,
            )
        except ValueError as exc:
            problem = exc.errors()[0]["msg"] if hasattr(exc, "errors") else str(exc)
            raise ValueError(f"invalid session name or token: {problem}") from None
        self.lossless = lossless
        self._on_steer = on_steer
        self._on_state = on_state
        self._lossless_depth = max(1, lossless_depth)
        self._backoff_initial = backoff_initial
        self._backoff_max = backoff_max
        self.give_up_after = give_up_after
        """Seconds of failed attempts after which the connection stops trying (`FAILED`);
        None retries for ever."""
        self._welcome_timeout = welcome_timeout
        self._loopback = urlsplit(url).hostname in ("127.0.0.1", "localhost", "::1")

        self.stats = ConnectionStats()
        self.error: str | None = None
        self.server_errors: deque[Error] = deque(maxlen=20)  # the latest `error` messages
        self.welcome: Welcome | None = None
        self.limits: Limits = protocol.DEFAULT_LIMITS

        # shared between threads, guarded by _lock
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._state = ConnectionState.IDLE
        self._frame_slot: Frame | None = None
        self._frame_queue: deque[Frame] = deque()
        self._control: deque[_Outgoing] = deque()
        self._steering: deque[Message] = deque()
        self._topology: Topology | None = None
        self._engine: EngineInfo | None = None
        self._generation = 0
        self._closing = False
        self._flush_timeout = 5.0

        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._drained: asyncio.Event | None = None  # set whenever the writer ran out of work
        self._stop: asyncio.Event | None = None

    # ------------------------------------------------------------------ public API (any thread)

    @property
    def state(self) -> ConnectionState:
        return self._state

    @property
    def connected(self) -> bool:
        return self._state is ConnectionState.CONNECTED

    def start(self) -> SimulationConnection:
        """Start the I/O thread; returns immediately (the connection is made in the background)."""
        with self._lock:
            if self._thread is not None or self._closing:
                return self
            ready = threading.Event()
            self._thread = threading.Thread(
                target=self._thread_main, args=(ready,), name="scalesteer-connection", daemon=True
            )
        self._thread.start()
        ready.wait()
        return self

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Block until welcomed (True), or until the timeout, failure or close (False)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._changed:
            while self._state is not ConnectionState.CONNECTED:
                if self._state in (ConnectionState.FAILED, ConnectionState.CLOSED):
                    return False
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._changed.wait(remaining)
            return True

    def send_topology(self, topology: Topology) -> None:
        """Set the topology; it is sent now if connected and again after every reconnect."""
        with self._lock:
            self._topology = topology
        self._kick()

    def send_engine(self, engine: EngineInfo) -> None:
        """Declare what this simulation can be steered with; re-sent after every reconnect,
        right after the topology."""
        with self._lock:
            self._engine = engine
        self._kick()

    def send_event(self, event: Event) -> None:
        """Tell everyone in the session (the guard fired, the replay ended, ...)."""
        self._queue_control(event, current=False)

    def send_frame(self, frame: Frame, timeout: float | None = None) -> bool:
        """Hand a frame to the I/O thread.

        Default mode never blocks: the frame replaces one not yet sent (counted as dropped).
        Lossless mode blocks while `lossless_depth` frames wait (also while disconnected), up to
        `timeout` seconds; it returns False if the frame could not be queued.
        """
        if not self.lossless:
            with self._lock:
                if self._closing:
                    return False
                was_empty = self._frame_slot is None
                if not was_empty:
                    self.stats.frames_dropped += 1
                self._frame_slot = frame
            if was_empty:
                self._kick()
            return True
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._changed:
            while len(self._frame_queue) >= self._lossless_depth and not self._closing:
                if self._state is ConnectionState.FAILED:
                    return False
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._changed.wait(remaining)
            if self._closing:
                return False
            self._frame_queue.append(frame)
        self._kick()
        return True

    def poll_steering(self) -> list[Message]:
        """The steering messages (sim_params, control, forces) received since the last call."""
        with self._lock:
            out = list(self._steering)
            self._steering.clear()
        return out

    def ack(
        self,
        ref: int | None,
        step: int | None,
        time_ps: float | None,
        ok: bool = True,
        applied: dict[str, Any] | None = None,
        detail: str = "",
    ) -> None:
        """Answer steering message `ref`: applied (or not) at MD step `step`."""
        if ref is None:
            return
        msg = ParamsAck(
            ref=ref,
            ok=ok,
            step=None if step is None else max(0, int(step)),
            time_ps=time_ps if time_ps is not None and math.isfinite(time_ps) else None,
            applied=applied or {},
            detail=detail[:1024],
        )
        self._queue_control(msg, current=True)

    def send_error(self, code: ErrorCode, message: str, path: str | None = None) -> None:
        """Tell the server something went wrong on the simulation side (NaN coordinates, ...)."""
        self._queue_control(Error(code=code, message=message[:4096], path=path), current=False)

    def close(self, timeout: float = 5.0) -> None:
        """Flush what is queued (lossless frames, acks) for up to `timeout`, then disconnect and
        join the I/O thread."""
        with self._changed:
            if not self._closing:
                self._flush_timeout = max(0.0, timeout)
                self._closing = True
                self._changed.notify_all()
            thread = self._thread
        loop, stop = self._loop, self._stop
        if thread is None:
            self._set_state(ConnectionState.CLOSED)
            return
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # loop already finished
                loop.call_soon_threadsafe(stop.set)
        thread.join(timeout + 3.0)
        loop = self._loop
        if thread.is_alive() and loop is not None:  # a stuck socket: cancel all on the loop
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_cancel_all)
            thread.join(5.0)
        self._set_state(ConnectionState.CLOSED)

    def __enter__(self) -> SimulationConnection:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SimulationConnection({self.url!r}, state={self._state.value})"

    # ------------------------------------------------------------------ helpers (any thread)

    def _queue_control(self, msg: Message, *, current: bool) -> None:
        with self._lock:
            if self._closing and self._thread is None:
                return
            self._control.append(_Outgoing(msg, self._generation if current else None))
        self._kick()

    def _kick(self) -> None:
        loop, wake = self._loop, self._wake
        if loop is None or wake is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop has already stopped
            loop.call_soon_threadsafe(wake.set)

    def _set_state(self, state: ConnectionState) -> None:
        with self._changed:
            if self._state is state or self._state is ConnectionState.CLOSED:
                return
            if self._state is ConnectionState.FAILED and state is not ConnectionState.CLOSED:
                return
            self._state = state
            self._changed.notify_all()
        log.debug("connection %s: %s", self.url, state.value)
        if self._on_state is not None:
            try:
                self._on_state(state)
            except Exception:
                log.exception("on_state callback failed")

    # ------------------------------------------------------------------ I/O thread

    def _thread_main(self, ready: threading.Event) -> None:
        try:
            asyncio.run(self._main(ready))
        except Exception:  # never let the thread die silently
            log.exception("scalesteer connection thread crashed")
            self.error = self.error or "connection thread crashed"
            self._set_state(ConnectionState.FAILED)
        finally:
            ready.set()
            self._loop = None
            with self._changed:
                self._changed.notify_all()

    async def _main(self, ready: threading.Event) -> None:
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._drained = asyncio.Event()
        self._stop = asyncio.Event()
        if self._closing:
            self._stop.set()
        ready.set()
        delay = self._backoff_initial
        failing_since: float | None = None
        attempt = 0
        while not self._stop.is_set():
            self._set_state(ConnectionState.CONNECTING)
            welcomed = False
            problem = ""
            try:
                welcomed = await self._connect_once()
            except (_FatalError, InvalidURI) as exc:
                self.error = str(exc)
                log.error("scalesteer: %s; not reconnecting", exc)
                self._set_state(ConnectionState.FAILED)
                break
            except (TimeoutError, OSError, WebSocketException, ProtocolError) as exc:
                problem = _describe(exc)
            if self._stop.is_set():
                break
            now = time.monotonic()
            if welcomed:
                log.warning("scalesteer: lost the connection to %s; reconnecting", self.url)
                delay, failing_since, attempt = self._backoff_initial, now, 0
            elif failing_since is None:
                failing_since = now
            attempt += 1
            jittered = delay * random.uniform(0.8, 1.2)
            waited = now - failing_since
            if self.give_up_after is not None and waited + jittered > self.give_up_after:
                self.error = (
                    f"could not reach {self.url} for {waited:.0f} s ({problem or 'lost'}); "
                    "giving up"
                )
                log.error("scalesteer: %s", self.error)
                self._set_state(ConnectionState.FAILED)
                break
            left = (
                ""
                if self.give_up_after is None
                else f", giving up in {self.give_up_after - waited:.0f} s"
            )
            log.warning(
                "scalesteer: %s: %s; retry %d in %.1f s%s",
                self.url,
                problem or "disconnected",
                attempt,
                jittered,
                left,
            )
            self._set_state(ConnectionState.BACKOFF)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), jittered)
            delay = min(delay * 2.0, self._backoff_max)
        with self._changed:
            self._frame_queue.clear()
            self._frame_slot = None
            self._changed.notify_all()

    async def _connect_once(self) -> bool:
        """One connection: handshake, then pump messages until it drops. True if welcomed."""
        try:
            ws_cm = connect(
                self.url,
                compression=None,
                max_size=16 * 1024 * 1024,
                open_timeout=self._welcome_timeout,
                close_timeout=2.0,
                ping_interval=20.0,
                ping_timeout=20.0,
                proxy=None if self._loopback else True,
                user_agent_header=f"scalesteer-adapter ({self.client})",
            )
        except InvalidURI as exc:
            raise _FatalError(f"invalid server URL {self.url!r}: {exc}") from None
        async with ws_cm as ws:
            welcome = await self._handshake(ws)
            self.welcome = welcome
            self.limits = welcome.limits
            with self._lock:
                self._generation += 1
                generation = self._generation
                # acks for messages of an earlier connection mean nothing to this server
                self._control = deque(c for c in self._control if c.generation is None)
            self.stats.connects += 1
            self._set_state(ConnectionState.CONNECTED)
            log.info("scalesteer: connected to %s (session %s)", self.url, welcome.session_id)
            await self._pump(ws, generation)
            return True

    async def _handshake(self, ws: ClientConnection) -> Welcome:
        await ws.send(protocol.encode(self._hello))
        raw = await asyncio.wait_for(ws.recv(), self._welcome_timeout)
        if not isinstance(raw, bytes):
            raise ProtocolError(ErrorCode.INVALID_MESSAGE, "server sent a text frame")
        msg = protocol.decode(raw)
        if isinstance(msg, Welcome):
            return msg
        if isinstance(msg, Error):
            code = ErrorCode(msg.code)
            text = f"server refused the connection: {code.value}: {msg.message}"
            if code in FATAL_CODES:
                raise _FatalError(text)
            raise ProtocolError(code, text)
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, f"expected welcome, got {msg.type}")

    async def _pump(self, ws: ClientConnection, generation: int) -> None:
        assert self._stop is not None and self._wake is not None
        reader = asyncio.create_task(self._reader(ws, generation))
        writer = asyncio.create_task(self._writer(ws, generation))
        stopper = asyncio.create_task(self._stop.wait())
        try:
            done, _ = await asyncio.wait(
                {reader, writer, stopper}, return_when=asyncio.FIRST_COMPLETED
            )
            if stopper in done:
                await self._flush(writer)
            for task in done:
                exc = None if task is stopper or task.cancelled() else task.exception()
                if exc is not None and not isinstance(exc, ConnectionClosed):
                    log.info("scalesteer: connection lost: %s", _describe(exc))
        finally:
            for task in (reader, writer, stopper):
                task.cancel()
            await asyncio.gather(reader, writer, stopper, return_exceptions=True)
        if self._stop.is_set():
            try:
                await asyncio.wait_for(ws.close(), 1.0)
            except (TimeoutError, OSError, WebSocketException):
                ws.transport.abort()  # the server does not read: do not wait for it

    async def _flush(self, writer: asyncio.Task[None]) -> None:
        """On close: give the writer a bounded time to send what is still queued."""
        assert self._wake is not None and self._drained is not None
        with self._lock:
            pending = bool(self._control or self._frame_queue or self._frame_slot)
        if not pending or writer.done():
            return
        self._drained.clear()
        self._wake.set()
        done = asyncio.create_task(self._drained.wait())
        await asyncio.wait({done, writer}, timeout=self._flush_timeout)
        done.cancel()

    async def _reader(self, ws: ClientConnection, generation: int) -> None:
        async for raw in ws:
            if not isinstance(raw, bytes):
                log.warning("scalesteer: ignoring a text frame from the server")
                continue
            try:
                msg = protocol.decode(raw)
            except ProtocolError as exc:
                log.warning("scalesteer: undecodable message from the server: %s", exc)
                continue
            self._dispatch(msg, generation)

    def _dispatch(self, msg: Message, generation: int) -> None:
        if isinstance(msg, SimSteering):
            self.stats.steering_received += 1
            with self._lock:
                self._steering.append(msg)
            if self._on_steer is not None:
                try:
                    self._on_steer(msg)
                except Exception:
                    log.exception("on_steer callback failed")
        elif isinstance(msg, Ping):
            pong = Pong(ref=msg.seq, client_time=msg.client_time, server_time=time.time())
            with self._lock:
                self._control.append(_Outgoing(pong, generation))
            assert self._wake is not None
            self._wake.set()
        elif isinstance(msg, Error):
            self.server_errors.append(msg)
            log.warning("scalesteer: server error %s: %s", msg.code, msg.message)
        else:
            log.debug("scalesteer: ignoring %s from the server", msg.type)

    async def _writer(self, ws: ClientConnection, generation: int) -> None:
        assert self._wake is not None and self._drained is not None
        topology_sent: Topology | None = None
        engine_sent: EngineInfo | None = None
        self._wake.set()  # a new connection: the topology (and what waits) goes out at once
        while True:
            await self._wake.wait()
            self._wake.clear()
            while True:
                item = self._next_outgoing(generation, topology_sent, engine_sent)
                if item is None:
                    self._drained.set()
                    break
                kind, msg = item
                data = protocol.encode(msg)
                if len(data) > self.limits.max_message_bytes:
                    self._reject(kind, msg, len(data))
                    continue
                await ws.send(protocol.fragments(data))
                if kind == "topology":
                    assert isinstance(msg, Topology)
                    topology_sent = msg
                    self.stats.topologies_sent += 1
                elif kind == "engine":
                    assert isinstance(msg, EngineInfo)
                    engine_sent = msg
                elif kind == "frame":
                    self.stats.frames_sent += 1
                elif isinstance(msg, ParamsAck):
                    self.stats.acks_sent += 1

    def _next_outgoing(
        self, generation: int, topology_sent: Topology | None, engine_sent: EngineInfo | None
    ) -> tuple[str, Message] | None:
        """Pick what to send next: control messages, then the topology and the engine's
        declaration, then one frame."""
        with self._changed:
            while self._control:
                out = self._control.popleft()
                if out.generation is None or out.generation == generation:
                    return "control", out.message
            if self._topology is not None and self._topology is not topology_sent:
                return "topology", self._topology
            if topology_sent is None:
                return None  # frames wait for the topology
            if self._engine is not None and self._engine is not engine_sent:
                return "engine", self._engine
            if self._frame_queue:
                frame = self._frame_queue.popleft()
                self._changed.notify_all()
                return "frame", frame
            if self._frame_slot is not None:
                frame, self._frame_slot = self._frame_slot, None
                return "frame", frame
        return None

    def _reject(self, kind: str, msg: Message, size: int) -> None:
        limit = self.limits.max_message_bytes
        if kind == "frame":
            self.stats.frames_rejected += 1
            if self.stats.frames_rejected == 1:
                log.error(
                    "scalesteer: a frame of %d bytes exceeds the server's limit of %d; "
                    "frames are dropped (fewer atoms or a larger server limit needed)",
                    size,
                    limit,
                )
        else:
            log.error("scalesteer: %s of %d bytes exceeds the limit of %d", msg.type, size, limit)


def _cancel_all() -> None:
    for task in asyncio.all_tasks():
        task.cancel()


class _FatalError(Exception):
    """The server refused us in a way retrying cannot fix."""


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
