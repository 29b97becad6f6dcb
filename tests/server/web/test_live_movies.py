"""Movies of a live session on the CPU device: every frame the simulation sends while the movie
records is in it, however much slower the renders are than the frames; and when the frames
waiting to be rendered would pass their limit, the movie says so at once, and says which it
keeps."""

from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

import protocol as p
from tests.conftest import LiveServer, make_settings, start_server
from tests.server.peers import Peer, frame, molecule

av = pytest.importorskip("av")
AUTH = {"Authorization": "Bearer test-token"}
BURST = 40


def _finished(c: httpx.Client, job: str) -> dict[str, Any]:
    deadline = time.monotonic() + 60
    while (info := c.get(f"/api/jobs/{job}", headers=AUTH).json())["state"] in (
        "queued",
        "running",
    ):
        assert time.monotonic() < deadline, info
        time.sleep(0.1)
    return info  # type: ignore[no-any-return]


def _movie_frames(c: httpx.Client, job: str) -> int:
    movie = c.get(f"/api/jobs/{job}/result", headers=AUTH)
    assert movie.status_code == 200, movie.text
    with av.open(io.BytesIO(movie.content)) as container:
        return sum(1 for _ in container.decode(video=0))


def _film(server: LiveServer, session: str) -> tuple[Peer, Peer, np.ndarray]:
    sim = Peer(server.ws_url, "simulation", server.token, session)
    topo, pos = molecule(40)
    sim.send(topo)
    sim.send(frame(pos, 0))
    watcher = Peer(server.view_url, "viewer", server.viewer_token, session)
    watcher.expect(p.Image, 60)
    return sim, watcher, pos


def test_a_movie_keeps_every_frame_sent_faster_than_it_renders(live_server: LiveServer) -> None:
    sim, watcher, pos = _film(live_server, "burst")
    with httpx.Client(base_url=live_server.url, timeout=60) as c:
        r = c.post(
            "/api/sessions/burst/movies",
            headers=AUTH,
            data={"width": "320", "height": "240", "max_frames": "1000"},
        )
        assert r.status_code == 202, r.text
        job = r.json()["id"]
        for step in range(1, BURST + 1):  # far faster than a 320x240 movie frame renders here
            sim.send(frame(pos + np.float32(0.05 * step), step))
        sim.send(p.Ping(client_time=0.0))  # every frame is in once the answer comes
        sim.expect(p.Pong)
        taken = c.get(f"/api/jobs/{job}", headers=AUTH).json()["movie"]
        assert taken["taken"] == BURST + 1, taken  # the frame on the screen, then each new one
        assert taken["waiting"] > 0  # the renders are behind: frames wait, none is dropped
        behind = watcher.expect(p.Event, 30, where=lambda m: m.code == "movie_behind")
        assert job in behind.message and "keeps every frame" in behind.message
        finishing = c.delete(f"/api/jobs/{job}", headers=AUTH).json()
        assert finishing["finishing"] and finishing["state"] == "running"
        info = _finished(c, job)
        assert info["state"] == "done", info
        assert info["progress"] == {"done": BURST + 1, "total": BURST + 1}
        assert info["movie"]["skipped"] == 0 and info["warning"] is None
        assert info["movie"]["ended_because"] == "it was stopped"
        assert info["movie"]["render_s"] > 0 and info["movie"]["eta_s"] == 0
        assert _movie_frames(c, job) == BURST + 1
    sim.close()
    watcher.close()


def test_a_movie_past_its_queue_says_at_once_what_it_skips(tmp_path: Path) -> None:
    server = start_server(make_settings(tmp_path, movie_queue_bytes=1))
    try:
        sim, watcher, pos = _film(server, "tight")
        with httpx.Client(base_url=server.url, timeout=60) as c:
            r = c.post(
                "/api/sessions/tight/movies",
                headers=AUTH,
                data={"width": "320", "height": "240", "max_frames": "1000"},
            )
            job = r.json()["id"]
            for step in range(1, 11):
                sim.send(frame(pos + np.float32(0.05 * step), step))
            told = watcher.expect(p.Event, 30, where=lambda m: m.code == "movie_skipped")
            assert told.level == "warning" and job in told.message
            assert "movie_queue_bytes" in told.message
            c.delete(f"/api/jobs/{job}", headers=AUTH)
            info = _finished(c, job)
            movie = info["movie"]
            assert info["state"] == "done" and info["partial"] is True
            assert movie["skipped"] > 0 and movie["taken"] + movie["skipped"] == 11
            skipped_steps = sum(span[2] for span in movie["skipped_spans"])
            assert skipped_steps == movie["skipped"]
            assert "skipped_spans" in info["warning"]
            assert _movie_frames(c, job) == movie["taken"]
        sim.close()
        watcher.close()
    finally:
        server.stop()


def test_a_movie_ends_at_its_duration(live_server: LiveServer) -> None:
    sim, watcher, _ = _film(live_server, "short")
    with httpx.Client(base_url=live_server.url, timeout=60) as c:
        r = c.post(
            "/api/sessions/short/movies",
            headers=AUTH,
            data={"width": "64", "height": "48", "max_s": "0.5"},
        )
        assert r.json()["movie"]["max_s"] == 0.5
        info = _finished(c, r.json()["id"])
        assert info["state"] == "done"
        assert info["movie"]["ended_because"] == "it recorded for its 0.5 s (max_s)"
    sim.close()
    watcher.close()
