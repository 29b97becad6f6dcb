"""The device's conversion of an image to the video encoders' I420 (BT.709, limited range),
against FFmpeg's swscale, which the encoder uses when no device conversion comes with a frame."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import av
import numpy as np
import pytest
import warp as wp

from protocol import Camera, RenderParams, Topology
from server.render.yuv import I420Converter
from tests.render.helpers import render


def swscale(rgba: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """What `VideoEncoder` makes of an RGBA image on the host (odd sides padded, as there)."""
    h, w = rgba.shape[:2]
    if (w, h) == size and (w % 2 or h % 2):
        rgba = np.pad(rgba, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    pw, ph = size[0] + size[0] % 2, size[1] + size[1] % 2
    frame = av.VideoFrame.from_numpy_buffer(np.ascontiguousarray(rgba), format="rgba")
    out: np.ndarray = frame.reformat(
        width=pw, height=ph, format="yuv420p", dst_colorspace="ITU709", interpolation="BILINEAR"
    ).to_ndarray()
    return out


def to_rgb(i420: np.ndarray) -> np.ndarray:
    frame = av.VideoFrame.from_numpy_buffer(np.ascontiguousarray(i420), format="yuv420p")
    rgb: np.ndarray = frame.reformat(format="rgb24", src_colorspace="ITU709").to_ndarray()
    return rgb


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


@pytest.fixture
def drawn(
    device: str, molecule: Callable[..., tuple[Topology, np.ndarray]]
) -> Callable[[int, int], object]:
    topology, positions = molecule(60, seed=3)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    params = RenderParams(sigma_A=1.2)
    return lambda w, h: render(device, topology, positions, params, camera, w, h)


@pytest.mark.parametrize(
    ("src", "size"), [((96, 64), (96, 64)), ((48, 32), (96, 64)), ((95, 63), (95, 63))]
)
def test_i420_matches_the_host_conversion(
    drawn: Callable[[int, int], object], src: tuple[int, int], size: tuple[int, int]
) -> None:
    r = drawn(*src)
    rgba = r.read_rgba()  # type: ignore[attr-defined]
    assert rgba[..., :3].std() > 20  # a molecule on its background, not a blank picture
    ours = r.read_i420(size)  # type: ignore[attr-defined]
    theirs = swscale(rgba, size)
    pw, ph = size[0] + size[0] % 2, size[1] + size[1] % 2
    assert ours.shape == theirs.shape == (ph * 3 // 2, pw)
    luma = np.abs(ours[:ph].astype(int) - theirs[:ph].astype(int))
    chroma = np.abs(ours[ph:].astype(int) - theirs[ph:].astype(int))
    assert luma.max() <= 2 and luma.mean() < 0.5  # one rounding apart
    assert chroma.mean() < 1.5  # swscale's chroma filter and rounding differ, not the colour
    # as faithful as swscale to the picture at the stream's size (drawn at that size)
    truth = drawn(size[0], size[1]).read_rgba()[..., :3]  # type: ignore[attr-defined]
    ours_db = psnr(to_rgb(ours)[: size[1], : size[0]], truth)
    theirs_db = psnr(to_rgb(theirs)[: size[1], : size[0]], truth)
    assert ours_db > theirs_db - 0.5, (ours_db, theirs_db)


def test_odd_sides_repeat_the_last_column_and_row(drawn: Callable[[int, int], object]) -> None:
    r = drawn(31, 21)
    y = r.read_i420((31, 21))[:22]  # type: ignore[attr-defined]
    assert np.array_equal(y[:, 31], y[:, 30]) and np.array_equal(y[21], y[20])


def test_the_colour_matrix_is_bt709_limited_range(device: str) -> None:
    # pure white, black, red, green, blue, in 2x2 blocks
    colors = [(255, 255, 255), (0, 0, 0), (255, 0, 0), (0, 255, 0), (0, 0, 255)]
    rgba = np.zeros((2, 10, 4), np.uint8)
    for k, c in enumerate(colors):
        rgba[:, 2 * k : 2 * k + 2, :3] = c
    packed = wp.array(rgba.view(np.uint32).reshape(-1), dtype=wp.uint32, device=device)
    out = I420Converter(device).convert(packed, (10, 2), (10, 2))
    y, u, v = out[:2].reshape(2, 10)[0, ::2], out[2:].reshape(-1)[:5], out[2:].reshape(-1)[5:]
    # BT.709 limited range: Y = 16 + 219 Y', Cb/Cr = 128 + 224 (B-Y')/1.8556, (R-Y')/1.5748
    assert y.tolist() == [235, 16, 63, 173, 32]
    assert u.tolist() == [128, 128, 102, 42, 240]
    assert v.tolist() == [128, 128, 240, 26, 118]


def test_renders_for_video_come_back_converted_on_cuda_only(
    device: str, molecule: Callable[..., tuple[Topology, np.ndarray]]
) -> None:
    from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot

    topology, positions = molecule(60, seed=3)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    queue = GpuQueue(device=device)
    try:
        snap = Snapshot(topology, positions)
        request = RenderRequest("t", snap, RenderParams(sigma_A=1.2), camera, 48, 32)
        assert queue.render_sync(request).i420 is None  # no video viewer: none asked for
        out = queue.render_sync(replace(request, video_size=(96, 64)))
        if device.startswith("cuda"):
            assert out.i420 is not None and out.i420.shape == (96, 96)
            assert psnr(to_rgb(out.i420), to_rgb(swscale(out.rgba, (96, 64)))) > 30
        else:
            assert out.i420 is None  # swscale converts faster than a kernel on the CPU device
    finally:
        queue.close()


def test_a_failed_conversion_leaves_the_frame_to_the_encoder(
    molecule: Callable[..., tuple[Topology, np.ndarray]], monkeypatch: pytest.MonkeyPatch
) -> None:
    from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
    from server.render.renderer import Renderer

    def broken(self: Renderer, size: tuple[int, int]) -> np.ndarray:
        raise RuntimeError("out of memory")

    monkeypatch.setattr(GpuQueue, "_on_cuda", lambda self: True)  # as on a GPU
    monkeypatch.setattr(Renderer, "read_i420", broken)
    topology, positions = molecule(60, seed=3)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    queue = GpuQueue(device="cpu")
    try:
        snap = Snapshot(topology, positions)
        request = RenderRequest("t", snap, RenderParams(), camera, 48, 32, video_size=(96, 64))
        out = queue.render_sync(request)
        assert out.i420 is None and out.rgba.shape == (32, 48, 4)  # swscale converts instead
    finally:
        queue.close()


def test_video_only_renders_come_back_without_the_rgba_image(
    molecule: Callable[..., tuple[Topology, np.ndarray]], monkeypatch: pytest.MonkeyPatch
) -> None:
    from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot

    topology, positions = molecule(60, seed=3)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    queue = GpuQueue(device="cpu")
    try:
        snap = Snapshot(topology, positions)
        request = RenderRequest(
            "t", snap, RenderParams(), camera, 48, 32, video_size=(96, 64), rgba=False
        )
        out = queue.render_sync(request)  # the CPU device makes no planes: RGBA comes back
        assert out.i420 is None and out.image().shape == (32, 48, 4)
        monkeypatch.setattr(GpuQueue, "_on_cuda", lambda self: True)  # as on a GPU
        out = queue.render_sync(request)
        assert out.rgba is None and out.i420 is not None and out.i420.shape == (96, 96)
        with pytest.raises(RuntimeError, match="no RGBA image"):
            out.image()
        out = queue.render_sync(replace(request, rgba=True))  # a JPEG viewer among them
        assert out.rgba is not None and out.i420 is not None
    finally:
        queue.close()
