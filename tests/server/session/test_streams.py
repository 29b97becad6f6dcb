"""Who shares which video stream: same view, codec and bit-rate rung share one encoder; a
joiner gets a keyframe; a slower link gets a stream of its own."""

from __future__ import annotations

import protocol as p
from server.pipeline.video import VideoEncoders
from server.session.clients import Client
from server.session.streams import VideoStreams
from tests.server.session.fakes import client

ENCODERS = VideoEncoders(("h264",))


def viewer(
    cid: str, size: tuple[int, int] = (640, 480), video: tuple[p.VideoCodec, ...] = ("h264",)
) -> Client:
    c = client(cid, "viewer")
    c.view = p.View(width=size[0], height=size[1], video=list(video))
    return c


def test_viewers_of_one_view_share_a_stream_and_a_joiner_forces_a_keyframe() -> None:
    streams = VideoStreams(ENCODERS, 4500.0, 350.0)
    a, b = viewer("a"), viewer("b")
    cam = p.Camera().model_dump_json()
    sa = streams.stream_for(a, "h264", cam, 0.0)
    assert a.awaiting_key
    a.awaiting_key = False  # its first keyframe went out
    sb = streams.stream_for(b, "h264", cam, 0.1)
    assert sb is sa and sa.members == {"a", "b"}
    assert b.video_stream == sa.stream_id and b.awaiting_key  # the next frame it takes: a key
    assert streams.stream_for(a, "h264", cam, 0.2) is sa and not a.awaiting_key  # no rejoin


def test_own_camera_own_size_or_slower_link_means_own_stream() -> None:
    streams = VideoStreams(ENCODERS, 4500.0, 350.0)
    cam = p.Camera().model_dump_json()
    other_cam = p.Camera(distance=80.0).model_dump_json()
    a, b, c, d = viewer("a"), viewer("b"), viewer("c", (800, 600)), viewer("d")
    d.link.target_kbps = 400
    sa = streams.stream_for(a, "h264", cam, 0)
    assert streams.stream_for(b, "h264", other_cam, 0) is not sa
    assert streams.stream_for(c, "h264", cam, 0) is not sa
    sd = streams.stream_for(d, "h264", cam, 0)
    assert sd is not sa and streams.kbps(sd) == 350
    assert len(streams) == 4
    # d's link recovers: it moves to the shared stream, and leaves its own
    d.link.target_kbps = 10_000
    assert streams.stream_for(d, "h264", cam, 1) is sa and "d" not in sd.members
    streams.reap(2.0)
    assert len(streams) == 3


def test_a_stream_follows_its_viewers_to_a_new_camera_unless_one_stays_behind() -> None:
    streams = VideoStreams(ENCODERS, 4500.0, 350.0)
    cams = [p.Camera(distance=50.0 + i).model_dump_json() for i in range(4)]
    a, b = viewer("a"), viewer("b")
    s = streams.stream_for(a, "h264", cams[0], 0, frozenset({"a"}))
    a.awaiting_key = False
    # a turns its own camera: the same stream (no keyframe), now under the new camera
    assert streams.stream_for(a, "h264", cams[1], 0.1, frozenset({"a"})) is s
    assert not a.awaiting_key and s.key[0] == cams[1] and len(streams) == 1
    # b joins that view: the stream is shared
    assert streams.stream_for(b, "h264", cams[1], 0.2, frozenset({"a", "b"})) is s
    a.awaiting_key = b.awaiting_key = False
    # both move to a new camera together (one render group): still the one stream
    for cid in ("a", "b"):
        c = a if cid == "a" else b
        assert streams.stream_for(c, "h264", cams[2], 0.3, frozenset({"a", "b"})) is s
    assert not a.awaiting_key and not b.awaiting_key
    # a turns away alone: b stays on the stream, a starts its own at a keyframe
    own = streams.stream_for(a, "h264", cams[3], 0.4, frozenset({"a"}))
    assert own is not s and a.awaiting_key and s.members == {"b"} and s.key[0] == cams[2]
    # a size change is a new stream even for a lone viewer (the encoder needs a keyframe)
    a.awaiting_key = False
    a.view = p.View(width=800, height=600, video=["h264"])
    assert streams.stream_for(a, "h264", cams[3], 0.5, frozenset({"a"})) is not own
    assert a.awaiting_key


def test_the_rate_is_what_the_canvas_needs_when_the_link_allows() -> None:
    streams = VideoStreams(ENCODERS, 4500.0, 350.0)
    full_hd = viewer("a", (1920, 1080))
    s = streams.stream_for(full_hd, "h264", "{}", 0)
    assert abs(streams.kbps(s) - 4500 * 1920 * 1080 / 1e6) < 1e-6
    tiny = viewer("b", (64, 48))
    assert streams.kbps(streams.stream_for(tiny, "h264", "{}", 0)) == 350
    assert streams.codec_for(viewer("c", video=())) is None
    jpeg_only = viewer("d")
    jpeg_only.force_jpeg = True
    assert streams.codec_for(jpeg_only) is None


def test_a_smaller_frame_of_a_stream_takes_only_the_rate_its_size_needs() -> None:
    streams = VideoStreams(ENCODERS, 4500.0, 350.0)
    s = streams.stream_for(viewer("a", (1920, 1080)), "h264", "{}", 0)
    full = streams.kbps(s, (1920, 1080))
    assert full == streams.kbps(s)
    steering = streams.kbps(s, (960, 540))  # the steering size: a quarter of the pixels
    assert abs(steering - full / 4) < 1e-6
    slow = viewer("b", (1920, 1080))
    slow.link.target_kbps = 900.0  # a slow link's rung is below even that
    s_slow = streams.stream_for(slow, "h264", "{}", 0)
    assert streams.kbps(s_slow, (960, 540)) == streams.kbps(s_slow) < steering


def test_streams_are_capped_per_session_and_per_server_and_close_with_their_last_viewer() -> None:
    encoders = VideoEncoders(("h264",), max_streams=3)
    one = VideoStreams(encoders, 4500.0, 350.0, max_streams=2)
    other = VideoStreams(encoders, 4500.0, 350.0, max_streams=2)
    cams = [p.Camera(distance=50.0 + i).model_dump_json() for i in range(5)]
    a, b, c, d, e = (viewer(x) for x in "abcde")
    assert one.stream_for(a, "h264", cams[0], 0) is not None
    assert one.stream_for(b, "h264", cams[1], 0) is not None
    assert one.stream_for(c, "h264", cams[2], 0) is None  # the session's two are taken
    assert "max_video_streams_per_session" in one.refusal()
    assert other.stream_for(d, "h264", cams[3], 0) is not None
    assert other.stream_for(e, "h264", cams[4], 0) is None  # the server's three are taken
    assert "max_video_streams" in other.refusal() and encoders.open_streams == 3
    # a refused viewer is a JPEG viewer until a slot frees
    c.video_refused = e.video_refused = True
    assert one.codec_for(c) is None and other.codec_for(e) is None
    assert one.leave("a") == 1 and encoders.open_streams == 2  # closed with its last viewer
    assert one.codec_for(c) == "h264"
    assert one.stream_for(c, "h264", cams[2], 1) is not None and encoders.open_streams == 3
    assert one.close() == 2 and other.close() == 1 and encoders.open_streams == 0
