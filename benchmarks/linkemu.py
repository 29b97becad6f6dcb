"""A slow network link on loopback: a TCP proxy that delays and throttles what goes through it.

    python benchmarks/linkemu.py --listen 9001 --to 8000 --mbit 50 --rtt-ms 40

Each direction is a link of its own, as `tc netem rate 50mbit delay 20ms limit 1000` would
make one: bytes leave one after another at the link rate, arrive the one-way delay later, and at
most `queue_bytes` (1.5 MB, about netem's default of 1000 full packets) wait on the link; when
the queue is full the proxy stops reading, so TCP's flow control pushes back on the sender as a
real bottleneck would. The proxy's sockets take small buffers (64 KiB) so that the kernel does
not hide a second, unlimited queue behind the emulated one.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import socket
import time
from collections import deque
from dataclasses import dataclass, field

CHUNK = 16 * 1024
SOCKET_BUFFER = 64 * 1024


@dataclass
class Link:
    """One direction: rate in bit/s, one-way delay in s, and the bytes it may hold."""

    rate_bps: float
    delay_s: float
    queue_bytes: int = 1_500_000
    _free_at: float = 0.0
    _held: int = 0
    _queue: deque[tuple[float, bytes]] = field(default_factory=deque)
    _space: asyncio.Event = field(default_factory=asyncio.Event)
    _data: asyncio.Event = field(default_factory=asyncio.Event)

    async def put(self, data: bytes) -> None:
        while self._held + len(data) > self.queue_bytes and self._held > 0:
            self._space.clear()
            await self._space.wait()
        now = time.monotonic()
        start = max(now, self._free_at)
        self._free_at = start + len(data) * 8 / self.rate_bps
        self._queue.append((self._free_at + self.delay_s, data))
        self._held += len(data)
        self._data.set()

    async def pump(self, writer: asyncio.StreamWriter) -> None:
        while True:
            while not self._queue:
                self._data.clear()
                await self._data.wait()
            due, data = self._queue.popleft()
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            writer.write(data)
            await writer.drain()
            self._held -= len(data)
            self._space.set()


def _small_buffers(writer: asyncio.StreamWriter) -> None:
    sock = writer.get_extra_info("socket")
    if sock is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)


async def _carry(reader: asyncio.StreamReader, link: Link) -> None:
    while data := await reader.read(CHUNK):
        await link.put(data)


async def _connection(
    client_r: asyncio.StreamReader,
    client_w: asyncio.StreamWriter,
    target: tuple[str, int],
    rate_bps: float,
    delay_s: float,
    queue_bytes: int,
) -> None:
    server_r, server_w = await asyncio.open_connection(*target)
    for w in (client_w, server_w):
        _small_buffers(w)
    up = Link(rate_bps, delay_s, queue_bytes)
    down = Link(rate_bps, delay_s, queue_bytes)
    tasks = [
        asyncio.create_task(_carry(client_r, up)),
        asyncio.create_task(up.pump(server_w)),
        asyncio.create_task(_carry(server_r, down)),
        asyncio.create_task(down.pump(client_w)),
    ]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        for w in (client_w, server_w):
            with contextlib.suppress(Exception):
                w.close()


async def serve(
    listen_port: int,
    target_port: int,
    mbit: float,
    rtt_ms: float,
    queue_bytes: int = 1_500_000,
    ready: object = None,
) -> None:
    async def handle(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        await _connection(
            r, w, ("127.0.0.1", target_port), mbit * 1e6, rtt_ms / 2000.0, queue_bytes
        )

    server = await asyncio.start_server(handle, "127.0.0.1", listen_port)
    if ready is not None:
        ready.set()  # type: ignore[attr-defined]
    async with server:
        await server.serve_forever()


def run(
    listen_port: int, target_port: int, mbit: float, rtt_ms: float, ready: object = None
) -> None:
    """Entry point for a process of its own."""
    asyncio.run(serve(listen_port, target_port, mbit, rtt_ms, ready=ready))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--listen", type=int, required=True)
    ap.add_argument("--to", type=int, required=True)
    ap.add_argument("--mbit", type=float, default=50.0)
    ap.add_argument("--rtt-ms", type=float, default=40.0)
    args = ap.parse_args()
    run(args.listen, args.to, args.mbit, args.rtt_ms)


if __name__ == "__main__":
    main()
