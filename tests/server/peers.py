"""Real WebSocket peers for server tests: a scripted simulation and viewers."""

from __future__ import annotations

import time
from collections import deque
from typing import Any, TypeVar

import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

import protocol as p

M = TypeVar("M", bound=p.Message)


class Peer:
    """A blocking protocol client; `expect` skips messages until one of the wanted type."""

    def __init__(
        self,
        url: str,
        role: p.Role,
        token: str | None,
        session: str = "default",
        *,
        origin: str | None = None,
        max_queue: int | None = 64,
        hello: bool = True,
        instance: str | None = None,
        takeover: bool = False,
        headers: dict[str, str] | None = None,
    ) -> None:
        headers = {**({"Origin": origin} if origin else {}), **(headers or {})} or None
        # entered as a context manager (the supported form); `close()` closes it
        self.ws: ClientConnection = connect(
            url,
            additional_headers=headers,
            max_size=None,
            max_queue=max_queue,
            open_timeout=20,
            compression=None,
        ).__enter__()
        self.seq = 0
        self.fragment = True
        self.welcome: p.Welcome | None = None
        if hello:
            self.send(
                p.Hello(
                    role=role,
                    token=token,
                    client=f"test-{role}",
                    session=session,
                    instance=instance,
                    takeover=takeover,
                )
            )
            self.welcome = self.expect(p.Welcome, timeout=20)

    def send(self, message: p.Message) -> int:
        self.seq += 1
        self.ws.send(p.encode(message.model_copy(update={"seq": self.seq})))
        return self.seq

    def send_raw(self, raw: bytes) -> None:
        """Send encoded bytes, a large message in fragments as the simulation adapters send it
        (`fragment = False`: in one piece)."""
        self.ws.send(p.fragments(raw) if self.fragment else raw)

    def recv(self, timeout: float = 20.0) -> p.Message:
        return p.decode(self.ws.recv(timeout=timeout), p.Limits(max_message_bytes=1 << 30))

    def expect(self, kind: type[M], timeout: float = 30.0, where: Any = None) -> M:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no {kind.__name__} within {timeout} s")
            msg = self.recv(left)
            if isinstance(msg, kind) and (where is None or where(msg)):
                return msg

    def drain(self, seconds: float) -> list[p.Message]:
        out: list[p.Message] = []
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                out.append(self.recv(left))
            except (TimeoutError, ConnectionClosed):
                break
        return out

    def close(self) -> None:
        self.ws.close()


def molecule(n: int = 24, seed: int = 0) -> tuple[p.Topology, np.ndarray]:
    """A small helix-like chain of carbon/nitrogen/oxygen atoms, ~1.5 A apart."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.6
    pos = np.stack([4.0 * np.cos(t), 4.0 * np.sin(t), 1.2 * t], axis=1) + rng.normal(
        0, 0.05, (n, 3)
    )
    elements = [("C", "N", "O")[i % 3] for i in range(n)]
    bonds = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    topo = p.Topology(
        n_atoms=n,
        elements=elements,
        names=[f"{e}{i}" for i, e in enumerate(elements)],
        residue_ids=p.WireArray.from_numpy(np.arange(n) // 3 + 1, "<i4"),
        residue_names=["ALA"] * n,
        chain_ids=["A"] * n,
        bonds=p.WireArray.from_numpy(bonds, "<i4"),
        title="test helix",
    )
    return topo, pos.astype(np.float32)


def frame(positions: np.ndarray, step: int, **observables: float) -> p.Frame:
    return p.Frame(
        step=step,
        time_ps=step * 0.002,
        positions=p.WireArray.from_numpy(positions, "<f4"),
        observables=observables,
    )


class VideoViewer:
    """A viewer that decodes what it is sent, as the browser does: video frames with FFmpeg's
    decoders (one decoder per stream, started at its keyframe) and acknowledged once decoded,
    JPEG stills with Pillow. `frames` keeps the last 64 (image message, RGB pixels)."""

    def __init__(
        self,
        url: str,
        token: str | None,
        role: p.Role = "viewer",
        session: str = "default",
        *,
        video: tuple[str, ...] = ("h264",),
        size: tuple[int, int] = (320, 240),
        camera: p.Camera | None = None,
        ack: bool = True,
    ) -> None:
        self.peer = Peer(url, role, token, session)
        self.ack = ack
        self.frames: deque[tuple[p.Image, np.ndarray]] = deque(maxlen=64)
        self._decoder: Any = None
        self._stream: int | None = None
        self.view(size, video, camera)

    def view(
        self,
        size: tuple[int, int],
        video: tuple[str, ...] = ("h264",),
        camera: p.Camera | None = None,
        interacting: bool = False,
    ) -> None:
        self.peer.send(
            p.View(
                width=size[0],
                height=size[1],
                video=list(video),
                camera=camera,
                interacting=interacting,
            )
        )

    def _decode(self, msg: p.Image) -> np.ndarray:
        import io

        import av
        from PIL import Image as PILImage

        if msg.format in ("jpeg", "png"):
            return np.asarray(PILImage.open(io.BytesIO(msg.data)).convert("RGB"))
        if msg.stream != self._stream:
            assert msg.key, "a new stream must start at a keyframe"
            name = {"h264": "h264", "vp9": "vp9", "av1": "libdav1d"}[msg.format]
            self._decoder = av.CodecContext.create(name, "r")
            self._stream = msg.stream
        out = [
            f.reformat(format="rgb24", src_colorspace="ITU709").to_ndarray()
            for f in self._decoder.decode(av.Packet(msg.data))
        ]
        assert len(out) == 1, "one frame in, one frame out"
        return out[0][: msg.height, : msg.width]

    def next(self, timeout: float = 30.0, where: Any = None) -> tuple[p.Image, np.ndarray]:
        """The next image (decoded), skipping other messages and images `where` refuses."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no image within {timeout} s")
            msg = self.peer.recv(left)
            if not isinstance(msg, p.Image):
                continue
            pixels = self._decode(msg)
            self.frames.append((msg, pixels))
            if self.ack and msg.format not in ("jpeg", "png"):
                self.peer.send(p.FrameAck(frame_id=msg.frame_id))
            if where is None or where(msg):
                return msg, pixels

    def close(self) -> None:
        self.peer.close()
