"""Encoding rendered pixels and offering the images to a view group's clients.

Renders and encodes overlap: a render hands its pixels here and the next render starts at once.
Each encode holds one of the shared encode slots (taken before its render), so encodes in flight
never outnumber the encoder threads. Clients keep only their newest image (`Client.offer_encoded`),
so an image whose encode finishes after a newer one's is dropped as stale.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import protocol as p
from server.pipeline.gpu import RenderOutput
from server.session.clients import Client, ImageOffer
from server.session.services import Services

log = logging.getLogger("scalesteer.session")


@dataclass(frozen=True)
class Rendered:
    """A render waiting for its encode: the pixels and what its image message will say."""

    out: RenderOutput
    image_id: int
    step: int
    width: int
    height: int
    jpeg_quality: int
    still: bool


class Delivery:
    """Encodes a session's renders off the event loop and offers them to its clients."""

    def __init__(self, session_id: str, services: Services) -> None:
        self.session_id = session_id
        self.services = services
        self.last_encode_ms = 0.0
        self._tasks: set[asyncio.Task[None]] = set()

    def start(
        self,
        rendered: Rendered,
        members: list[Client],
        refs: dict[str, int | None],
        on_failure: Callable[[], None],
    ) -> None:
        """Encode and offer in a task of its own; the caller's encode slot is released when it
        ends. `on_failure` runs when the encode fails (the view must render again)."""
        task = asyncio.create_task(
            self._encode_and_offer(rendered, members, refs, on_failure),
            name=f"encode-{self.session_id}-{rendered.image_id}",
        )
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def in_flight(self) -> list[asyncio.Task[None]]:
        return list(self._tasks)

    async def _encode_and_offer(
        self,
        rendered: Rendered,
        members: list[Client],
        refs: dict[str, int | None],
        on_failure: Callable[[], None],
    ) -> None:
        services = self.services
        out = rendered.out
        loop = asyncio.get_running_loop()
        try:
            data, encode_ms = await loop.run_in_executor(
                services.encoders,
                services.encoder.encode,
                out.rgba,
                "jpeg",
                rendered.jpeg_quality,
            )
        except Exception:
            log.exception("encoding failed in session %s", self.session_id)
            on_failure()
            for client in members:
                client.send(
                    p.Error(
                        code=p.ErrorCode.INTERNAL, message="encoding failed; see the server log"
                    )
                )
            return
        finally:
            services.encode_slots.release()
        self.last_encode_ms = encode_ms
        services.metrics.encode_ms.observe(encode_ms)
        hist = p.WireArray.from_numpy(out.histogram, "<f4") if out.histogram is not None else None
        base = p.Image(
            frame_id=rendered.image_id,
            step=rendered.step,
            format="jpeg",
            data=data,
            width=rendered.width,
            height=rendered.height,
            still=rendered.still,
            render_ms=out.timings.get("total", 0.0),
            encode_ms=encode_ms,
            server_time=time.time(),
            histogram=hist,
        )
        packed: dict[int | None, bytes] = {}  # viewers that echo the same ref share the bytes
        for client in members:
            ref = refs.get(client.client_id)
            if ref not in packed:
                packed[ref] = p.encode(base.model_copy(update={"ref": ref}))
            match client.offer_encoded(rendered.image_id, packed[ref]):
                case ImageOffer.REPLACED:
                    services.metrics.frames_dropped.inc()
                case ImageOffer.STALE:
                    services.metrics.frames_stale.inc()
                case _:
                    pass
