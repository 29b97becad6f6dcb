"""A session's video streams: who shares which encoder.

Viewers that see the same view (camera and canvas), decode the same codec and whose links sit on
the same bit-rate rung share one stream: one encode serves them all. A viewer whose link is
slower lands on a lower rung and so on a stream of its own; a viewer with its own camera has its
own. A viewer that joins a stream (it connected, its rung or view changed) gets a keyframe on
that stream's next frame it is ready for, and nothing of the stream before it.

A stream follows its viewers' camera: when every viewer of a stream is in the render group of
a new camera (one viewer turning its own camera, the dashboard's drag; or all the viewers of a
camera that changes for them together), the stream carries on under the new camera with delta
frames. A viewer that leaves the others' view (or changes size, codec or rung) starts a stream
of its own at a keyframe: a keyframe per camera move would swamp a slow link while the user
turns the molecule.

Encoders cost memory (`server.pipeline.video.VideoEncoders`), so a session opens at most
`max_streams` streams and the server at most its `max_streams` in all: a viewer that would need
one more gets JPEG images (and one `capacity` error naming the limit) until a stream closes. A
stream closes, and its encoder with it, as soon as its last viewer leaves it.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from server.pipeline.video import EncodedFrame, VideoEncoder, VideoEncoders
from server.session.clients import Client
from server.session.link import rung

log = logging.getLogger("scalesteer.video")

StreamKey = tuple[str, int, int, str, int]
"""(camera JSON, canvas width, canvas height, codec, rung in kbit/s)."""

IDLE_S = 10.0
"""A stream no frame went to for this long is closed (its encoder freed)."""


@dataclass(eq=False)
class VideoStream:
    """One encoder's output and the viewers it goes to."""

    stream_id: int
    key: StreamKey
    codec: str
    encoder_name: str
    kbps: float
    members: set[str] = field(default_factory=set)
    """Clients that got this stream's last keyframe (or joined and wait for the next one)."""
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    """Held while a frame encodes: frames go into the encoder in the order they rendered."""
    last_used: float = 0.0
    newest: int = 0
    """The newest render offered to this stream: an older one still waiting for the lock is
    skipped (the encoder takes the newest picture, as a JPEG viewer's slot does)."""
    shown_refs: dict[str, int | None] = field(default_factory=dict)
    """Per viewer, the last change (`view_ref`) its last encoded frame showed."""
    last_encoded: float = float("-inf")
    """When the last frame went into the encoder (monotonic seconds)."""
    frames: int = 0
    keyframes: int = 0
    """Frames encoded, and how many of them were keyframes (joins, resizes, lost frames)."""
    closed: bool = False
    """Its viewers left and its slot was given back: an encode still waiting for the lock
    finds it so and leaves the frame out."""
    _encoder: VideoEncoder | None = None
    _busy: threading.Lock = field(default_factory=threading.Lock)
    """Held by the encoder thread while it encodes and by `close`: an encoder is never
    closed under a frame (a cancelled encode task leaves its thread running)."""

    def encode(
        self,
        rgba: npt.NDArray[np.uint8] | None,
        kbps: float,
        size: tuple[int, int],
        key: bool,
        i420: npt.NDArray[np.uint8] | None = None,
    ) -> EncodedFrame:
        """Encode one frame at `size` (runs in an encoder thread, under `lock`); `key` asks for
        a keyframe. A new size or bit rate opens a new encoder, which starts with one. `i420`:
        the frame already converted at `size` on the device."""
        with self._busy:
            if self.closed:
                raise RuntimeError(f"video stream {self.stream_id} is closed")
            w, h = size
            enc = self._encoder
            if enc is None or (enc.width, enc.height) != (w, h) or enc.kbps != kbps:
                if enc is not None:
                    enc.close()
                enc = self._encoder = VideoEncoder(self.codec, self.encoder_name, w, h, kbps)
                self.kbps = kbps
            return enc.encode(rgba, key=key, i420=i420)

    def close(self) -> None:
        """Close the encoder (a failed one; or the stream's, with `closed` set by its owner);
        the next frame opens a new one unless the stream is closed."""
        with self._busy:
            if self._encoder is not None:
                self._encoder.close()
                self._encoder = None


class VideoStreams:
    """The streams of one session, by `StreamKey`; at most `max_streams` of them."""

    def __init__(
        self,
        encoders: VideoEncoders,
        kbps_per_mpixel: float,
        min_kbps: float,
        max_streams: int = 8,
    ) -> None:
        self.encoders = encoders
        self.kbps_per_mpixel = kbps_per_mpixel
        self.min_kbps = min_kbps
        self.max_streams = max_streams
        self._streams: dict[StreamKey, VideoStream] = {}
        self._ids = itertools.count(1)

    def cap_kbps(self, width: int, height: int) -> float:
        """The bit rate a picture of this size needs at 60 fps for a near-transparent image;
        more would be wasted on a link that has it."""
        return max(self.min_kbps, self.kbps_per_mpixel * width * height / 1e6)

    def codec_for(self, client: Client) -> str | None:
        """The codec `client` is streamed in; None: JPEG (it decodes no video we encode, its
        video failed, or it was refused a stream and none is free yet)."""
        if client.view is None or not client.view.video or client.force_jpeg:
            return None
        if client.video_refused and client.video_stream is None and not self._room():
            return None
        return self.encoders.pick(client.view.video)

    def _room(self) -> bool:
        """Whether a new stream would get a slot now (in this session and in the server)."""
        free = self.encoders.open_streams < self.encoders.max_streams
        return free and len(self._streams) < self.max_streams

    def stream_for(
        self,
        client: Client,
        codec: str,
        camera_json: str,
        now: float,
        group: frozenset[str] = frozenset(),
    ) -> VideoStream | None:
        """The stream `client` gets its next frame from (joining it when that is new), None
        when it would need a new one and the session or the server holds its limit of streams
        (it gets JPEG images meanwhile). `group`: the ids of every client this frame's render
        is for (all see `camera_json`); the client's current stream follows it to the new
        camera when all its viewers are among them."""
        view = client.view
        assert view is not None
        cap = self.cap_kbps(view.width, view.height)
        key: StreamKey = (
            camera_json,
            view.width,
            view.height,
            codec,
            rung(min(client.link.target_kbps, cap)),
        )
        stream = self._streams.get(key)
        if stream is None:
            stream = self._follow(client, key, group | {client.client_id})
        if stream is None:
            self.leave(client.client_id)  # the stream it leaves gives its slot back first
            if len(self._streams) >= self.max_streams or not self.encoders.take_slot():
                return None
            encoder = self.encoders.chosen()[codec]
            stream = VideoStream(next(self._ids), key, codec, encoder, 0.0)
            stream.kbps = self.kbps(stream)
            self._streams[key] = stream
        if client.client_id not in stream.members:
            for other in self._streams.values():
                other.members.discard(client.client_id)
            stream.members.add(client.client_id)
            client.join_stream(stream.stream_id)  # it waits for a keyframe
        stream.last_used = now
        return stream

    def refusal(self) -> str:
        """Why a viewer gets no stream of its own (what `stream_for` returning None means)."""
        if len(self._streams) >= self.max_streams:
            return (
                f"this session streams video for {self.max_streams} views at once, its limit "
                "(max_video_streams_per_session); this view gets JPEG images until one ends"
            )
        return (
            f"the server streams video for {self.encoders.max_streams} views at once, its "
            "limit (max_video_streams); this view gets JPEG images until one ends"
        )

    def _follow(self, client: Client, key: StreamKey, group: frozenset[str]) -> VideoStream | None:
        """The client's stream, moved to `key`, when only the camera differs and all its
        viewers see the new camera too (none stays behind at the old one); else None."""
        stream = next((s for s in self._streams.values() if client.client_id in s.members), None)
        if stream is None or stream.key[1:] != key[1:] or not stream.members <= group:
            return None
        del self._streams[stream.key]
        stream.key = key
        self._streams[key] = stream
        return stream

    def kbps(self, stream: VideoStream, size: tuple[int, int] | None = None) -> float:
        """What the stream encodes at: what its canvas needs when the links of its viewers
        allow that (their rung is the cap's own), else their rung; a frame smaller than the
        canvas (a steering stream's, or one limited by the quality or the CPU's live size) at
        most what its own `size` needs."""
        _, w, h, _, r = stream.key
        cap = self.cap_kbps(w, h)
        kbps = cap if r >= rung(cap) else float(r)
        if size is not None and size[0] * size[1] < w * h:
            kbps = min(kbps, self.cap_kbps(*size))
        return kbps

    def leave(self, client_id: str) -> int:
        """The client leaves its stream, which closes if it was the last viewer (one encoding
        a frame closes when the frame is done); returns how many streams closed."""
        for stream in self._streams.values():
            stream.members.discard(client_id)
        return self._close_where(lambda s: not s.members)

    def leave_empty(self) -> int:
        """Close the streams whose viewers all moved to others; how many closed."""
        return self._close_where(lambda s: not s.members)

    def reap(self, now: float) -> int:
        """Close streams nobody watches or no frame went to for `IDLE_S`; how many closed."""
        return self._close_where(lambda s: not s.members or now - s.last_used > IDLE_S)

    def close(self) -> int:
        """Close every stream (the session ends); how many closed."""
        return self._close_where(lambda s: True, even_encoding=True)

    def _close_where(
        self, condition: Callable[[VideoStream], bool], even_encoding: bool = False
    ) -> int:
        closed = 0
        for key, stream in list(self._streams.items()):
            if condition(stream) and (even_encoding or not stream.lock.locked()):
                del self._streams[key]
                stream.closed = True
                stream.close()
                self.encoders.give_slot()
                closed += 1
        return closed

    def __len__(self) -> int:
        return len(self._streams)

    def describe(self) -> list[dict[str, object]]:
        return [
            {
                "stream": s.stream_id,
                "codec": s.codec,
                "encoder": s.encoder_name,
                "kbps": s.kbps,
                "viewers": len(s.members),
                "frames": s.frames,
                "keyframes": s.keyframes,
            }
            for s in self._streams.values()
        ]
