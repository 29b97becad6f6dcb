"""Stand-ins for what a session talks to, so its logic is tested without a GPU or a socket:
a render backend that paints small images from the snapshot it is given, and a transport that
keeps what is sent."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Coroutine
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import protocol as p
from server.metrics import Metrics
from server.pipeline.encoder import ImageEncoder
from server.pipeline.gpu import DisplayRequest, RenderOutput, RenderRequest
from server.render.boxes import Shown
from server.session.clients import Client
from server.session.services import Services
from server.session.steering_log import SteeringLog


@dataclass
class Loopback:
    """A transport that records every message sent through it."""

    sent: list[bytes] = field(default_factory=list)
    closed: int | None = None

    async def send_bytes(self, data: bytes) -> None:
        self.sent.append(data)

    async def close(self, code: int = 1000, reason: str | None = None) -> None:
        self.closed = code

    def messages(self) -> list[p.Message]:
        return [p.decode(raw, p.Limits(max_message_bytes=1 << 30)) for raw in self.sent]


@dataclass
class PaintBackend:
    """Paints each requested image a flat grey whose level is the snapshot's positions id, so a
    test can tell from the pixels which frame was drawn; picks answer atom 0 at depth 1."""

    requests: list[RenderRequest] = field(default_factory=list)
    released: list[str] = field(default_factory=list)
    staged: list[tuple[str, int]] = field(default_factory=list)
    displayed: list[DisplayRequest] = field(default_factory=list)
    transforms: dict[str, Any] = field(default_factory=dict)
    actual_device: str = "paint"
    gate: asyncio.Event | None = None
    """When set, renders wait for it (to hold a render in flight)."""

    @property
    def device_name(self) -> str:
        return self.actual_device

    async def render(self, request: RenderRequest) -> RenderOutput:
        self.requests.append(request)
        if self.gate is not None:
            await self.gate.wait()
        level = request.snapshot.positions_id % 256
        rgba = np.full((request.height, request.width, 4), level, dtype=np.uint8)
        hist = np.ones(64, np.float32) if request.histogram else None
        return RenderOutput(rgba, {"total": 1.0, "grid": 0.5, "upload": 0.1}, hist)

    async def pick(
        self, request: RenderRequest, x: int, y: int
    ) -> tuple[int | None, float | None, str | None]:
        self.requests.append(request)
        return 0, 1.0, None

    async def release(self, slot: str) -> None:
        self.released.append(slot)
        self.transforms.pop(slot, None)

    async def display(self, request: DisplayRequest) -> Shown:
        """The periodic steps themselves, on warp's CPU device."""
        from server.render.periodic import PeriodicTransform

        self.displayed.append(request)
        transform = self.transforms.setdefault(request.slot, PeriodicTransform("cpu"))
        transform.set_topology(request.topology)
        if request.restart:
            transform.restart()
        return transform.apply(request.positions, request.box, request.options, request.reference)

    def stage(self, slot: str, positions_id: int, positions: np.ndarray) -> None:
        self.staged.append((slot, positions_id))


def services(tmp_path: Path, backend: PaintBackend | None = None, slots: int = 2) -> Services:
    return Services(
        backend=backend or PaintBackend(),
        encoders=ThreadPoolExecutor(max_workers=slots),
        encoder=ImageEncoder(),
        encode_slots=asyncio.Semaphore(slots),
        metrics=Metrics(),
        steering_log=SteeringLog(tmp_path / "logs"),
    )


def client(client_id: str, role: p.Role = "steerer") -> Client:
    return Client(client_id, role, f"test-{role}", ws=Loopback())


def sent(c: Client) -> list[p.Message]:
    """What has been queued for a client (control messages, then its unsent image)."""
    out = [p.decode(raw, p.Limits(max_message_bytes=1 << 30)) for raw in c._control]
    if c._image is not None:
        out.append(p.decode(c._image[1], p.Limits(max_message_bytes=1 << 30)))
    return out


def run_on_own_loop(main: Callable[[], Coroutine[Any, Any, None]], timeout_s: float = 60) -> None:
    """Run `main()` with asyncio in a thread of its own: another test's framework may hold
    this thread's event loop."""
    errors: list[BaseException] = []

    def target() -> None:
        try:
            asyncio.run(main())
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=target)
    thread.start()
    thread.join(timeout_s)
    assert not thread.is_alive(), "the test hung"
    if errors:
        raise errors[0]
