"""Raw WebSocket peers that misbehave on purpose: upgrades by hand, floods of tiny frames, and
a viewer's round trips while they run (the hostile-input tests and `benchmarks/flood_bench.py`)."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time

import protocol as p
from tests.server.peers import Peer
from tests.server.processes import VIEWER_TOKEN, ServerProcess


def upgrade_request(port: int, query: str = "", extra: str = "") -> bytes:
    """A WebSocket upgrade request for /ws/view, with `extra` header lines."""
    return (
        f"GET /ws/view{query} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
        "Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
        f"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n{extra}\r\n"
    ).encode()


def upgrade(server: ServerProcess, rcvbuf: int | None = None) -> tuple[socket.socket, int]:
    """A raw WebSocket upgrade to /ws/view: the socket and the status it was answered."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(10)
    sock.connect(("127.0.0.1", server.port))
    sock.sendall(upgrade_request(server.port, f"?token={VIEWER_TOKEN}"))
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(1)
        if not chunk:
            break
        head += chunk
    return sock, int(head.split(b" ", 2)[1]) if head.startswith(b"HTTP/1.1 ") else 0


class Flood(threading.Thread):
    """`sockets` peers that send `frames` over and over for `seconds` and read nothing;
    `flooding` is set once all of them are connected."""

    def __init__(self, server: ServerProcess, frames: bytes, seconds: float, sockets: int) -> None:
        super().__init__(daemon=True)
        self.server, self.seconds, self.sockets = server, seconds, sockets
        self.block = frames * (262_144 // len(frames)) if frames else b""
        self.flooding = threading.Event()

    def run(self) -> None:
        socks = []
        for _ in range(self.sockets):
            sock, status = upgrade(self.server, rcvbuf=4096)
            assert status == 101
            sock.setblocking(False)
            socks.append(sock)
        self.flooding.set()
        until = time.monotonic() + self.seconds
        while time.monotonic() < until:
            if not socks:
                time.sleep(min(0.2, max(0.0, until - time.monotonic())))
                continue
            _, ready, _ = select.select([], socks, [], 0.2)
            for sock in ready:
                with contextlib.suppress(OSError):
                    sock.send(self.block)
        for sock in socks:
            sock.close()


def flood(server: ServerProcess, frames: bytes, seconds: float, sockets: int = 1) -> Flood:
    """A started `Flood` (no sockets: one that only waits, the control)."""
    thread = Flood(server, frames, seconds, sockets)
    thread.start()
    return thread


def round_trips(viewer: Peer, attacker: Flood) -> list[float]:
    """`viewer`'s protocol ping round trips, sorted, while `attacker` floods (from when all of
    its sockets are connected)."""
    attacker.flooding.wait(60)
    time.sleep(0.1)
    rtts = []
    while attacker.is_alive():
        sent = time.monotonic()
        viewer.send(p.Ping(client_time=sent))
        viewer.expect(p.Pong, 30)
        rtts.append(time.monotonic() - sent)
        time.sleep(0.02)
    return sorted(rtts)
