"""Recordings and movies end with the page that started them: listed (REST), stopped when
their owner has left the session for the grace time, kept going through a reconnection, and
left running when started without an owner."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

import protocol as p
from tests.conftest import LiveServer, make_settings, start_server
from tests.server.peers import Peer, frame, molecule

pytest.importorskip("av")
AUTH = {"Authorization": "Bearer test-token"}
GRACE_S = 1.0


@pytest.fixture
def server(tmp_path: Path) -> Iterator[LiveServer]:
    live = start_server(make_settings(tmp_path, owner_grace_s=GRACE_S))
    yield live
    live.stop()


def _start(c: httpx.Client, owner: str | None) -> tuple[str, str]:
    """A recording and a movie of session `work`, owned by `owner`."""
    body: dict[str, Any] = {"owner": owner} if owner else {}
    rec = c.post("/api/sessions/work/recordings", json=body, headers=AUTH)
    assert rec.status_code == 201, rec.text
    form = {"width": "64", "height": "48", **({"owner": owner} if owner else {})}
    movie = c.post("/api/sessions/work/movies", data=form, headers=AUTH)
    assert movie.status_code == 202, movie.text
    return rec.json()["id"], movie.json()["id"]


def _states(c: httpx.Client, rec: str, job: str) -> tuple[str, str]:
    return (
        c.get(f"/api/recordings/{rec}", headers=AUTH).json()["state"],
        c.get(f"/api/jobs/{job}", headers=AUTH).json()["state"],
    )


def _wait(condition: Any, what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def test_work_ends_once_its_page_has_left(server: LiveServer) -> None:
    sim = Peer(server.ws_url, "simulation", server.token, "work")
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 0))
    page = Peer(server.view_url, "steerer", server.token, "work", instance="tab-1")
    page.expect(p.State, where=lambda m: m.camera is not None)
    with httpx.Client(base_url=server.url, timeout=30) as c:
        rec, job = _start(c, "tab-1")
        listed = c.get("/api/jobs", params={"active": "true"}, headers=AUTH).json()
        assert [(j["id"], j["kind"], j["owner"]) for j in listed] == [(job, "live", "tab-1")]
        page.close()  # the tab reconnects within the grace time: nothing ends
        time.sleep(GRACE_S / 2)
        page = Peer(server.view_url, "steerer", server.token, "work", instance="tab-1")
        time.sleep(GRACE_S)
        sim.send(frame(pos, 1))
        assert _states(c, rec, job) == ("recording", "running")
        page.close()  # the tab closes
        _wait(lambda: _states(c, rec, job) == ("finished", "done"), "both to end")
        why = "the page that started it left session 'work'"
        assert c.get(f"/api/recordings/{rec}", headers=AUTH).json()["ended_because"] == why
        info = c.get(f"/api/jobs/{job}", headers=AUTH).json()
        assert info["movie"]["ended_because"] == why and info["result"]
        assert c.get("/api/jobs", params={"active": "true"}, headers=AUTH).json() == []
        assert [j["id"] for j in c.get("/api/jobs", headers=AUTH).json()] == [job]
    sim.close()


def test_work_without_an_owner_outlives_the_page(server: LiveServer) -> None:
    sim = Peer(server.ws_url, "simulation", server.token, "work")
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 0))
    page = Peer(server.view_url, "steerer", server.token, "work", instance="tab-2")
    page.expect(p.State, where=lambda m: m.camera is not None)
    with httpx.Client(base_url=server.url, timeout=30) as c:
        rec, job = _start(c, None)  # the page asked to keep them running
        page.close()
        time.sleep(GRACE_S * 2)
        assert _states(c, rec, job) == ("recording", "running")
        assert c.post(f"/api/recordings/{rec}/stop", headers=AUTH).status_code == 200
        assert c.delete(f"/api/jobs/{job}", headers=AUTH).json()["finishing"]
        _wait(lambda: _states(c, rec, job) == ("finished", "done"), "both to end")
        assert c.get(f"/api/recordings/{rec}", headers=AUTH).json()["ended_because"] is None
    sim.close()


def test_work_of_a_page_that_is_not_there_ends_after_the_grace(server: LiveServer) -> None:
    """An owner that never connects (or left before its request arrived) is gone already."""
    sim = Peer(server.ws_url, "simulation", server.token, "work")
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 0))
    watcher = Peer(server.view_url, "viewer", server.viewer_token, "work")
    watcher.expect(p.Image, 60)
    with httpx.Client(base_url=server.url, timeout=30) as c:
        rec, job = _start(c, "nobody")
        _wait(lambda: _states(c, rec, job) == ("finished", "done"), "both to end")
    sim.close()
    watcher.close()
