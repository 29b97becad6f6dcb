"""JPEG encoded where the image was rendered: the RGB image packed on the device, the render lane
encoding it with the queue's device encoder (only the JPEG comes back), and the fall-back to
the host's encoder when that encoder fails or serves another device."""

from __future__ import annotations

import io
import logging
from collections.abc import Callable

import numpy as np
import pytest
from PIL import Image

from protocol import Camera, RenderParams, Topology
from server.pipeline.encoder import DeviceJpeg, ImageEncoder, NvJpeg, cuda_device_count
from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
from server.render.rgb import DeviceImage
from tests.render.helpers import render

COMMENT = b"encoded on the render device"


class LaneEncoder:
    """Stands in for nvJPEG on any device: reads the packed image back and writes it with
    Pillow, marked with a JPEG comment so that a test can tell its images apart."""

    name = "lane-encoder"

    def __init__(self, device: str, fail: bool = False) -> None:
        self.device = device
        self.fail = fail
        self.calls = 0

    def encode_on_device(self, image: DeviceImage, quality: int) -> bytes:
        self.calls += 1
        if self.fail:
            raise RuntimeError("encoder lost")
        out = io.BytesIO()
        Image.fromarray(image.numpy()).save(out, format="JPEG", quality=quality, comment=COMMENT)
        return out.getvalue()


def decode(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.float32)


@pytest.fixture
def scene(
    molecule: Callable[..., tuple[Topology, np.ndarray]],
) -> tuple[Topology, np.ndarray, Camera]:
    topology, positions = molecule(60, seed=3)
    return topology, positions, Camera(target=tuple(positions.mean(axis=0)), distance=30.0)


def request(
    scene: tuple[Topology, np.ndarray, Camera], quality: int | None = 85, **kw: object
) -> RenderRequest:
    topology, positions, camera = scene
    snap = Snapshot(topology, positions)
    return RenderRequest("session:a", snap, RenderParams(sigma_A=1.2), camera, 72, 40,
                         jpeg_quality=quality, **kw)  # type: ignore[arg-type]  # fmt: skip


def test_the_packed_image_is_the_rgb_of_the_rendered_one(
    device: str, scene: tuple[Topology, np.ndarray, Camera]
) -> None:
    topology, positions, camera = scene
    r = render(device, topology, positions, RenderParams(sigma_A=1.2), camera, 72, 40)
    rgba = r.read_rgba()
    assert rgba[..., :3].std() > 20  # a molecule on its background
    image = r.device_rgb()
    assert image.shape == (40, 72, 3)
    assert np.array_equal(image.numpy(), rgba[..., :3])
    r.render(RenderParams(sigma_A=1.2), camera, 30, 20)  # a smaller image reuses the buffer
    assert np.array_equal(r.device_rgb().numpy(), r.read_rgba()[..., :3])


def test_a_lane_with_an_encoder_for_its_device_sends_the_jpeg_alone(
    device: str, scene: tuple[Topology, np.ndarray, Camera]
) -> None:
    queue = GpuQueue(device=device)
    queue.jpeg = encoder = LaneEncoder(queue.actual_device or device)
    try:
        plain = queue.render_sync(request(scene, quality=None))
        assert plain.jpeg is None and plain.rgba is not None and encoder.calls == 0
        out = queue.render_sync(request(scene, quality=90))
        assert encoder.calls == 1
        assert out.rgba is None  # the JPEG came back instead of the pixels
        assert out.jpeg is not None and COMMENT in out.jpeg and out.jpeg_ms > 0
        same = io.BytesIO()  # what the stand-in makes of the pixels read back
        Image.fromarray(plain.image()[..., :3]).save(same, "JPEG", quality=90, comment=COMMENT)
        assert out.jpeg == same.getvalue()
        # a video stream without the device's planes still needs the pixels
        video = queue.render_sync(request(scene, video_size=(72, 40)))
        assert video.jpeg is not None
        assert (video.rgba is None) == (video.i420 is not None)
    finally:
        queue.close()


def test_an_encoder_for_another_device_is_left_alone(
    scene: tuple[Topology, np.ndarray, Camera],
) -> None:
    queue = GpuQueue(device="cpu")
    queue.jpeg = encoder = LaneEncoder("cuda:7")
    try:
        out = queue.render_sync(request(scene))
        assert encoder.calls == 0 and out.jpeg is None and out.rgba is not None
    finally:
        queue.close()


def test_a_failing_lane_encoder_is_dropped_and_the_pixels_come_back(
    scene: tuple[Topology, np.ndarray, Camera], caplog: pytest.LogCaptureFixture
) -> None:
    queue = GpuQueue(device="cpu")
    queue.jpeg = encoder = LaneEncoder("cpu", fail=True)
    try:
        with caplog.at_level(logging.WARNING, logger="scalesteer.gpu"):
            first = queue.render_sync(request(scene))
            second = queue.render_sync(request(scene))
        assert first.jpeg is None and first.rgba is not None and second.rgba is not None
        assert encoder.calls == 1 and queue.jpeg is None
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "encoder lost" in warnings[0]
    finally:
        queue.close()


class BothWays(LaneEncoder):
    """An encoder of host images that also reads device images, as `NvJpeg` does."""

    def encode(self, rgba: np.ndarray, quality: int) -> bytes:
        return b"host"


class HostOnly:
    name = "host-only"

    def encode(self, rgba: np.ndarray, quality: int) -> bytes:
        return b"host"


def test_only_an_encoder_that_reads_device_images_is_lent_to_the_lanes() -> None:
    assert ImageEncoder().on_device() is None  # Pillow
    assert ImageEncoder(HostOnly()).on_device() is None
    both = BothWays("cuda:0")
    assert ImageEncoder(both).on_device() is both
    assert isinstance(both, DeviceJpeg)
    assert all(hasattr(NvJpeg, m) for m in ("encode", "encode_on_device"))


def _nvjpeg_missing() -> str | None:
    try:
        import nvidia.nvimgcodec  # noqa: F401
    except ImportError:
        return "nvImageCodec is not installed (pip install 'scalesteer[gpu-jpeg]')"
    if cuda_device_count() == 0:
        return "no CUDA device"
    return None


@pytest.mark.gpu
@pytest.mark.skipif(_nvjpeg_missing() is not None, reason=str(_nvjpeg_missing()))
def test_nvjpeg_encodes_the_image_where_it_was_rendered(
    scene: tuple[Topology, np.ndarray, Camera],
) -> None:
    queue = GpuQueue(device="cuda:0")
    queue.jpeg = nvjpeg = NvJpeg(0)
    try:
        plain = queue.render_sync(request(scene, quality=None)).image()
        for quality in (60, 85, 95):
            out = queue.render_sync(request(scene, quality=quality))
            assert queue.jpeg is not None, "nvJPEG failed on the device"
            assert out.jpeg is not None and out.jpeg[:2] == b"\xff\xd8" and out.rgba is None
            # the same picture nvJPEG makes of the pixels read back
            assert np.array_equal(decode(out.jpeg), decode(nvjpeg.encode(plain, quality)))
        assert np.abs(decode(out.jpeg) - plain[..., :3]).mean() < 3.0  # at quality 95
    finally:
        queue.close()


@pytest.mark.gpu
@pytest.mark.skipif(_nvjpeg_missing() is not None, reason=str(_nvjpeg_missing()))
def test_a_host_image_encodes_while_a_lane_captures_a_graph() -> None:
    """nvJPEG on the legacy default stream failed while a render lane captured a CUDA graph
    on the same device (error 906), and broke the capture: the renderer then launched its
    kernels one by one for good."""
    import threading

    import warp as wp

    from server.render.rgb import rgb_kernel

    nvjpeg = NvJpeg(0)
    rgba = wp.zeros(64 * 48, dtype=wp.uint32, device="cuda:0")
    rgb = wp.zeros(3 * 64 * 48, dtype=wp.uint8, device="cuda:0")
    wp.launch(rgb_kernel, dim=64 * 48, inputs=[rgba], outputs=[rgb], device="cuda:0")
    capturing, encoded = threading.Event(), threading.Event()
    graphs: list[object] = []

    def capture() -> None:
        with wp.ScopedCapture(device="cuda:0", force_module_load=False) as cap:
            wp.launch(rgb_kernel, dim=64 * 48, inputs=[rgba], outputs=[rgb], device="cuda:0")
            capturing.set()
            encoded.wait(30)
        graphs.append(cap.graph)

    lane = threading.Thread(target=capture)
    lane.start()
    try:
        assert capturing.wait(30)
        picture = np.zeros((48, 64, 4), np.uint8)
        picture[..., 0] = np.arange(64, dtype=np.uint8)[None, :] * 4
        data = nvjpeg.encode(picture, 90)
    finally:
        encoded.set()
        lane.join(30)
    assert np.abs(decode(data) - picture[..., :3]).mean() < 3.0
    (graph,) = graphs
    wp.capture_launch(graph)  # the capture survived
    wp.synchronize_device("cuda:0")
