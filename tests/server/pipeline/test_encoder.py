"""Image encoders: Pillow reading the pixels in place, the choice of the JPEG backend, and the
fall-back to Pillow when a GPU encoder fails at run time."""

from __future__ import annotations

import io
import logging
import sys
import types
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, ClassVar

import httpx
import numpy as np
import pytest
from PIL import Image

import protocol as p
from server.pipeline.encoder import (
    PILLOW,
    ImageEncoder,
    NvJpeg,
    cuda_device_count,
    cuda_index,
    encode_image,
    select_encoder,
)
from tests.conftest import LiveServer
from tests.render.test_device_jpeg import COMMENT, LaneEncoder, _nvjpeg_missing
from tests.server.peers import Peer, frame, molecule


def picture(h: int = 60, w: int = 80, seed: int = 0) -> np.ndarray:
    """A smooth RGBA test picture with a random alpha channel (which JPEG must ignore)."""
    y, x = np.mgrid[0:h, 0:w]
    rgba = np.empty((h, w, 4), np.uint8)
    rgba[..., 0] = x * 255 // max(1, w - 1)
    rgba[..., 1] = y * 255 // max(1, h - 1)
    rgba[..., 2] = 128
    rgba[..., 3] = np.random.default_rng(seed).integers(0, 256, (h, w))
    return rgba


def decode(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.float32)


@pytest.mark.parametrize("quality", [60, 85, 95])
def test_pillow_jpeg_is_what_pillow_writes_for_the_rgb_channels(quality: int) -> None:
    rgba = picture()
    data, _ms = encode_image(rgba, "jpeg", quality)
    reference = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba[..., :3])).save(
        reference, format="JPEG", quality=quality, subsampling=0 if quality >= 90 else 2
    )
    assert data == reference.getvalue()
    assert np.abs(decode(data) - rgba[..., :3]).mean() < 3.0


def test_pillow_png_is_lossless_and_any_memory_layout_works() -> None:
    rgba = picture(seed=1)
    flipped = rgba[::-1]  # a view with negative strides
    data, _ = encode_image(flipped, "png")
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(data))), flipped)
    jpeg, _ = encode_image(flipped, "jpeg", 90)
    assert np.abs(decode(jpeg) - flipped[..., :3]).mean() < 3.0


def test_threads_encoding_at_once_each_get_their_own_image() -> None:
    pictures = [picture(40 + k, 50 + 3 * k, seed=k) for k in range(12)]
    with ThreadPoolExecutor(4) as pool:
        outputs = list(pool.map(lambda a: encode_image(a, "png")[0], pictures))
    for rgba, data in zip(pictures, outputs, strict=True):
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(data))), rgba)


def test_refuses_what_is_not_rgba() -> None:
    with pytest.raises(ValueError, match="RGBA"):
        encode_image(np.zeros((4, 4, 3), np.uint8), "jpeg")


class FakeGpu:
    """Stands in for `NvJpeg`: built from a CUDA ordinal, optionally failing."""

    built: ClassVar[list[int]] = []

    def __init__(self, index: int, fail_at: str = "", mark: int = 7) -> None:
        if fail_at == "build":
            raise RuntimeError("no such device")
        FakeGpu.built.append(index)
        self.name = f"fake-gpu (cuda:{index})"
        self.fail_at = fail_at
        self.mark = mark
        self.calls = 0

    def encode(self, rgba: np.ndarray, quality: int) -> bytes:
        self.calls += 1
        if self.fail_at == "encode":
            raise RuntimeError("device lost")
        return bytes([self.mark]) * 4


@pytest.fixture(autouse=True)
def _fresh_fake() -> Iterator[None]:
    FakeGpu.built = []
    yield


def test_devices_name_their_cuda_ordinal() -> None:
    assert cuda_index("cpu") is None
    assert cuda_index("cuda") == 0
    assert cuda_index("cuda:2") == 2
    assert cuda_index("cuda:x") is None
    assert cuda_index("auto") == (0 if cuda_device_count() > 0 else None)


def test_a_cpu_render_device_encodes_with_pillow(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="scalesteer.encoder"):
        encoder = select_encoder("cpu", FakeGpu)
    assert encoder.describe() == PILLOW
    assert FakeGpu.built == []
    assert not caplog.records


def test_a_cuda_device_uses_the_gpu_encoder_for_jpeg_only() -> None:
    encoder = select_encoder("cuda:1", FakeGpu)
    assert FakeGpu.built == [1]
    assert encoder.describe() == "fake-gpu (cuda:1)"
    data, _ = encoder.encode(picture(), "jpeg", 80)
    assert data == b"\x07" * 4
    png, _ = encoder.encode(picture(), "png")
    assert png.startswith(b"\x89PNG")


def test_without_nvimagecodec_the_choice_is_pillow_quietly(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def missing(index: int) -> Any:
        raise ImportError("No module named 'nvidia'")

    with caplog.at_level(logging.INFO, logger="scalesteer.encoder"):
        encoder = select_encoder("cuda:0", missing)
    assert encoder.describe() == PILLOW
    assert [r.levelno for r in caplog.records] == [logging.INFO]


def test_a_gpu_encoder_that_cannot_start_is_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="scalesteer.encoder"):
        encoder = select_encoder("cuda:0", lambda index: FakeGpu(index, fail_at="build"))
    assert encoder.describe() == PILLOW
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "no such device" in warnings[0].getMessage()


def test_a_gpu_encoder_failing_at_run_time_falls_back_to_pillow_for_good(
    caplog: pytest.LogCaptureFixture,
) -> None:
    gpu = FakeGpu(0, fail_at="encode")
    encoder = ImageEncoder(gpu)
    rgba = picture()
    with caplog.at_level(logging.WARNING, logger="scalesteer.encoder"):
        first, _ = encoder.encode(rgba, "jpeg", 85)
        second, _ = encoder.encode(rgba, "jpeg", 85)
    assert first == second == encode_image(rgba, "jpeg", 85)[0]  # the frame still went out
    assert gpu.calls == 1  # dropped after the first failure
    assert encoder.describe() == PILLOW
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "device lost" in warnings[0].getMessage()


def fake_nvimgcodec(results: list[Any]) -> types.ModuleType:
    """A minimal `nvidia.nvimgcodec` whose Encoder.encode returns `results` in turn (None is
    how nvImageCodec reports an image it could not encode)."""
    nv = types.ModuleType("nvidia.nvimgcodec")
    enum = types.SimpleNamespace
    nv.BackendKind = enum(CPU_ONLY=1, GPU_ONLY=2, HYBRID_CPU_GPU=3, HW_GPU_ONLY=4)  # type: ignore[attr-defined]
    nv.ChromaSubsampling = enum(CSS_444=0, CSS_420=3)  # type: ignore[attr-defined]
    nv.QualityType = enum(QUALITY=2)  # type: ignore[attr-defined]
    nv.Backend = lambda kind: ("backend", kind)  # type: ignore[attr-defined]
    nv.EncodeParams = lambda **kw: kw  # type: ignore[attr-defined]
    seen: list[Any] = []
    nv.seen = seen  # type: ignore[attr-defined]

    class Encoder:
        def __init__(self, **kw: Any) -> None:
            seen.append(("encoder", kw))

        def encode(self, image: np.ndarray, codec: str, *, params: Any, cuda_stream: int) -> Any:
            seen.append(("encode", image.shape, image.flags.c_contiguous, codec, params))
            seen.append(("stream", cuda_stream))
            return results.pop(0)

    nv.Encoder = Encoder  # type: ignore[attr-defined]
    return nv


def test_nvjpeg_passes_rgb_and_quality_and_a_failed_encode_falls_back(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    nv = fake_nvimgcodec([b"probe", b"jpeg-bytes", None])
    package = types.ModuleType("nvidia")
    package.nvimgcodec = nv  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "nvidia", package)
    monkeypatch.setitem(sys.modules, "nvidia.nvimgcodec", nv)
    monkeypatch.setattr(NvJpeg, "_stream", lambda self: 17)  # no CUDA device here
    encoder = select_encoder("cuda:0")
    assert encoder.describe() == "nvimagecodec-nvjpeg (cuda:0)"
    rgba = picture()
    assert encoder.encode(rgba, "jpeg", 95)[0] == b"jpeg-bytes"
    assert nv.seen[-1] == ("stream", 17)  # type: ignore[attr-defined]  # never the legacy 0
    kind, shape, contiguous, codec, params = nv.seen[-2]  # type: ignore[attr-defined]
    assert (kind, shape, contiguous, codec) == ("encode", (60, 80, 3), True, "jpeg")
    assert params["quality_value"] == 95.0 and params["chroma_subsampling"] == 0
    made = nv.seen[0][1]  # type: ignore[attr-defined]
    assert made["device_id"] == 0
    # GPU backends only: nvImageCodec's own CPU codec would hide a GPU failure
    assert sorted(made["backends"]) == [("backend", 2), ("backend", 3), ("backend", 4)]
    with caplog.at_level(logging.WARNING, logger="scalesteer.encoder"):
        data, _ = encoder.encode(rgba, "jpeg", 85)  # nvImageCodec answers None
    assert data == encode_image(rgba, "jpeg", 85)[0]
    assert encoder.describe() == PILLOW
    assert any("could not encode" in r.getMessage() for r in caplog.records)


@pytest.mark.gpu
@pytest.mark.skipif(_nvjpeg_missing() is not None, reason=str(_nvjpeg_missing()))
def test_nvjpeg_on_the_gpu_encodes_what_pillow_decodes() -> None:
    gpu = NvJpeg(0)
    encoder = ImageEncoder(gpu)
    assert encoder.describe().startswith("nvimagecodec-nvjpeg")
    rgba = picture(1080, 1920)
    for quality in (60, 85, 95):
        data, _ = encoder.encode(rgba, "jpeg", quality)
        assert encoder.describe() != PILLOW, "the GPU encoder failed and fell back"
        assert data[:2] == b"\xff\xd8"
        assert np.abs(decode(data) - rgba[..., :3]).mean() < 3.0
    with ThreadPoolExecutor(4) as pool:  # one nvImageCodec encoder per thread
        outputs = list(pool.map(lambda q: encoder.encode(rgba, "jpeg", q)[0], [70] * 8))
    assert all(np.abs(decode(d) - rgba[..., :3]).mean() < 3.0 for d in outputs)
    assert encoder.describe() != PILLOW


def test_healthz_names_the_encoder(live_server: LiveServer) -> None:
    health = httpx.get(f"{live_server.url}/healthz", timeout=30).json()
    assert health["encoder"] == PILLOW and health["encoder_on_device"] is None
    live_server.app_state.gpu.jpeg = LaneEncoder("cpu")
    health = httpx.get(f"{live_server.url}/healthz", timeout=30).json()
    assert health["encoder_on_device"] == "lane-encoder"
    assert live_server.app_state.encoder.describe() == PILLOW


def test_a_session_sends_the_jpeg_its_render_lane_encoded(
    live_server: LiveServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    lane = LaneEncoder("cpu")
    live_server.app_state.gpu.jpeg = lane
    host_formats: list[str] = []
    host_encode = ImageEncoder.encode

    def counted(encoder: ImageEncoder, rgba: np.ndarray, fmt: Any, *args: Any) -> Any:
        host_formats.append(fmt)
        return host_encode(encoder, rgba, fmt, *args)

    monkeypatch.setattr(ImageEncoder, "encode", counted)
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "lane")
    topology, positions = molecule(24)
    sim.send(topology)
    sim.send(frame(positions, 0))
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "lane")
    try:
        image = viewer.expect(p.Image, 60)
        assert image.format == "jpeg" and COMMENT in image.data
        assert lane.calls >= 1 and image.encode_ms > 0
        assert "jpeg" not in host_formats  # the encode threads had nothing to do
        assert decode(image.data).shape == (image.height, image.width, 3)
    finally:
        viewer.close()
        sim.close()
