"""Delivery of images by the links they go over: a video frame that shows a waiting viewer
nothing new is left out while its change is on the way (the change's frame does not wait behind
it), and JPEG images go to a viewer that acknowledges them only while its link is ready."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np

import protocol as p
from server.pipeline.gpu import RenderOutput
from server.session.clients import Client
from server.session.delivery import HOLD_S, Delivery, Rendered
from tests.server.session.fakes import client, run_on_own_loop, services

SIZE = (64, 48)


def rendered(image_id: int) -> Rendered:
    rgba = np.full((SIZE[1], SIZE[0], 4), 40 * image_id % 256, dtype=np.uint8)
    return Rendered(
        RenderOutput(rgba, {"total": 1.0}),
        image_id,
        image_id,
        *SIZE,
        jpeg_quality=85,
        still=False,
        camera_json="{}",
        stream_size=SIZE,
    )


def shown(c: Client, seen: list[int]) -> list[int]:
    """The frames the viewer got so far: its queue is sent and each frame acknowledged, as the
    dashboard does (`seen` keeps what earlier calls took)."""
    limits = p.Limits(max_message_bytes=1 << 30)
    while c._video:
        _, raw = c._video.popleft()
        msg = p.decode(raw, limits)
        assert isinstance(msg, p.Image)
        c.link.on_ack(msg.frame_id, time.monotonic())
        seen.append(msg.frame_id)
    return seen


async def deliver(
    delivery: Delivery, image_id: int, c: Client, refs: dict[str, int | None] | None = None
) -> None:
    """Offer one render, holding the encode slot a render pass takes; `refs` are the changes
    it shows (by default each viewer's newest, as when the pass began after them)."""
    await delivery.services.encode_slots.acquire()
    refs = {c.client_id: c.view_ref} if refs is None else refs
    delivery.start(rendered(image_id), [c], refs, lambda: None)
    while tasks := delivery.in_flight():
        await asyncio.gather(*tasks)


def test_a_frame_without_the_viewers_change_is_left_out_while_the_change_renders(
    tmp_path: Path,
) -> None:
    async def main() -> None:
        delivery = Delivery("s", services(tmp_path))
        c = client("v")
        c.view = p.View(width=SIZE[0], height=SIZE[1], video=["h264"])
        c.view_ref = 1
        seen: list[int] = []
        await deliver(delivery, 1, c)
        assert shown(c, seen) == [1]
        await deliver(delivery, 2, c)  # simulation motion, nothing pending: encoded
        assert shown(c, seen) == [1, 2]
        c.needs_image = False  # served (the scheduler clears it when it plans a render)
        # the viewer steers (seq 5) while render 3, begun before the change, is in flight
        refs_before = {c.client_id: c.view_ref}
        c.view_ref = 5
        await deliver(delivery, 3, c, refs_before)
        assert shown(c, seen) == [1, 2] and c.needs_image  # left out; asked for again
        await deliver(delivery, 4, c)  # the render with the change
        assert shown(c, seen) == [1, 2, 4]

    run_on_own_loop(main)


def test_a_pending_change_never_holds_a_stream_longer_than_the_hold(tmp_path: Path) -> None:
    async def main() -> None:
        delivery = Delivery("s", services(tmp_path))
        c = client("v")
        c.view = p.View(width=SIZE[0], height=SIZE[1], video=["h264"])
        c.view_ref = 1
        await deliver(delivery, 1, c)
        seen = shown(c, [])
        (stream,) = delivery.streams._streams.values()
        stream.last_encoded -= 2 * HOLD_S  # the last frame went out a while ago
        refs_before = {c.client_id: c.view_ref}
        c.view_ref = 2
        await deliver(delivery, 2, c, refs_before)
        assert shown(c, seen) == [1, 2]

    run_on_own_loop(main)


def test_jpeg_images_wait_for_the_link_of_a_viewer_that_acknowledges_them(
    tmp_path: Path,
) -> None:
    async def main() -> None:
        delivery = Delivery("s", services(tmp_path))
        paced, plain = client("paced"), client("plain")
        for c in (paced, plain):
            c.view = p.View(width=SIZE[0], height=SIZE[1])  # no video: JPEG
        paced.paced_images = True
        # an image sent to each 0.5 s ago and not acknowledged yet: a link with a queue
        for c in (paced, plain):
            c.link.on_sent(0, 50_000, time.monotonic() - 0.5)
        await delivery.services.encode_slots.acquire()
        delivery.start(rendered(1), [paced, plain], {}, lambda: None)
        while tasks := delivery.in_flight():
            await asyncio.gather(*tasks)
        assert paced._image is None and paced.needs_image  # held back, drawn after the ack
        assert plain._image is not None and plain._image[0] == 1  # scripts get every image
        paced.link.on_ack(0, time.monotonic())
        await delivery.services.encode_slots.acquire()
        delivery.start(rendered(2), [paced], {}, lambda: None)
        while tasks := delivery.in_flight():
            await asyncio.gather(*tasks)
        assert paced._image is not None and paced._image[0] == 2

    run_on_own_loop(main)
