"""The per-client send queues: control messages in order, images latest-wins with one slot."""

from __future__ import annotations

import asyncio

import pytest

import protocol as p
from server.session import clients
from server.session.clients import (
    MAX_QUEUED_CONTROL,
    SEND_QUEUE_BYTES,
    Client,
    ClientState,
    ImageOffer,
)
from tests.server.session.fakes import Loopback


def make_client() -> Client:
    return Client("c1", "viewer", "test", ws=Loopback())


def image(i: int) -> p.Image:
    return p.Image(frame_id=i, format="jpeg", data=bytes([i % 256]) * 100, width=1, height=1)


def test_unsent_images_are_replaced_not_queued() -> None:
    client = make_client()
    for i in range(1, 51):
        client.offer_image(image(i))
    assert client.frames_dropped == 49
    assert client._image is not None
    assert p.decode(client._image[1]) == image(50)


def test_an_image_older_than_one_already_offered_is_refused() -> None:
    client = make_client()
    assert client.offer_image(image(5)) is ImageOffer.TAKEN
    assert client.offer_image(image(3)) is ImageOffer.STALE  # its encode finished late
    assert client.offer_image(image(5)) is ImageOffer.STALE
    assert client._image is not None and p.decode(client._image[1]) == image(5)
    assert client.offer_image(image(6)) is ImageOffer.REPLACED
    assert client.frames_dropped == 3
    client.close()
    assert client.offer_image(image(7)) is ImageOffer.CLOSED


def test_control_messages_keep_order_and_a_reader_that_never_reads_is_cut_off() -> None:
    client = make_client()
    for i in range(MAX_QUEUED_CONTROL):
        client.send(p.Pong(ref=i))
    assert len(client._control) == MAX_QUEUED_CONTROL
    assert [p.decode(client._control[i]).ref for i in (0, 1, 2)] == [0, 1, 2]  # type: ignore[attr-defined]
    assert client.state is ClientState.CONNECTED
    client.send(p.Pong(ref=MAX_QUEUED_CONTROL))  # one too many: dropped, and the client goes
    assert client.state is ClientState.CLOSING
    # the backlog is dropped; only the reason is left to send before the close frame
    assert len(client._control) == 1
    reason = p.decode(client._control[0])
    assert isinstance(reason, p.Error) and reason.code == "rate_limited"


def test_replaced_client_flushes_then_closes() -> None:
    client = make_client()
    client.send(p.Error(code=p.ErrorCode.FORBIDDEN, message="replaced"))
    client.close_after_flush()
    assert client.state is ClientState.CLOSING and len(client._control) == 1
    client.offer_image(image(1))  # nothing new is taken once closing
    assert client._image is None


@pytest.fixture
def quick_polls(monkeypatch: pytest.MonkeyPatch) -> float:
    """Looks 1-10 ms apart and a slot wait of at most 0.4 s; the time a check waits."""
    monkeypatch.setattr(clients, "QUEUE_POLL_S", (0.001, 0.01))
    monkeypatch.setattr(clients, "SLOT_WAIT_S", 0.4)
    return 0.05


def test_an_image_waits_while_its_link_holds_more_than_an_image_and_newer_ones_replace_it(
    quick_polls: float,
) -> None:
    """A reader slower than its images had every one queued in the kernel behind the last
    (they reached it minutes old): the slot's image goes only once what waits in front of the
    link is at most about an image, and newer ones replace it meanwhile; control goes first."""
    queued = [SEND_QUEUE_BYTES + 1]
    ws = Loopback()
    client = Client("c1", "viewer", "test", ws=ws, queued=lambda: queued[0])

    async def main() -> None:
        sender = asyncio.create_task(client.run_sender())
        client.offer_image(image(1))
        await asyncio.sleep(quick_polls)
        assert ws.sent == []  # the link is busy: the image waits
        client.send(p.Pong(ref=7))
        client.offer_image(image(2))
        await asyncio.sleep(quick_polls)
        assert ws.messages() == [p.Pong(ref=7)]  # control still goes
        queued[0] = SEND_QUEUE_BYTES
        await asyncio.sleep(quick_polls)
        assert ws.messages() == [p.Pong(ref=7), image(2)]  # the newest, the older one dropped
        assert client.frames_dropped == 1
        client.close()
        await sender

    asyncio.run(main())


def test_an_image_waits_for_its_link_no_longer_than_the_slot_allows(quick_polls: float) -> None:
    """A link too slow for the control messages alone never had less than an image waiting in
    front of it, and its viewer got no image at all: after `SLOT_WAIT_S` the image goes."""
    ws = Loopback()
    client = Client("c1", "viewer", "test", ws=ws, queued=lambda: 1 << 20)
    wait_s = 0.4  # quick_polls' SLOT_WAIT_S

    async def first_sent() -> None:
        while not ws.sent:
            await asyncio.sleep(0.005)

    async def main() -> None:
        sender = asyncio.create_task(client.run_sender())
        loop = asyncio.get_running_loop()
        started = loop.time()
        client.offer_image(image(1))
        await asyncio.sleep(wait_s / 2)
        client.offer_image(image(2))  # replaces it; the wait goes on from the first
        await asyncio.wait_for(first_sent(), 10 * wait_s)
        assert loop.time() - started >= wait_s
        assert ws.messages() == [image(2)]
        client.offer_image(image(3))  # the next one waits afresh
        await asyncio.sleep(wait_s / 2)
        assert ws.messages() == [image(2)]
        client.close()
        await sender

    asyncio.run(main())


def test_an_image_larger_than_the_queue_limit_goes_once_at_most_its_size_waits() -> None:
    big = p.Image(frame_id=1, format="jpeg", data=b"x" * (2 * SEND_QUEUE_BYTES), width=1, height=1)
    size = len(p.encode(big))
    for waiting, goes in ((size, True), (size + 1, False)):
        client = Client("c1", "viewer", "test", ws=Loopback(), queued=lambda w=waiting: w)
        client.offer_image(big)
        assert client._link_busy() is not goes
