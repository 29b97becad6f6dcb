"""What a WebSocket's peer has taken of the bytes written to it, and what still waits to go.

The keep-alive and the stall watch need the bytes the peer has taken (written, less those still
in the transport's buffer and the kernel's send queue, `TIOCOUTQ`); the image sender needs the
bytes that wait in front of the network (the transport's buffer and what the kernel has not
sent yet, `SIOCOUTQNSD`), so that it sends the newest image once the link can carry it instead
of queueing every image behind the last. Both kernel readings are Linux's; elsewhere only the
transport's buffer is counted.
"""

from __future__ import annotations

import asyncio
import fcntl
import sys
import termios
from collections.abc import Callable, MutableMapping
from typing import Any

SIOCOUTQNSD = 0x894B
"""Linux (since 2.6.38): bytes in a TCP socket's send queue not sent yet (in flight excluded)."""
SEND_QUEUE = "scalesteer.send_queue"
"""Scope extension: `{"queued": callable() -> int}`, the bytes waiting to go on this connection."""


def _ioctl_int(fd: int | None, request: int) -> int:
    if fd is None or fd < 0:
        return 0
    out = bytearray(4)
    try:
        fcntl.ioctl(fd, request, out)
    except OSError:
        return 0
    return int.from_bytes(out, sys.byteorder)


class Counted:
    """A transport that counts the bytes written to it."""

    def __init__(self, transport: asyncio.Transport) -> None:
        self._transport = transport
        self.written = 0
        sock = transport.get_extra_info("socket")
        self._fd: int | None = sock.fileno() if sock is not None else None

    def write(self, data: bytes | bytearray | memoryview) -> None:
        self.written += len(data)
        self._transport.write(data)

    def delivered(self) -> int:
        """Bytes the peer has acknowledged: those written less those not acknowledged yet."""
        unacked = self._transport.get_write_buffer_size() + _ioctl_int(self._fd, termios.TIOCOUTQ)
        return self.written - unacked

    def queued(self) -> int:
        """Bytes written that have not gone out on the network yet (in flight excluded)."""
        return self._transport.get_write_buffer_size() + _ioctl_int(self._fd, SIOCOUTQNSD)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)


def scope_extension(scope: MutableMapping[str, Any], name: str, key: str) -> Any:
    """`key` of the scope extension `name` that the server under the app provides (None on
    other servers)."""
    extension = scope.get("extensions", {}).get(name)
    return extension.get(key) if extension else None


def send_queue(scope: MutableMapping[str, Any]) -> Callable[[], int] | None:
    """The connection's `Counted.queued`, where the server under the app provides it."""
    queued: Callable[[], int] | None = scope_extension(scope, SEND_QUEUE, "queued")
    return queued
