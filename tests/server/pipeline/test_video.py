"""Video encoders: selection with automatic fallback, low-latency behaviour (one frame in, one
packet out, keyframes on demand), scaling to the stream's size, and what a decoder gets back."""

from __future__ import annotations

import logging
import os

import av
import numpy as np
import pytest

from server.pipeline.video import CANDIDATES, WEBCODECS, VideoEncoder, VideoEncoders


def picture(w: int, h: int, shift: int = 0) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(xx - w / 2 - shift, yy - h / 2)
    img = np.zeros((h, w, 4), np.uint8)
    img[..., 0] = np.clip(250 - r, 0, 255)
    img[..., 1] = np.clip(180 - r / 2, 0, 255)
    img[..., 2] = 60
    img[..., 3] = 255
    return img


def decode(codec: str, packets: list[bytes]) -> list[np.ndarray]:
    name = {"h264": "h264", "h264-baseline": "h264", "vp9": "vp9", "av1": "libdav1d"}[codec]
    dec = av.CodecContext.create(name, "r")
    out = []
    for data in packets:
        for f in dec.decode(av.Packet(data)):
            out.append(f.reformat(format="rgb24", src_colorspace="ITU709").to_ndarray())
    return out


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(float) - b.astype(float)) ** 2))
    return 10 * np.log10(255**2 / max(mse, 1e-9))


def test_without_nvenc_h264_falls_back_to_libx264_and_says_why(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """This machine has no NVIDIA driver: NVENC cannot open, so libx264 serves H.264."""
    caplog.set_level(logging.INFO, "scalesteer.video")
    encoders = VideoEncoders(("h264", "vp9"))
    assert encoders.chosen() == {"h264": "libx264", "vp9": "libvpx-vp9"}
    why = encoders.describe()["unavailable"]
    assert "h264/h264_nvenc" in why
    # FFmpeg's reason, whole, not its message cut inside the options the encoder was opened with
    assert why["h264/h264_nvenc"].endswith("(opening h264_nvenc)"), why
    assert "{" not in why["h264/h264_nvenc"], why
    assert any("h264_nvenc unavailable" in r.message for r in caplog.records)


def test_a_server_without_video_codecs_says_why_it_streams_jpeg() -> None:
    """The CPU demo configures none: /healthz had shown no encoder and nothing unavailable."""
    off = VideoEncoders(()).describe()
    assert off["encoders"] == {} and "--video-codecs" in off["off"]
    assert "off" not in VideoEncoders(("h264",)).describe()


def test_the_server_preference_decides_among_what_the_viewer_decodes() -> None:
    encoders = VideoEncoders(("h264", "vp9"))
    assert encoders.pick(["vp9", "h264"]) == "h264"
    assert encoders.pick(["vp9"]) == "vp9"
    assert encoders.pick(["av1"]) is None  # not offered by this server: JPEG
    assert encoders.pick([]) is None


def test_unknown_codecs_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"unknown video codec.*'hevc'"):
        VideoEncoders(("h264", "hevc"))


@pytest.mark.parametrize("codec", ["h264", "h264-baseline", "vp9"])
def test_one_frame_in_one_packet_out_and_keyframes_on_demand(codec: str) -> None:
    encoder = CANDIDATES[codec][-1]
    enc = VideoEncoder(codec, encoder, 160, 120, 800)
    frames = [enc.encode(picture(160, 120, k)) for k in range(5)]
    forced = enc.encode(picture(160, 120, 5), key=True)
    assert [f.key for f in frames] == [True, False, False, False, False]
    assert forced.key
    decoded = decode(codec, [f.data for f in [*frames, forced]])
    assert len(decoded) == 6  # nothing held back: every frame decodes as it arrives
    for k, img in enumerate(decoded):
        assert psnr(img, picture(160, 120, k)[..., :3]) > 30
    # a decoder that starts at the forced keyframe decodes it alone
    assert len(decode(codec, [forced.data])) == 1


def test_h264_is_annex_b_with_parameter_sets_in_every_keyframe() -> None:
    enc = VideoEncoder("h264", "libx264", 64, 48, 500)
    first = enc.encode(picture(64, 48)).data
    enc.encode(picture(64, 48, 1))
    later = enc.encode(picture(64, 48, 2), key=True).data
    for data in (first, later):
        assert data.startswith(b"\x00\x00\x00\x01")
        starts = [i + 3 for i in range(len(data) - 3) if data[i : i + 3] == b"\x00\x00\x01"]
        assert {7, 8, 5} <= {data[i] & 0x1F for i in starts}  # SPS, PPS, IDR slice
    assert WEBCODECS["h264"].startswith("avc1.64")


def test_odd_sizes_and_smaller_renders_are_scaled_into_the_stream() -> None:
    enc = VideoEncoder("h264", "libx264", 161, 121, 800)
    full = enc.encode(picture(161, 121), key=True)
    small = enc.encode(picture(80, 60))  # a render shrunk by the frame budget
    out = decode("h264", [full.data, small.data])
    assert [o.shape for o in out] == [(122, 162, 3), (122, 162, 3)]  # padded to even sides
    assert psnr(out[0][:121, :161], picture(161, 121)[..., :3]) > 30
    assert psnr(out[1][:121, :161], picture(161, 121)[..., :3]) > 20  # upscaled, softer


@pytest.mark.parametrize("size", [(160, 120), (161, 121)])
def test_planes_converted_on_the_device_are_encoded_as_they_are(size: tuple[int, int]) -> None:
    from tests.render.test_yuv import swscale

    w, h = size
    enc = VideoEncoder("h264", "libx264", w, h, 2000)
    img = picture(w, h)
    moved = picture(w, h, shift=40)  # planes of another picture than the RGBA image's:
    planes = swscale(moved, size)  # the device's `read_i420` output is what is encoded
    out = decode("h264", [enc.encode(img, key=True, i420=planes).data])[0][:h, :w]
    assert psnr(out, moved[..., :3]) > 30 > psnr(out, img[..., :3])
    # planes of another size (a stale conversion) are not taken: the RGBA image is
    wrong = swscale(img, (80, 60))
    out = decode("h264", [enc.encode(img, key=True, i420=wrong).data])[0]
    assert psnr(out[:h, :w], img[..., :3]) > 30


def test_the_rate_follows_the_setting() -> None:
    rng = np.random.default_rng(0)
    sizes = {}
    for kbps in (300, 3000):
        enc = VideoEncoder("h264", "libx264", 320, 240, kbps)
        total = 0
        for k in range(60):
            img = picture(320, 240, k)
            img[..., :3] = np.clip(img[..., :3] + rng.integers(0, 40, img[..., :3].shape), 0, 255)
            total += len(enc.encode(img, pts_ms=round(k * 1000 / 60)).data)
        sizes[kbps] = total * 8 / 1000  # kbit in one second of video
    assert sizes[300] < 0.5 * sizes[3000]
    assert sizes[300] < 2 * 300  # near the rate asked for, within the VBV buffer


@pytest.mark.parametrize("codec", ["h264", "av1", "vp9"])
def test_closing_an_encoder_ends_its_stream_quietly(
    codec: str, capfd: pytest.CaptureFixture[str]
) -> None:
    """An encoder is told its stream ended before it is freed (SVT-AV1 printed an error on
    every server start, from the start-up probe, when it was not); closing twice is harmless."""
    encoder = VideoEncoders((codec,)).chosen().get(codec)
    if encoder is None:
        pytest.skip(f"no {codec} encoder here")
    capfd.readouterr()
    enc = VideoEncoder(codec, encoder, 320, 240, 500.0)  # SVT-AV1 opens no smaller stream
    enc.encode(picture(320, 240), key=True)
    enc.encode(picture(320, 240, shift=3))
    enc.close()
    enc.close()
    err = capfd.readouterr().err
    assert "error" not in err.lower(), err


def shaded_sphere(w: int, h: int) -> np.ndarray:
    """A lit sphere on a dark background: the smooth surface villin's density is at sigma 6."""
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    dx, dy = (xx - w / 2) / (0.45 * h), (yy - h / 2) / (0.45 * h)
    inside = dx * dx + dy * dy < 1
    nz = np.sqrt(np.clip(1 - dx * dx - dy * dy, 0, 1))
    light = np.array([-0.4, -0.5, 0.77]) / np.linalg.norm([-0.4, -0.5, 0.77])
    lit = np.clip(dx * light[0] + dy * light[1] + nz * light[2], 0, 1)
    rgb = (
        np.stack([0.78 * lit + 0.12, 0.72 * lit + 0.1, 0.8 * lit + 0.14], -1)
        + 0.3 * lit[..., None] ** 30
    )
    rgb = np.where(inside[..., None], rgb, [0.07, 0.08, 0.1])
    img = np.full((h, w, 4), 255, np.uint8)
    img[..., :3] = np.clip(rgb * 255, 0, 255)
    return img


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one core encodes one slice")
def test_a_smooth_picture_at_a_low_bit_rate_shows_no_seam() -> None:
    """At 350 kbit/s a 960x540 stream was cut into a slice per core, and the boundary between
    two slices showed as a seam across a smooth surface: a row whose step stood 0.9 grey
    levels above the picture's own. Such a stream is one slice now."""
    w, h = 960, 540
    img = shaded_sphere(w, h)
    enc = VideoEncoder("h264", "libx264", w, h, 350.0)
    packets = [enc.encode(img, key=i == 0, pts_ms=33 * i).data for i in range(12)]
    out = decode("h264", packets)[-1].astype(float).mean(axis=2)
    source = img[..., :3].astype(float).mean(axis=2)
    excess = np.abs(np.diff(out, axis=0)).mean(axis=1) - np.abs(np.diff(source, axis=0)).mean(1)
    boundary = ((h + 15) // 16 + 1) // 2 * 16  # where two slices of macroblock rows meet
    assert excess[boundary - 2 : boundary + 2].max() < 0.5, excess[boundary - 2 : boundary + 2]
    full = VideoEncoder("h264", "libx264", w, h, 4500.0 * w * h / 1e6)
    assert full.threads == min(8, len(os.sched_getaffinity(0)), os.cpu_count() or 1)
