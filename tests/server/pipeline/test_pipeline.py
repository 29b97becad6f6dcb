"""Rendering and encoding overlap: renders run on while earlier frames encode, images stay in
order per viewer, and a session closing with encodes in flight shuts down cleanly.

A stand-in encoder that sleeps (and so releases the GIL, like Pillow and nvJPEG do) makes the
encode the slow stage, so the effects show with the tiny CPU renders of a test.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import protocol as p
from server.pipeline.encoder import ImageEncoder
from tests.conftest import LiveServer, make_settings, start_server
from tests.server.peers import Peer, frame, molecule

WORKERS = 4


@pytest.fixture
def server(tmp_path: Path) -> Iterator[LiveServer]:
    live = start_server(make_settings(tmp_path, encode_workers=WORKERS))
    yield live
    live.stop()


class SlowEncodes:
    """Patches `ImageEncoder.encode` to sleep first; records how many encodes overlap."""

    def __init__(self, delay: Callable[[int], float]) -> None:
        self.delay = delay
        self.calls = 0
        self.in_flight = 0
        self.most_in_flight = 0
        self._lock = threading.Lock()
        self._encode = ImageEncoder.encode

    def install(self, monkeypatch: pytest.MonkeyPatch) -> SlowEncodes:
        def encode(encoder: ImageEncoder, *args: Any, **kwargs: Any) -> tuple[bytes, float]:
            return self._slowly(encoder, *args, **kwargs)

        monkeypatch.setattr(ImageEncoder, "encode", encode)
        return self

    def _slowly(self, encoder: ImageEncoder, *args: Any, **kwargs: Any) -> tuple[bytes, float]:
        with self._lock:
            self.calls += 1
            call = self.calls
            self.in_flight += 1
            self.most_in_flight = max(self.most_in_flight, self.in_flight)
        try:
            time.sleep(self.delay(call))
            return self._encode(encoder, *args, **kwargs)
        finally:
            with self._lock:
                self.in_flight -= 1


class Stream:
    """A simulation sending slightly moved frames every few ms until stopped."""

    def __init__(self, server: LiveServer, session: str, atoms: int = 24) -> None:
        self.sim = Peer(server.ws_url, "simulation", server.token, session)
        topo, self.pos = molecule(atoms)
        self.sim.send(topo)
        self.sim.send(frame(self.pos, 0))
        self.step = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.step += 1
            self.sim.send(frame(self.pos + np.float32(0.02 * (self.step % 9)), self.step))
            time.sleep(0.005)

    def start(self) -> Stream:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.sim.close()


def test_renders_go_on_while_frames_encode(
    server: LiveServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    encode_s = 0.25
    slow = SlowEncodes(lambda call: encode_s).install(monkeypatch)
    stream = Stream(server, "overlap")
    viewer = Peer(server.view_url, "viewer", server.viewer_token, "overlap")
    viewer.expect(p.Image, 60)
    session = server.app_state.sessions.get("overlap")
    stream.start()
    renders0, t0 = session.render_count, time.monotonic()
    images = [m for m in viewer.drain(2.5) if isinstance(m, p.Image)]
    renders, elapsed = session.render_count - renders0, time.monotonic() - t0
    stream.stop()
    # one encode at a time would allow at most elapsed / encode_s renders
    serial = elapsed / encode_s
    assert renders > 1.5 * serial, (renders, serial)
    assert 2 <= slow.most_in_flight <= WORKERS, slow.most_in_flight
    assert len(images) > serial, (len(images), serial)
    viewer.close()


def test_an_image_encoded_late_never_follows_a_newer_one(
    server: LiveServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    # every other encode is slow, so the next frame's image is ready first
    SlowEncodes(lambda call: 0.3 if call % 2 else 0.01).install(monkeypatch)
    stream = Stream(server, "order").start()
    viewers = [
        Peer(server.view_url, "viewer", server.viewer_token, "order", max_queue=None)
        for _ in range(2)
    ]
    got = [[m for m in v.drain(3.0) if isinstance(m, p.Image)] for v in viewers]
    stream.stop()
    for images in got:
        ids = [m.frame_id for m in images]
        assert len(ids) >= 3, ids
        assert ids == sorted(set(ids)), ids  # strictly increasing
        steps = [m.step for m in images]
        assert steps == sorted(steps), steps
    metrics = server.app_state.metrics
    assert metrics.frames_stale._value.get() > 0, "no encode finished out of order"
    for v in viewers:
        v.close()


def test_closing_with_encodes_in_flight_is_clean(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    slow = SlowEncodes(lambda call: 0.2).install(monkeypatch)
    live = start_server(make_settings(tmp_path, encode_workers=WORKERS))
    stream = Stream(live, "closing").start()
    viewer = Peer(live.view_url, "viewer", live.viewer_token, "closing")
    viewer.expect(p.Image, 60)
    session = live.app_state.sessions.get("closing")
    deadline = time.monotonic() + 10
    while slow.in_flight < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert slow.in_flight >= 2
    with caplog.at_level(logging.WARNING):
        stream.stop()
        viewer.close()
        live.stop()
    assert not session.delivery.in_flight(), "encode tasks outlived their session"
    assert all(t.done() for t in session._tasks)
    errors = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert not errors, [r.getMessage() for r in errors]


def test_a_render_waiting_for_an_encoder_skips_a_scene_that_went_away(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    slow = SlowEncodes(lambda call: 0.6).install(monkeypatch)
    live = start_server(make_settings(tmp_path, encode_workers=1))
    sim = Peer(live.ws_url, "simulation", live.token, "shrink")
    topo, pos = molecule(24)
    sim.send(topo)
    sim.send(frame(pos, 1))
    viewer = Peer(live.view_url, "viewer", live.viewer_token, "shrink", max_queue=None)
    deadline = time.monotonic() + 30
    while slow.in_flight < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert slow.in_flight == 1  # the only encoder is busy
    with caplog.at_level(logging.WARNING):
        sim.send(frame(pos + np.float32(1.0), 2))  # this render now waits for the encoder
        small, small_pos = molecule(12)
        sim.send(small)  # another atom count: the session drops its positions
        while slow.in_flight and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)  # the waiting render has its encoder now, and no positions
        sim.send(frame(small_pos, 3))
        image = viewer.expect(p.Image, 60, where=lambda m: m.step == 3)
        seen = viewer.drain(0.5)
    assert image.width > 0
    assert not [m for m in seen if isinstance(m, p.Error)]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    sim.close()
    viewer.close()
    live.stop()


def test_views_of_one_pass_render_the_same_frame(server: LiveServer) -> None:
    """Viewers with cameras of their own, frames arriving faster than renders: each pass
    renders every view from one frame (one upload and grid), so the viewers see the same
    steps instead of each catching a different newer frame."""
    stream = Stream(server, "turns")
    viewers = [
        Peer(server.view_url, "viewer", server.viewer_token, "turns", max_queue=None)
        for _ in range(3)
    ]
    base = viewers[0].expect(p.State, 30, where=lambda m: m.camera is not None).camera
    assert base is not None
    for k, v in enumerate(viewers):
        q = (float(np.cos(0.3 * (k + 1))), 0.0, float(np.sin(0.3 * (k + 1))), 0.0)
        v.send(p.View(camera=base.model_copy(update={"orientation": q}), width=64, height=48))
    for v in viewers:
        v.expect(p.Image, 60)
    stream.start()
    got = [
        {m.step for m in v.drain(3.0) if isinstance(m, p.Image) and m.width == 64} for v in viewers
    ]
    stream.stop()
    assert stream.step > 1.5 * max(len(g) for g in got), "frames did not outpace the renders"
    common = got[0] & got[1] & got[2]
    assert min(len(g) for g in got) >= 5, [len(g) for g in got]
    assert len(common) >= 0.8 * min(len(g) for g in got), (len(common), [len(g) for g in got])
    for v in viewers:
        v.close()


def test_big_frames_are_read_at_the_pace_of_rendering(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With viewers attached, a simulation's next big frame (here 1.2 MB) is read once a render
    took the last one: frames nobody would see are not received and validated. The only
    encoder is kept busy, so the render of the second frame waits and so does the third's
    read; small frames are read at once."""
    SlowEncodes(lambda call: 0.01 if call == 1 else 1.5).install(monkeypatch)
    live = start_server(make_settings(tmp_path, encode_workers=1, frame_wait_s=10.0))
    frames = live.app_state.metrics.sim_frames
    sim = Peer(live.ws_url, "simulation", live.token, "pace")
    topo, pos = molecule(100_000)
    sim.send(topo)
    sim.send(frame(pos, 0))
    viewer = Peer(live.view_url, "viewer", live.viewer_token, "pace", max_queue=None)
    viewer.expect(p.Image, 60)  # the first encode is quick
    n0 = frames._value.get()
    sender = threading.Thread(
        target=lambda: [sim.send(frame(pos + np.float32(0.01 * k), k)) for k in range(1, 6)],
        daemon=True,
    )
    sender.start()
    time.sleep(1.0)
    read = frames._value.get() - n0
    assert 1 <= read <= 2, read  # the frame being encoded, then one waiting for the encoder
    deadline = time.monotonic() + 60
    while frames._value.get() - n0 < 5 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert frames._value.get() - n0 == 5  # read as renders take them
    sender.join(10)
    small = Stream(live, "small").start()  # tiny frames: no pacing
    small_viewer = Peer(live.view_url, "viewer", live.viewer_token, "small", max_queue=None)
    time.sleep(0.5)
    n0, s0 = frames._value.get(), small.step
    time.sleep(1.0)
    assert frames._value.get() - n0 >= 0.8 * (small.step - s0)
    small.stop()
    for peer in (sim, viewer, small_viewer):
        peer.close()
    live.stop()
