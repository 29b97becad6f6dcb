"""Video encoding for the live stream (H.264, AV1, VP9 through PyAV/FFmpeg), tuned for latency.

A viewer whose browser decodes video (WebCodecs) gets a video stream instead of one JPEG per
frame: at 1080p60 that is a few Mbit/s instead of a hundred. Every encoder here is set up for
interaction, not for files: no B-frames, no look-ahead, one frame in and one packet out, a
keyframe on demand (a viewer joins, a stream starts), parameter sets in every keyframe (Annex B
for H.264), and a VBV buffer of a quarter second so that no frame bursts far over the rate.

Encoders are probed once, in the order of `CANDIDATES`: NVENC where the GPU has one (the H100
has none, so there `libx264` takes over without anyone asking), then the software encoder. A
codec none of whose encoders opens is not offered. `VideoEncoders.describe()` says what is in
use (shown by /healthz).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np
import numpy.typing as npt

log = logging.getLogger("scalesteer.video")

CANDIDATES: dict[str, tuple[str, ...]] = {
    "h264": ("h264_nvenc", "libx264"),
    "h264-baseline": ("h264_nvenc", "libx264"),
    "av1": ("av1_nvenc", "libsvtav1"),
    "vp9": ("libvpx-vp9",),
}
"""Encoders for each wire codec, hardware first."""

WEBCODECS: dict[str, str] = {
    "h264": "avc1.640033",  # High, level 5.1 (up to 4096x2160 at 60 fps)
    "h264-baseline": "avc1.42E033",  # Constrained Baseline, level 5.1
    "av1": "av01.0.13M.08",  # Main, level 5.1, Main tier, 8 bit
    "vp9": "vp09.00.51.08",  # profile 0, level 5.1, 8 bit
}
"""The WebCodecs codec string a viewer configures its decoder with, per wire codec."""

FORMAT: dict[str, str] = {"h264": "h264", "h264-baseline": "h264", "av1": "av1", "vp9": "vp9"}
"""`image.format` of each wire codec."""

TIME_BASE = Fraction(1, 1000)
"""Frame timestamps in milliseconds of wall time: rate control sees the real frame rate."""


def _threads() -> int:
    """Slices (threads) per encode: zero-latency encoders split each frame and never pipeline
    frames; at 1080p 16 slices were slower than 8 (benchmarks/HISTORY.md, "Video")."""
    return max(1, min(8, os.cpu_count() or 1))


SLICED_KBPS_PER_MPIXEL = 2500.0
"""Bit rate per megapixel of picture below which a stream is encoded in one slice. Slices are
predicted and rate-controlled each on its own: where few bits cover a smooth surface (villin at
sigma 6 in 960x540 at 350 kbit/s, two slices) the boundary between them shows as a horizontal
seam across the picture (a step 1.1 grey levels above the picture's own edges on that row);
from about 1,300 kbit/s (2,500 per megapixel) it no longer shows. One slice also encodes such a
picture no slower here (the bits are few)."""


def slices(kbps: float, width: int, height: int) -> int:
    """Slices (threads) for a stream of this size and bit rate: `_threads()` where the bits
    hide slice boundaries, else one."""
    if kbps < SLICED_KBPS_PER_MPIXEL * width * height / 1e6:
        return 1
    return _threads()


X264_PRESET = "superfast"
"""libx264's speed/quality trade. At 1080p on an H100 host, superfast with 8 slices encoded in
10.5 ms (1M atoms) at the same bit rate and PSNR as veryfast (12.1 ms) and faster (15.7 ms);
benchmarks/HISTORY.md, "Video", has every variant."""


def _options(
    encoder: str, codec: str, kbps: float, fps: float, preset: str | None = None
) -> dict[str, str]:
    """Low-latency options of one encoder at a bit rate."""
    rate = int(kbps * 1000)
    buf = max(rate // 4, 200_000)  # a quarter second of bits: keyframes fit, nothing bursts
    if encoder == "libx264":
        profile = "baseline" if codec == "h264-baseline" else "high"
        return {
            "preset": preset or X264_PRESET,
            "tune": "zerolatency",
            "profile": profile,
            "x264-params": (
                f"bframes=0:rc-lookahead=0:sliced-threads=1:sync-lookahead=0:"
                f"vbv-maxrate={rate // 1000}:vbv-bufsize={buf // 1000}:"
                "repeat-headers=1:annexb=1:"
                "colormatrix=bt709:colorprim=bt709:transfer=bt709:range=tv"
            ),
        }
    if encoder in ("h264_nvenc", "av1_nvenc"):
        opts = {
            "preset": "p4",
            "tune": "ull",
            "zerolatency": "1",
            "delay": "0",
            "rc": "cbr",
            "bf": "0",
            "forced-idr": "1",
        }
        if encoder == "h264_nvenc":
            opts["profile"] = "baseline" if codec == "h264-baseline" else "high"
        return opts
    if encoder == "libsvtav1":
        return {"preset": "10", "svtav1-params": f"pred-struct=1:rc=2:lp={_threads()}"}
    if encoder == "libvpx-vp9":
        return {
            "deadline": "realtime",
            "cpu-used": "8",
            "lag-in-frames": "0",
            "row-mt": "1",
            "error-resilient": "1",
        }
    raise ValueError(f"unknown encoder {encoder!r}")


@dataclass(frozen=True)
class EncodedFrame:
    data: bytes
    key: bool
    encode_ms: float


class VideoEncoder:
    """One stream's encoder: PyAV codec context at one size; frames go in strictly in order.

    Not thread-safe by design: a stream encodes one frame at a time (its owner serialises).
    The size is fixed per encoder; a new size needs a new encoder (and so starts at a key).
    """

    def __init__(
        self,
        codec: str,
        encoder: str,
        width: int,
        height: int,
        kbps: float,
        fps: float = 60.0,
        preset: str | None = None,
        threads: int | None = None,
    ) -> None:
        import av

        if codec not in CANDIDATES:
            raise ValueError(f"unknown video codec {codec!r}")
        # 4:2:0 needs even sides; the encoder pads by one row/column of the edge
        self.width, self.height = width, height
        self.codec, self.encoder, self.kbps = codec, encoder, kbps
        ctx: Any = av.CodecContext.create(encoder, "w")
        ctx.width, ctx.height = width + width % 2, height + height % 2
        ctx.pix_fmt = "yuv420p"
        ctx.time_base = TIME_BASE
        ctx.framerate = Fraction(round(fps), 1)
        ctx.bit_rate = int(kbps * 1000)
        ctx.max_b_frames = 0
        ctx.gop_size = 100_000  # keyframes on demand only (a joiner, a new stream)
        self.threads = threads or slices(kbps, width, height)
        ctx.thread_count = self.threads
        ctx.options = _options(encoder, codec, kbps, fps, preset)
        ctx.open()
        self._ctx = ctx
        self._av = av
        self._t0: float | None = None
        self._last_pts = -1
        self.frames = 0

    def encode(
        self,
        rgba: npt.NDArray[np.uint8] | None,
        key: bool = False,
        pts_ms: int | None = None,
        i420: npt.NDArray[np.uint8] | None = None,
    ) -> EncodedFrame:
        """Encode one (h, w, 4) RGBA image (None when `i420` is given); `key` forces a
        keyframe (IDR). An image of another size than the stream's (a render shrunk to the
        frame budget) is scaled to it, so the stream does not restart at a keyframe each time
        the budget moves. Frames are stamped with the wall time (rate control sees the real
        frame rate) unless `pts_ms` is given. `i420`: the same picture already converted at
        the stream's padded size (the device's `read_i420`), taken instead of converting
        `rgba` here."""
        av = self._av
        t0 = time.perf_counter()
        pw, ph = self._ctx.width, self._ctx.height
        if i420 is not None and i420.shape == (ph * 3 // 2, pw):
            frame = self._wrap(i420)
        elif rgba is not None:
            frame = self._convert(rgba)
        else:
            raise ValueError(f"no RGBA image and no planes of {pw}x{ph} to encode")
        if pts_ms is None:
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = now
            pts_ms = round((now - self._t0) * 1000)
        pts = max(self._last_pts + 1, pts_ms)
        self._last_pts = pts
        frame.pts = pts
        frame.time_base = TIME_BASE
        first = self.frames == 0
        if key or first:
            frame.pict_type = av.video.frame.PictureType.I
        packets = self._ctx.encode(frame)
        self.frames += 1
        if not packets:
            raise RuntimeError(f"{self.encoder} held a frame back (not a zero-latency setup)")
        data = b"".join(bytes(pk) for pk in packets)
        is_key = any(pk.is_keyframe for pk in packets)
        if (key or first) and not is_key:
            raise RuntimeError(f"{self.encoder} did not make the keyframe it was asked for")
        return EncodedFrame(data, is_key, (time.perf_counter() - t0) * 1000.0)

    def _wrap(self, i420: npt.NDArray[np.uint8]) -> Any:
        """A frame of (h * 3 / 2, w) I420 planes: wrapped without a copy where PyAV can (a
        height that is a multiple of 4), else copied plane by plane into a frame's rows."""
        pw, ph = self._ctx.width, self._ctx.height
        if ph % 4 == 0:
            return self._av.VideoFrame.from_numpy_buffer(i420, format="yuv420p")
        frame = self._av.VideoFrame(pw, ph, "yuv420p")
        flat = i420.reshape(-1)
        at = 0
        for plane in frame.planes:
            w, h = plane.width, plane.height
            rows = np.frombuffer(memoryview(plane), np.uint8).reshape(h, plane.line_size)
            rows[:, :w] = flat[at : at + w * h].reshape(h, w)
            at += w * h
        return frame

    def _convert(self, rgba: npt.NDArray[np.uint8]) -> Any:
        """RGBA to the encoder's I420 at its size with swscale (`server.render.yuv` does it on
        a CUDA device: BT.709 limited range, bilinear scaling). An image of the stream's own
        size has its odd sides padded by repeating the edge; a smaller one is scaled to the
        padded size."""
        h, w = rgba.shape[:2]
        pw, ph = self._ctx.width, self._ctx.height
        if (w, h) == (self.width, self.height) and (pw, ph) != (w, h):
            rgba = np.pad(rgba, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")
        # wraps the pixels without a copy (from_ndarray copies row by row: 2-8 ms at 1080p)
        frame = self._av.VideoFrame.from_numpy_buffer(np.ascontiguousarray(rgba), format="rgba")
        return frame.reformat(
            width=pw,
            height=ph,
            format="yuv420p",
            dst_colorspace="ITU709",
            interpolation="BILINEAR",
            threads=self.threads,
        )

    def close(self) -> None:
        """End the stream (an end-of-stream to the encoder, which some, SVT-AV1 among them,
        expect before they are freed) and drop the encoder."""
        ctx, self._ctx = self._ctx, None
        if ctx is not None:
            with contextlib.suppress(Exception):  # a failed encoder may refuse the flush too
                ctx.encode(None)


def _probe(codec: str, encoder: str) -> str | None:
    """None when `encoder` opens and encodes a keyframe and a delta frame, else why not."""
    try:
        enc = VideoEncoder(codec, encoder, 320, 240, 500.0)
        img = np.zeros((240, 320, 4), np.uint8)
        enc.encode(img, key=True)
        img[..., 0] = 200
        enc.encode(img)
        enc.close()
    except Exception as exc:
        strerror = getattr(exc, "strerror", None)
        if isinstance(strerror, str) and strerror:  # FFmpeg's words, not its options dict
            return f"{type(exc).__name__}: {strerror} (opening {encoder})"
        return f"{type(exc).__name__}: {exc}".splitlines()[0][:120]
    return None


class VideoEncoders:
    """Which encoder serves each codec on this server, found by probing once (lazily), and how
    many streams may have one open at once.

    An encoder holds its own frames and look-ups: after two frames, about 12 MB (libx264) to
    17 MB (SVT-AV1) at 640x480, 48 MB (libx264), 67 MB (SVT-AV1) and 160 MB (libvpx-vp9) at
    1920x1080. Every viewer with a camera of its own would otherwise open one (80 such
    viewers took 1.2 GB), so at most `max_streams` are open in the whole server; a viewer
    beyond them gets JPEG images until one closes."""

    def __init__(self, codecs: tuple[str, ...], max_streams: int = 16) -> None:
        unknown = [c for c in codecs if c not in CANDIDATES]
        if unknown:
            raise ValueError(f"unknown video codec(s) {unknown}; known: {', '.join(CANDIDATES)}")
        self.preference = codecs
        self.max_streams = max_streams
        self.open_streams = 0
        """Streams holding a slot now (each has at most one encoder open)."""
        self._chosen: dict[str, str] | None = None
        self._why: dict[str, str] = {}
        self._lock = threading.Lock()

    def take_slot(self) -> bool:
        """A slot for one more stream; False when `max_streams` are open."""
        with self._lock:
            if self.open_streams >= self.max_streams:
                return False
            self.open_streams += 1
            return True

    def give_slot(self) -> None:
        with self._lock:
            self.open_streams -= 1

    def chosen(self) -> dict[str, str]:
        """codec -> encoder, for the codecs that have a working encoder here."""
        with self._lock:
            if self._chosen is None:
                self._chosen = self._select()
            return self._chosen

    def _select(self) -> dict[str, str]:
        # SVT-AV1 prints its whole configuration for every encoder it opens, unless told not to
        os.environ.setdefault("SVT_LOG", "1")
        try:
            import av  # noqa: F401
        except ImportError:
            log.warning("PyAV is not installed: no video streaming, JPEG images only")
            self._why = {c: "PyAV is not installed" for c in self.preference}
            return {}
        out: dict[str, str] = {}
        tried: dict[str, str | None] = {}
        for codec in self.preference:
            for encoder in CANDIDATES[codec]:
                if encoder not in tried:
                    tried[encoder] = _probe(codec, encoder)
                why = tried[encoder]
                if why is None:
                    out[codec] = encoder
                    break
                self._why[f"{codec}/{encoder}"] = why
                log.info("video encoder %s unavailable for %s (%s)", encoder, codec, why)
        for codec in self.preference:
            if codec in out:
                log.info("video %s: %s", codec, out[codec])
            else:
                log.warning("no encoder for video codec %s: viewers get another codec", codec)
        return out

    def pick(self, wanted: Sequence[str]) -> str | None:
        """The best codec both sides have (server preference first); None: JPEG."""
        if not wanted:
            return None
        chosen = self.chosen()
        for codec in self.preference:
            if codec in wanted and codec in chosen:
                return codec
        return None

    def describe(self) -> dict[str, Any]:
        chosen = self.chosen()
        out: dict[str, Any] = {
            "encoders": dict(chosen),
            "unavailable": dict(self._why),
            "streams": {"open": self.open_streams, "max": self.max_streams},
        }
        if not self.preference:  # no encoder and nothing unavailable: say why
            out["off"] = "no video codec is configured (--video-codecs): viewers get JPEG images"
        return out
