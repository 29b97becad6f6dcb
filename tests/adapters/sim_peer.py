"""A tiny real `/ws/sim` server for the adapter tests: the render server's side of the contract.

It runs the `websockets` asyncio server on 127.0.0.1 (ephemeral port) in its own thread, checks
the token, answers `hello` with `welcome`, records everything the adapter sends, and lets a test
send steering messages and wait for their acks. `never_read=True` makes it stop reading after the
handshake (with a tiny receive buffer), which is how a hopelessly slow server looks to a client.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from websockets.asyncio.server import Server, ServerConnection, serve

import protocol
from protocol import (
    Error,
    ErrorCode,
    Frame,
    Hello,
    Limits,
    Message,
    ParamsAck,
    Topology,
    Welcome,
)

M = TypeVar("M", bound=Message)


class SimPeer:
    """Test double of the render server's simulation endpoint (real sockets, real protocol)."""

    def __init__(
        self,
        token: str | None = "secret",
        *,
        never_read: bool = False,
        limits: Limits | None = None,
        port: int = 0,
    ) -> None:
        self.token = token
        self.never_read = never_read
        self.limits = limits or Limits()
        self.port = port
        self.received: list[Message] = []
        self.hellos: list[Hello] = []
        self.connections = 0
        self._cond = threading.Condition()
        self._seq = 1000
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: Server | None = None
        self._clients: set[ServerConnection] = set()

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> SimPeer:
        """Listen (again); what a previous run received is forgotten, like a restarted server."""
        with self._cond:
            self.received = []
        ready = threading.Event()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, args=(ready,), name="sim-peer")
        self._thread.start()
        ready.wait(10)
        fut = asyncio.run_coroutine_threadsafe(self._serve(), self._loop)
        fut.result(10)
        return self

    def stop(self) -> None:
        """Close the listening socket and every connection (like a server that exits)."""
        if self._loop is None:
            return
        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop).result(10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        assert self._thread is not None
        self._thread.join(10)
        self._loop.close()
        self._loop = None
        self._thread = None

    def restart(self, downtime: float = 0.3) -> None:
        """Stop, wait, and listen again on the same port (a server restart)."""
        self.stop()
        time.sleep(downtime)
        self.start()

    def __enter__(self) -> SimPeer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/ws/sim"

    # ------------------------------------------------------------------ what arrived

    def of_type(self, kind: type[M]) -> list[M]:
        with self._cond:
            return [m for m in self.received if isinstance(m, kind)]

    @property
    def frames(self) -> list[Frame]:
        return self.of_type(Frame)

    @property
    def topologies(self) -> list[Topology]:
        return self.of_type(Topology)

    def wait_for(self, predicate: Callable[[], Any], timeout: float = 10.0) -> Any:
        """Block until `predicate()` is truthy (re-checked whenever a message arrives)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                value = predicate()
                if value:
                    return value
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError("condition not met in time")
                self._cond.wait(remaining)

    def wait_frames(self, n: int, timeout: float = 10.0) -> list[Frame]:
        self.wait_for(lambda: len(self.frames) >= n, timeout)
        return self.frames

    def wait_ack(self, seq: int, timeout: float = 10.0) -> ParamsAck:
        def find() -> ParamsAck | None:
            return next((a for a in self.of_type(ParamsAck) if a.ref == seq), None)

        ack: ParamsAck = self.wait_for(find, timeout)
        return ack

    # ------------------------------------------------------------------ steering

    def send(self, message: Message) -> int:
        """Send a message (with a fresh seq) to every connected simulation; returns the seq."""
        with self._cond:
            self._seq += 1
            seq = self._seq
        msg = message.model_copy(update={"seq": seq})
        assert self._loop is not None
        asyncio.run_coroutine_threadsafe(self._broadcast(protocol.encode(msg)), self._loop).result(
            10
        )
        return seq

    # ------------------------------------------------------------------ server internals

    def _run(self, ready: threading.Event) -> None:
        assert self._loop is not None
        asyncio.set_event_loop(self._loop)
        self._loop.call_soon(ready.set)
        self._loop.run_forever()
        pending = asyncio.all_tasks(self._loop)
        for task in pending:
            task.cancel()
        self._loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))

    async def _serve(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if self.never_read:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.bind(("127.0.0.1", self.port))
        self.port = sock.getsockname()[1]
        self._server = await serve(
            self._handle,
            sock=sock,
            compression=None,
            max_size=self.limits.max_message_bytes,
            max_queue=1 if self.never_read else 64,
            ping_interval=None,
            close_timeout=1.0,
        )

    async def _shutdown(self) -> None:
        if self._server is not None:
            self._server.close(close_connections=True)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 3)
            self._server = None

    async def _broadcast(self, data: bytes) -> None:
        for ws in list(self._clients):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.send(data), 5)

    async def _handle(self, ws: ServerConnection) -> None:
        try:
            hello = protocol.decode(await ws.recv())
        except Exception:
            await ws.close(1008)
            return
        if not isinstance(hello, Hello) or hello.role != "simulation":
            await ws.close(1008)
            return
        with self._cond:
            self.hellos.append(hello)
        if self.token is not None and hello.token != self.token:
            err = Error(code=ErrorCode.UNAUTHORIZED, message="bad token", ref=hello.seq)
            await ws.send(protocol.encode(err))
            await ws.close(1008, "unauthorized")
            return
        with self._cond:
            self.connections += 1
            self._cond.notify_all()
        welcome = Welcome(
            session_id=hello.session or "default",
            client_id=f"sim-{self.connections}",
            role="simulation",
            limits=self.limits,
        )
        self._clients.add(ws)  # before the welcome: a welcomed client can be steered at once
        try:
            await ws.send(protocol.encode(welcome))
            if self.never_read:
                await ws.wait_closed()
                return
            async for raw in ws:
                assert isinstance(raw, bytes)
                msg = protocol.decode(raw, self.limits)
                with self._cond:
                    self.received.append(msg)
                    self._cond.notify_all()
        except Exception:
            return
        finally:
            self._clients.discard(ws)
