"""Encoding rendered pixels and offering the images to a view group's clients.

Renders and encodes overlap: a render hands its pixels here and the next render starts at once.
Each encode holds one of the shared encode slots (taken before its render), so encodes in flight
never outnumber the encoder threads. Clients keep only their newest image (`Client.offer_encoded`),
so an image whose encode finishes after a newer one's is dropped as stale.

Viewers that decode video get frames of a video stream instead (`streams.VideoStreams`): each
stream encodes in a task of its own, started in render order and serialised by the stream's
lock, so its encoder sees frames in order. A stream encodes a frame only when one of its viewers
is ready for it (`LinkEstimate.ready`): a slow link gets fewer frames, not a queue. While a
viewer waits for its change to show, a frame that shows it nothing new is left out, so the
encoder is free when the frame with the change arrives (steer-to-photon is one encode shorter).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any

import protocol as p
from server.heap import give_back_memory
from server.pipeline.gpu import RenderOutput
from server.pipeline.video import FORMAT, WEBCODECS
from server.session.clients import Client, ClientState, ImageOffer
from server.session.services import Services
from server.session.streams import VideoStream, VideoStreams

log = logging.getLogger("scalesteer.session")

HOLD_S = 0.1
"""A video stream leaves a frame out for a viewer's pending change at most this long after its
last encoded frame (motion keeps flowing at 10 frames/s or more)."""


@dataclass(frozen=True)
class Rendered:
    """A render waiting for its encode: the pixels and what its image message will say."""

    out: RenderOutput
    image_id: int
    step: int
    width: int
    height: int
    jpeg_quality: int
    """What its JPEG is encoded at (`RenderScheduler.jpeg_quality`; the render lane may have
    encoded it already, `RenderOutput.jpeg`)."""
    still: bool
    camera_json: str = ""
    stream_size: tuple[int, int] = (0, 0)
    """The size video streams of this view encode at: the full image size whatever the frame
    budget or a single interactive render made of this render (scaled to it), the interactive
    size while someone steers (`RenderScheduler.steering`)."""
    rest: bool = False
    """The view rests: video viewers get this one as a near-lossless JPEG still."""


class Delivery:
    """Encodes a session's renders off the event loop and offers them to its clients."""

    def __init__(self, session_id: str, services: Services) -> None:
        self.session_id = session_id
        self.services = services
        self.last_encode_ms = 0.0
        self.streams = VideoStreams(
            services.video,
            services.video_kbps_per_mpixel,
            services.video_min_kbps,
            services.video_streams_per_session,
        )
        self._tasks: set[asyncio.Task[None]] = set()

    def start(
        self,
        rendered: Rendered,
        members: list[Client],
        refs: dict[str, int | None],
        on_failure: Callable[[], None],
    ) -> None:
        """Encode and offer in tasks of their own; the caller's encode slot is released when
        they end. `on_failure` runs when the encode fails (the view must render again)."""
        now = time.monotonic()
        # first the streams their viewers left (a slot they free serves this render)
        self._closed(self.streams.leave_empty())
        # a viewer that left while this rendered needs no image (nor a stream opened for it)
        members = [c for c in members if c.state is ClientState.CONNECTED]
        stills: list[Client] = []
        by_stream: dict[VideoStream, list[Client]] = {}
        group = frozenset(c.client_id for c in members)
        # only its JPEG came back (encoded on the render's device for JPEG viewers): a viewer
        # that asked for video since gets that JPEG, and its stream starts with the next render
        no_frame = rendered.out.rgba is None and rendered.out.i420 is None
        for client in members:
            codec = self.streams.codec_for(client)
            if codec is None:
                if client.video_stream is not None:
                    client.leave_video()
                    self.streams.leave(client.client_id)
                if not rendered.rest:  # a JPEG viewer has this picture already
                    stills.append(client)
            elif rendered.rest or no_frame:
                stills.append(client)
            else:
                stream = self.streams.stream_for(client, codec, rendered.camera_json, now, group)
                if stream is None:  # no stream to spare: JPEG, and the viewer is told why
                    self._refuse_video(client)
                    stills.append(client)
                else:
                    client.video_refused = False
                    by_stream.setdefault(stream, []).append(client)
        self._closed(self.streams.reap(now))
        # created here, in render order: each takes its stream's lock before any other await
        video = []
        for stream, clients in by_stream.items():
            stream.newest = max(stream.newest, rendered.image_id)
            coro = self._encode_video(rendered, stream, clients, refs)
            video.append(self._spawn(coro, f"video-{stream.stream_id}-{rendered.image_id}"))
        self._spawn(
            self._encode_and_offer(rendered, stills, refs, on_failure, video),
            f"encode-{rendered.image_id}",
        )

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        task = asyncio.create_task(coro, name=f"{name}-{self.session_id}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def in_flight(self) -> list[asyncio.Task[None]]:
        return list(self._tasks)

    def leave(self, client: Client) -> None:
        self._closed(self.streams.leave(client.client_id))

    def close(self) -> None:
        """The session ends: its streams close (their encoders and slots go back)."""
        self._closed(self.streams.close())

    def _refuse_video(self, client: Client) -> None:
        if client.video_stream is not None:
            client.leave_video()
        if not client.video_refused:  # told once, until it gets a stream again
            client.video_refused = True
            self.services.metrics.errors.labels(p.ErrorCode.CAPACITY.value).inc()
            client.send(
                p.Error(
                    code=p.ErrorCode.CAPACITY, message=self.streams.refusal(), path="view.video"
                )
            )

    def _closed(self, streams: int) -> None:
        """Streams closed: the heap their encoders held goes back to the system."""
        if streams:
            asyncio.get_running_loop().run_in_executor(None, give_back_memory)

    def _packer(
        self, rendered: Rendered, fmt: str, data: bytes, encode_ms: float, **video: Any
    ) -> Callable[[int | None], bytes]:
        """The image message of an encode, packed once per `ref` it is sent with (viewers that
        echo the same ref share the bytes). `video` adds a video frame's fields."""
        out = rendered.out
        hist = p.WireArray.from_numpy(out.histogram, "<f4") if out.histogram is not None else None
        fields: dict[str, Any] = {
            "frame_id": rendered.image_id,
            "step": rendered.step,
            "format": fmt,
            "data": data,
            "width": rendered.width,
            "height": rendered.height,
            "still": rendered.still,
            "render_ms": out.timings.get("total", 0.0),
            "encode_ms": encode_ms,
            "server_time": time.time(),
            "histogram": hist,
            **video,
        }
        packed: dict[int | None, bytes] = {}

        def pack(ref: int | None) -> bytes:
            if ref not in packed:
                packed[ref] = p.encode(p.Image(ref=ref, **fields))
            return packed[ref]

        return pack

    async def _encode_video(
        self,
        rendered: Rendered,
        stream: VideoStream,
        clients: list[Client],
        refs: dict[str, int | None],
    ) -> None:
        try:
            await self._encode_frame(rendered, stream, clients, refs)
        finally:
            if not stream.members:  # its viewers left while it encoded: it closes now
                self._closed(self.streams.leave_empty())

    async def _encode_frame(
        self,
        rendered: Rendered,
        stream: VideoStream,
        clients: list[Client],
        refs: dict[str, int | None],
    ) -> None:
        services = self.services
        async with stream.lock:
            if stream.closed or rendered.image_id < stream.newest:
                # a newer render waits behind this one: encode that (each encode would
                # otherwise queue behind the last and every frame would arrive later)
                services.metrics.frames_dropped.inc()
                return
            now = time.monotonic()
            # frame rate follows the links: encode only for viewers ready for a frame (at most
            # the last one still waiting to be written, their link not full), else skip this
            # render. (The last frame's offer may not have reached its socket yet: its sender
            # runs after this task, so one queued frame is no sign of a slow viewer.)
            takers = [c for c in clients if c.video_queued <= 1 and c.link.ready(now)]
            if not takers:
                for client in clients:  # drawn once the link is ready again (`on_frame_ack`)
                    client.needs_image = True
                    services.metrics.frames_dropped.inc()
                return
            # a keyframe when a ready viewer waits for one (it joined, or lost frames)
            key = any(c.awaiting_key for c in takers)
            if not key and self._nothing_new(stream, takers, refs, now):
                for client in takers:  # drawn with the change, or once the link acks
                    client.needs_image = True
                services.metrics.frames_dropped.inc()
                return
            stream.shown_refs = {c.client_id: refs.get(c.client_id) for c in takers}
            stream.last_encoded = now
            loop = asyncio.get_running_loop()
            kbps = self.streams.kbps(stream, rendered.stream_size)
            try:
                frame = await loop.run_in_executor(
                    services.encoders,
                    stream.encode,
                    rendered.out.rgba,
                    kbps,
                    rendered.stream_size,
                    key,
                    rendered.out.i420,
                )
            except Exception as exc:
                if stream.closed:  # closed while this frame waited for the encoder thread
                    return
                log.warning(
                    "video encoder %s failed in session %s (%s: %s); its viewers get JPEG",
                    stream.encoder_name,
                    self.session_id,
                    type(exc).__name__,
                    exc,
                )
                stream.close()
                for client in clients:
                    client.force_jpeg = True
                    client.leave_video()
                    client.needs_image = True
                    self.streams.leave(client.client_id)
                return
        services.metrics.encode_ms.observe(frame.encode_ms)
        self.last_encode_ms = frame.encode_ms
        stream.frames += 1
        stream.keyframes += frame.key
        pack = self._packer(
            rendered,
            FORMAT[stream.codec],
            frame.data,
            frame.encode_ms,
            width=rendered.stream_size[0],
            height=rendered.stream_size[1],
            codec=WEBCODECS[stream.codec],
            key=frame.key,
            stream=stream.stream_id,
            bitrate_kbps=kbps,
            encoder=stream.encoder_name,
        )
        for client in clients:
            data = pack(refs.get(client.client_id))
            offer = client.offer_video(stream.stream_id, rendered.image_id, data, frame.key)
            if offer is ImageOffer.OVERFLOW:
                # a link that cannot keep up: a lower rung (a stream of its own), and a
                # keyframe once it is ready again
                client.link.overflowed(time.monotonic())
                services.metrics.frames_dropped.inc()
            elif offer is ImageOffer.WAITING:
                services.metrics.frames_dropped.inc()

    @staticmethod
    def _nothing_new(
        stream: VideoStream, takers: list[Client], refs: dict[str, int | None], now: float
    ) -> bool:
        """Whether to leave this frame out: a viewer waits for its change (it steered or
        moved since this frame's render began), while the frame shows every viewer nothing
        but motion past what its last frame showed. The encoder then stays free for the render
        that carries the change, which would otherwise wait one whole encode behind this one;
        a stream that went `HOLD_S` without a frame encodes it anyway."""
        if now - stream.last_encoded > HOLD_S:
            return False
        waiting = any(c.view_ref != refs.get(c.client_id) for c in takers)
        return waiting and all(
            stream.shown_refs.get(c.client_id, -1) == refs.get(c.client_id) for c in takers
        )

    async def _encode_and_offer(
        self,
        rendered: Rendered,
        members: list[Client],
        refs: dict[str, int | None],
        on_failure: Callable[[], None],
        video: list[asyncio.Task[None]],
    ) -> None:
        services = self.services
        try:
            if members and rendered.out.rgba is None and rendered.out.jpeg is None:
                # rendered for video viewers only, and one of them now wants JPEG (its video
                # failed, or it dropped video since): it gets the next render
                for client in members:
                    client.needs_image = True
                on_failure()
            elif members:
                await self._encode_jpeg(rendered, members, refs, on_failure)
            if video:
                await asyncio.gather(*video, return_exceptions=True)
        finally:
            services.encode_slots.release()

    async def _encode_jpeg(
        self,
        rendered: Rendered,
        members: list[Client],
        refs: dict[str, int | None],
        on_failure: Callable[[], None],
    ) -> None:
        services = self.services
        loop = asyncio.get_running_loop()
        try:
            if rendered.out.jpeg is not None:  # encoded on the render's device
                data, encode_ms = rendered.out.jpeg, rendered.out.jpeg_ms
            else:
                data, encode_ms = await loop.run_in_executor(
                    services.encoders,
                    services.encoder.encode,
                    rendered.out.image(),
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
        self.last_encode_ms = encode_ms
        services.metrics.encode_ms.observe(encode_ms)
        pack = self._packer(rendered, "jpeg", data, encode_ms)
        now = time.monotonic()
        for client in members:
            if client.paced_images and not client.link.ready(now):
                # its link still carries older images: drawn once it acknowledges them
                client.needs_image = True
                services.metrics.frames_dropped.inc()
                continue
            match client.offer_encoded(rendered.image_id, pack(refs.get(client.client_id))):
                case ImageOffer.REPLACED:
                    services.metrics.frames_dropped.inc()
                case ImageOffer.STALE:
                    services.metrics.frames_stale.inc()
                case _:
                    pass
