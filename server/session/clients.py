"""One connected WebSocket peer and its outgoing queues.

Control messages (state, acks, errors) are queued in order; images go through a slot of depth
one where the newest replaces an unsent older one, so a slow client only loses its own frames
and never holds anyone else up. Images are encoded in parallel and may finish out of order, so
the slot refuses an image older than one the client already got. Video frames go through a
short queue instead (each depends on the one before): every frame of the client's stream, in
order, and a client that lets 4 pile up loses them and restarts at a keyframe.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import protocol as p
from server.session.link import LinkEstimate

log = logging.getLogger("scalesteer.clients")

MAX_QUEUED_CONTROL = 1024
MAX_QUEUED_VIDEO = 4
"""Video frames a client may have waiting to be sent; more and it starts over at a keyframe."""
SEND_QUEUE_BYTES = 16384
"""Bytes that may wait in front of a client's network link before an image is written behind
them (or the image's own size, if larger): the rest wait in the slot, where a newer one replaces
them. The kernel's send buffer holds up to 4 MB: images written behind that much reached a slow
reader minutes old."""
QUEUE_POLL_S = (0.001, 0.25)
"""How soon a sender looks again whether its link has taken what waits in front of it: first
after a millisecond (a link busy for a moment), then twice as long each time, up to 0.25 s
(250 stalled viewers took 10 % of a core; looked at up to 20 ms apart, 25-35 %)."""
SLOT_WAIT_S = 2.0
"""The longest an image waits in the slot for its link: one too slow for the control messages
alone (under about 1 KB/s) never had less waiting in front of it, and got no image at all."""


class Transport(Protocol):
    """What a client sends through: a WebSocket in the server, anything alike in tests."""

    async def send_bytes(self, data: bytes) -> None: ...

    async def close(self, code: int = 1000, reason: str | None = None) -> None: ...


class ClientState(enum.Enum):
    CONNECTED = "connected"
    CLOSING = "closing"
    CLOSED = "closed"


class ImageOffer(enum.Enum):
    """What became of an image offered to a client."""

    TAKEN = "taken"
    REPLACED = "replaced"
    """Taken, and an unsent older image was dropped for it."""
    STALE = "stale"
    """Dropped: a newer image had already been offered."""
    WAITING = "waiting"
    """Video: dropped, the client waits for a keyframe of its stream."""
    OVERFLOW = "overflow"
    """Video: the client's queue was full; it lost its frames and waits for a keyframe."""
    CLOSED = "closed"


@dataclass(eq=False)
class Client:
    """A peer of a session: simulation, steerer or viewer."""

    client_id: str
    role: p.Role
    name: str
    ws: Transport
    instance: str | None = None
    """The client's identity across its reconnections (`hello.instance`): a simulation
    adapter's, or a dashboard page's (what it starts is tied to it: `server.web.owners`)."""
    view: p.View | None = None
    view_ref: int | None = None
    interacting_until: float = 0.0
    interacted_at: float = float("-inf")
    """When its last interacting view came (monotonic seconds): its video stream stays at the
    steering size for `video_steer_hold_s` after it."""
    needs_image: bool = True
    served_at: float = float("-inf")
    """When a render for it was last planned (monotonic seconds): views that have waited
    longest come first when a pass cannot render them all."""
    frames_sent: int = 0
    frames_dropped: int = 0
    newest_frame: int = 0
    """`frame_id` of the newest image offered; an older one arriving later is stale."""
    state: ClientState = ClientState.CONNECTED
    link: LinkEstimate = field(default_factory=LinkEstimate)
    """Video only: what this client's link takes (from its `frame_ack`s)."""
    force_jpeg: bool = False
    """Video failed for this client (its encoder could not run): JPEG from now on."""
    video_stream: int | None = None
    """The video stream this client is on (None: JPEG)."""
    video_refused: bool = False
    """It was told that no video stream was free for it (and gets JPEG images meanwhile)."""
    awaiting_key: bool = True
    paced_images: bool = False
    """It acknowledges its JPEG images too (the dashboard does): they then go only while its
    link is ready, as video frames do, so a slow link shows fewer images instead of old ones."""
    queued: Callable[[], int] | None = None
    """Bytes written to its socket that have not gone out on the network yet (None: unknown,
    as with transports other than the server's own)."""
    _control: deque[bytes] = field(default_factory=deque)
    _image: tuple[int, bytes] | None = None
    _video: deque[tuple[int, bytes]] = field(default_factory=deque)
    _wake: asyncio.Event = field(default_factory=asyncio.Event)

    def info(self) -> p.ClientInfo:
        return p.ClientInfo(client_id=self.client_id, role=self.role, client=self.name)

    def send(self, message: p.Message) -> None:
        """Queue a control message; a peer that lets 1024 pile up is disconnected."""
        if self.state is ClientState.CONNECTED:
            self.send_encoded(p.encode(message))

    def send_encoded(self, data: bytes) -> None:
        """Queue an encoded control message (one encoding serves every client of a broadcast)."""
        if self.state is not ClientState.CONNECTED:
            return
        if len(self._control) >= MAX_QUEUED_CONTROL:
            log.warning("client %s is not reading; disconnecting", self.client_id)
            self._control.clear()
            self._control.append(
                p.encode(
                    p.Error(
                        code=p.ErrorCode.RATE_LIMITED,
                        message=f"{MAX_QUEUED_CONTROL} messages waited for this client to read "
                        "them; disconnecting (read faster, or send less)",
                    )
                )
            )
            self.state = ClientState.CLOSING
            self._wake.set()
            return
        self._control.append(data)
        self._wake.set()

    @property
    def backlog(self) -> int:
        """Control messages queued and not yet sent."""
        return len(self._control)

    def offer_image(self, message: p.Image) -> ImageOffer:
        """Put an image in the slot (see `offer_encoded`)."""
        return self.offer_encoded(message.frame_id, p.encode(message))

    def offer_encoded(self, frame_id: int, data: bytes) -> ImageOffer:
        """Put an encoded image in the slot, unless a newer one was offered before it."""
        if self.state is not ClientState.CONNECTED:
            return ImageOffer.CLOSED
        if frame_id <= self.newest_frame:
            self.frames_dropped += 1
            return ImageOffer.STALE
        self.newest_frame = frame_id
        replaced = self._image is not None
        if replaced:
            self.frames_dropped += 1
        self._image = (frame_id, data)
        self._wake.set()
        return ImageOffer.REPLACED if replaced else ImageOffer.TAKEN

    def join_stream(self, stream_id: int) -> None:
        """Switch to another video stream: what is queued of the old one goes, and nothing of
        the new one is taken before its keyframe."""
        self.video_stream = stream_id
        self.awaiting_key = True
        self._video.clear()
        self.link.forget_in_flight()

    def leave_video(self) -> None:
        self.video_stream = None
        self.awaiting_key = True
        self._video.clear()

    def offer_video(self, stream_id: int, frame_id: int, data: bytes, key: bool) -> ImageOffer:
        """Queue a frame of a video stream; every frame goes, in order (each depends on the
        last), so a client that cannot keep up loses its queue and restarts at a keyframe."""
        if self.state is not ClientState.CONNECTED:
            return ImageOffer.CLOSED
        if stream_id != self.video_stream or (self.awaiting_key and not key):
            self.frames_dropped += 1
            return ImageOffer.WAITING
        if len(self._video) >= MAX_QUEUED_VIDEO:
            self.frames_dropped += len(self._video) + 1
            self._video.clear()
            self.awaiting_key = True
            return ImageOffer.OVERFLOW
        self.awaiting_key = False
        self.newest_frame = max(self.newest_frame, frame_id)
        self._video.append((frame_id, data))
        self._wake.set()
        return ImageOffer.TAKEN

    @property
    def video_queued(self) -> int:
        return len(self._video)

    def _is(self, state: ClientState) -> bool:
        """The state now (other tasks change it while the sender awaits)."""
        return self.state is state

    async def run_sender(self, on_image_sent: Callable[[], None] | None = None) -> None:
        """Drain the queues until the client closes; control first, then the latest image."""
        poll = QUEUE_POLL_S[0]
        give_up_at: float | None = None  # when the image in the slot stops waiting for the link
        try:
            while not self._is(ClientState.CLOSED):
                await self._wake.wait()
                self._wake.clear()
                while self._control and not self._is(ClientState.CLOSED):
                    await self.ws.send_bytes(self._control.popleft())
                if self._is(ClientState.CLOSING):
                    break  # what was queued is out; now close
                while self._video and self.state is ClientState.CONNECTED:
                    frame_id, data = self._video.popleft()
                    self.link.on_sent(frame_id, len(data), time.monotonic())
                    await self.ws.send_bytes(data)
                    self.frames_sent += 1
                    if on_image_sent is not None:
                        on_image_sent()
                    if self._control:
                        break  # control first, then the rest of the video queue
                if self._video or self._control:
                    self._wake.set()
                    continue
                if self._image is not None and self.state is ClientState.CONNECTED:
                    now = time.monotonic()
                    if (give_up_at is None or now < give_up_at) and self._link_busy():
                        if give_up_at is None:
                            give_up_at = now + SLOT_WAIT_S
                        await asyncio.sleep(min(poll, give_up_at - now))
                        poll = min(2 * poll, QUEUE_POLL_S[1])
                        self._wake.set()  # control first; a newer image may take the slot
                        continue
                    poll, give_up_at = QUEUE_POLL_S[0], None
                    (frame_id, data), self._image = self._image, None
                    if self.paced_images:  # only a client that acknowledges images is paced
                        self.link.on_sent(frame_id, len(data), time.monotonic())
                    await self.ws.send_bytes(data)
                    self.frames_sent += 1
                    if on_image_sent is not None:
                        on_image_sent()
        except Exception:  # the socket went away; the receive loop cleans up
            pass
        finally:
            if self.state is ClientState.CLOSING:
                with contextlib.suppress(Exception):
                    await self.ws.close(code=1008, reason="client too slow")
            self.state = ClientState.CLOSED

    def _link_busy(self) -> bool:
        """Whether more than about an image waits in front of the link: the image in the slot
        waits too (and is replaced by newer ones), so a slow reader gets fewer images, not
        older ones. A client that acknowledges its images is paced by them as well."""
        if self.queued is None or self._image is None:
            return False
        return self.queued() > max(SEND_QUEUE_BYTES, len(self._image[1]))

    def close(self) -> None:
        self.state = ClientState.CLOSED
        self._wake.set()

    def close_after_flush(self) -> None:
        """Send what is queued, then close the socket (1008)."""
        if self.state is ClientState.CONNECTED:
            self.state = ClientState.CLOSING
            self._wake.set()
