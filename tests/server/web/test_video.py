"""Video streaming end to end: a real server, a scripted simulation, viewers that decode H.264
(and VP9) with FFmpeg's decoders the way the browser does with WebCodecs, and acknowledge."""

from __future__ import annotations

import io
import itertools
import time
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

import protocol as p
from tests.conftest import LiveServer, make_settings, start_server
from tests.render.test_device_jpeg import COMMENT, LaneEncoder
from tests.server.peers import Peer, VideoViewer, frame
from tests.server.web.test_streaming import LockStep, StalledTransport, start_sim


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def video_frame(
    v: VideoViewer, timeout: float = 30.0, **want: object
) -> tuple[p.Image, np.ndarray]:
    return v.next(
        timeout,
        where=lambda m: m.format != "jpeg" and all(getattr(m, k) == x for k, x in want.items()),
    )


def seen(msg: p.Image, pixels: np.ndarray) -> tuple[object, ...]:
    """A decoded video frame as its stream, whether it is a key, its size and the decoded
    picture's shape."""
    return msg.stream, msg.key, msg.width, msg.height, pixels.shape


def test_viewer_that_decodes_h264_gets_a_video_stream_that_follows_the_simulation(
    live_server: LiveServer,
) -> None:
    sim, pos = start_sim(live_server)
    v = VideoViewer(live_server.view_url, live_server.viewer_token)
    first, a = video_frame(v, width=320)
    assert first.format == "h264" and first.key and first.codec == "avc1.640033"
    assert first.encoder == "libx264"  # this machine has no NVENC: the fallback is automatic
    assert (first.width, first.height) == (320, 240) and a.shape == (240, 320, 3)
    assert first.bitrate_kbps and first.bitrate_kbps > 0
    shown = [a]
    for step in range(1, 6):
        sim.send(frame(pos + np.float32(0.8 * step), step))
        msg, pixels = video_frame(v, step=step)
        assert msg.stream == first.stream and not msg.key  # one stream, deltas after its key
        shown.append(pixels)
    # the picture moves with the molecule: each decoded frame differs from the one before
    for before, after in itertools.pairwise(shown):
        assert np.abs(before.astype(int) - after.astype(int)).mean() > 0.5
    sim.close()
    v.close()


def test_resting_view_ends_with_a_near_lossless_still(live_server: LiveServer) -> None:
    sim, pos = start_sim(live_server)
    v = VideoViewer(live_server.view_url, live_server.viewer_token)
    sim.send(frame(pos + np.float32(0.5), 1))
    moving, moving_px = video_frame(v, step=1)
    # nothing changes from here: the rest still follows the last video frame
    rest, rest_px = v.next(10, where=lambda m: m.format == "jpeg")
    assert rest.still and rest.step == 1 and rest.frame_id > moving.frame_id
    assert (rest.width, rest.height) == (moving.width, moving.height)
    assert psnr(rest_px, moving_px) > 25  # the same picture, sharper
    sim.close()
    v.close()


def test_a_still_its_render_lane_encoded_keeps_the_rest_quality(live_server: LiveServer) -> None:
    # the lane encodes the JPEG as it renders (as nvJPEG does on a CUDA device), before
    # delivery: it must encode a resting view's still at the rest quality, not the view's
    lane = LaneEncoder("cpu")
    live_server.app_state.gpu.jpeg = lane
    sim, pos = start_sim(live_server)
    v = VideoViewer(live_server.view_url, live_server.viewer_token)
    sim.send(frame(pos + np.float32(0.5), 1))
    video_frame(v, step=1)
    rest, _ = v.next(10, where=lambda m: m.format == "jpeg")
    assert rest.still and COMMENT in rest.data  # encoded by the render lane
    quality = live_server.settings.rest_jpeg_quality
    assert quality != p.RenderParams().jpeg_quality
    made = io.BytesIO()  # Pillow's tables at that quality (the stand-in writes with Pillow)
    Image.new("RGB", (8, 8)).save(made, format="JPEG", quality=quality)
    assert Image.open(io.BytesIO(rest.data)).quantization == Image.open(made).quantization
    sim.close()
    v.close()


def test_a_viewer_joining_mid_stream_shares_it_and_starts_at_a_keyframe(
    live_server: LiveServer,
) -> None:
    sim, pos = start_sim(live_server)
    a = VideoViewer(live_server.view_url, live_server.viewer_token)
    first, _ = video_frame(a, width=320)
    for step in range(1, 4):
        sim.send(frame(pos + np.float32(0.3 * step), step))
        video_frame(a, step=step)
    b = VideoViewer(live_server.view_url, live_server.viewer_token)
    sim.send(frame(pos + np.float32(2.0), 10))
    joined, b_px = video_frame(b, step=10)
    assert joined.key and joined.stream == first.stream  # one shared encoded stream
    seen, a_px = video_frame(a, step=10)
    assert seen.frame_id == joined.frame_id and seen.key  # the joiner's keyframe, for all
    assert np.array_equal(a_px, b_px)
    sim.send(frame(pos + np.float32(2.5), 11))
    after, _ = video_frame(b, step=11)
    assert not after.key and after.stream == first.stream
    sim.close()
    a.close()
    b.close()


def test_a_resize_mid_stream_restarts_it_at_a_keyframe_of_the_new_size(
    live_server: LiveServer,
) -> None:
    sim, pos = start_sim(live_server)
    v = VideoViewer(live_server.view_url, live_server.viewer_token)
    first, _ = video_frame(v, width=320)
    v.view((400, 300))
    sim.send(frame(pos + np.float32(1.0), 1))
    resized, px = video_frame(v, width=400)
    assert resized.key and resized.height == 300 and px.shape == (300, 400, 3)
    assert resized.stream != first.stream
    sim.close()
    v.close()


def test_a_viewer_with_its_own_camera_gets_its_own_stream(live_server: LiveServer) -> None:
    sim, _ = start_sim(live_server)
    a = VideoViewer(live_server.view_url, live_server.viewer_token)
    b = VideoViewer(
        live_server.view_url,
        live_server.viewer_token,
        camera=p.Camera(orientation=(0.0, 0.7071068, 0.0, 0.7071068)),
    )
    ma, _ = video_frame(a, width=320)
    mb, _ = video_frame(b, width=320)
    assert ma.stream != mb.stream and ma.key and mb.key
    sim.close()
    a.close()
    b.close()


def test_a_viewer_turning_its_camera_keeps_its_stream_without_keyframes(
    live_server: LiveServer,
) -> None:
    """Orbiting is the commonest interaction: each move is a delta frame of the same stream,
    not a new stream that starts at a keyframe (a keyframe per move swamps a slow link)."""
    sim, _ = start_sim(live_server)
    v = VideoViewer(live_server.view_url, live_server.viewer_token, camera=p.Camera())
    first, shown = video_frame(v, width=320)
    for turn in range(1, 5):
        angle = 0.15 * turn
        cam = p.Camera(orientation=(0.0, float(np.sin(angle)), 0.0, float(np.cos(angle))))
        v.view((320, 240), camera=cam)
        msg, px = video_frame(v)
        while msg.frame_id <= first.frame_id or np.array_equal(px, shown):
            msg, px = video_frame(v)
        assert (msg.stream, msg.key) == (first.stream, False), f"turn {turn}"
        shown = px
    sim.close()
    v.close()


def test_a_steering_viewer_gets_the_interactive_size_until_it_stops(tmp_path: Path) -> None:
    """While a viewer drags its camera its stream carries the interactive image's size, one
    keyframe on the way down, deltas through the drag's pauses, one keyframe back up once the
    drag has rested for `video_steer_hold_s`; the decoder follows both changes of size."""
    hold = 2.5
    server = start_server(make_settings(tmp_path, video_steer_hold_s=hold))
    try:
        sim, pos = start_sim(server)
        cam = p.Camera()
        v = VideoViewer(server.view_url, server.viewer_token, camera=cam)
        first, _ = video_frame(v, width=320)
        steered = time.monotonic()
        v.view((320, 240), camera=cam, interacting=True)
        down, px = video_frame(v, width=160)
        assert seen(down, px) == (first.stream, True, 160, 120, (120, 160, 3))
        for step in range(1, 3):  # the simulation moves on while the drag pauses
            sim.send(frame(pos + np.float32(0.3 * step), step))
            msg, px = video_frame(v, step=step)
            assert seen(msg, px) == (first.stream, False, 160, 120, (120, 160, 3))
        assert time.monotonic() - steered < hold, "the checks above must fall within the hold"
        time.sleep(max(0.0, steered + hold + 0.2 - time.monotonic()))
        sim.send(frame(pos + np.float32(2.0), 10))
        up, px = video_frame(v, width=320)  # the first frame back at full size: a keyframe
        assert seen(up, px) == (first.stream, True, 320, 240, (240, 320, 3))
        if up.step != 10:  # a render between the hold's end and the new frame went up first
            msg, px = video_frame(v, step=10)
            assert seen(msg, px) == (first.stream, False, 320, 240, (240, 320, 3))
        sim.close()
        v.close()
    finally:
        server.stop()


def test_jpeg_for_viewers_without_video_and_when_a_viewer_drops_it(
    live_server: LiveServer,
) -> None:
    sim, pos = start_sim(live_server)
    v = VideoViewer(live_server.view_url, live_server.viewer_token)
    video_frame(v)
    v.view((320, 240), video=())  # what the dashboard sends after a decoder error
    sim.send(frame(pos + np.float32(1.0), 1))
    msg, px = v.next(where=lambda m: m.step == 1)
    assert msg.format == "jpeg" and px.shape == (msg.height, msg.width, 3)
    # a codec the server cannot encode is the same as none
    v.view((320, 240), video=("h264-baseline",))
    sim.send(frame(pos + np.float32(1.5), 2))
    msg, _ = video_frame(v)  # the new stream's first frame: its keyframe
    assert msg.format == "h264" and msg.codec == "avc1.42E033" and msg.key
    sim.close()
    v.close()


def test_vp9_when_that_is_what_the_viewer_decodes(live_server: LiveServer) -> None:
    sim, pos = start_sim(live_server)
    v = VideoViewer(live_server.view_url, live_server.viewer_token, video=("vp9",))
    msg, _ = video_frame(v)
    assert msg.format == "vp9" and msg.codec == "vp09.00.51.08" and msg.key
    sim.send(frame(pos + np.float32(1.0), 1))
    msg, _ = video_frame(v, step=1)
    assert not msg.key
    sim.close()
    v.close()


def test_health_names_the_video_encoders(live_server: LiveServer) -> None:
    info = httpx.get(f"{live_server.url}/healthz", timeout=30).json()
    assert info["video"]["encoders"]["h264"] == "libx264"
    assert "h264/h264_nvenc" in info["video"]["unavailable"]


def test_slow_video_viewer_does_not_slow_the_steerer(live_server: LiveServer) -> None:
    """The steerer decodes and acknowledges each frame; a viewer of the same view whose socket
    takes nothing and that acknowledges nothing must not hold it back: the steerer gets every
    frame, and the stalled viewer's frames are dropped, never waited for."""
    sim, pos = start_sim(live_server)
    fast = VideoViewer(live_server.view_url, live_server.token, role="steerer", size=(160, 120))
    video_frame(fast)
    slow = Peer(live_server.view_url, "viewer", live_server.viewer_token, max_queue=1)
    slow.send(p.View(width=160, height=120, video=["h264"]))
    session = live_server.app_state.sessions.get("default")
    assert slow.welcome is not None
    deadline = time.monotonic() + 60
    while session.clients[slow.welcome.client_id].frames_sent == 0:
        assert time.monotonic() < deadline, "the second viewer never got a frame"
        time.sleep(0.05)
    stalled = session.clients[slow.welcome.client_id]
    stalled.ws = StalledTransport(stalled.ws)
    lock = LockStep(sim, pos, lambda step: video_frame(fast, 30.0, step=step))
    frames = 24
    delivered = lock.window_of(frames)
    assert delivered == frames, f"the steerer got {delivered} of {frames} frames"
    assert stalled.frames_dropped > 0
    assert len(session.clients) == 2
    sim.close()
    fast.close()
    slow.close()
