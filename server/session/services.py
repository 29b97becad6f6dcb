"""What a session needs from below, as narrow interfaces: a render backend and the shared
encoding resources. The server passes the GPU queue and its encoder pool; unit tests pass a
backend that draws without a GPU."""

from __future__ import annotations

import asyncio
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from server.metrics import Metrics
from server.pipeline.encoder import ImageEncoder
from server.pipeline.gpu import DisplayRequest, RenderOutput, RenderRequest
from server.pipeline.video import VideoEncoders
from server.render.boxes import Shown
from server.session.steering_log import SteeringLog
from structures.selection_pool import SelectionPool


class RenderBackend(Protocol):
    """Renders images of snapshots, one slot (renderer) per caller; `GpuQueue` is the real one."""

    @property
    def actual_device(self) -> str: ...

    @property
    def device_name(self) -> str:
        """The device renders run on, named before the first render too."""

    async def render(self, request: RenderRequest) -> RenderOutput: ...

    async def pick(
        self, request: RenderRequest, x: int, y: int
    ) -> tuple[int | None, float | None, str | None]: ...

    async def release(self, slot: str) -> None: ...

    async def display(self, request: DisplayRequest) -> Shown:
        """A frame as displayed (the periodic steps), on the slot's device."""

    def stage(self, slot: str, positions_id: int, positions: npt.NDArray[np.float32]) -> None:
        """A new frame arrived for `slot`: the backend may start moving it towards the device
        now, ahead of its render (on the event loop: it must not block)."""


@dataclass(frozen=True)
class Services:
    """Resources every session of a server shares."""

    backend: RenderBackend
    encoders: Executor
    encoder: ImageEncoder
    encode_slots: asyncio.Semaphore
    """Taken before a render, given back when its encode ends: bounds encodes in flight."""
    metrics: Metrics
    steering_log: SteeringLog
    video: VideoEncoders = field(default_factory=lambda: VideoEncoders(("h264",)))
    """Which video encoders this server has (probed on first use)."""
    video_kbps_per_mpixel: float = 4500.0
    video_min_kbps: float = 350.0
    video_streams_per_session: int = 8
    """Video streams (each with its encoder) one session may have open at once."""
    selections: SelectionPool = field(default_factory=SelectionPool)
    """The worker processes that evaluate layer selections (never the event loop)."""
