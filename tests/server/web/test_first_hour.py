"""What a newcomer's dashboard needs from the server: legends, atoms that markers follow, a
trajectory opened from the browser as a replay session, and a movie of the live session."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import numpy as np
import pytest

import protocol as p
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame, molecule

pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import DCD, PSF, PDB_small

AUTH = {"Authorization": "Bearer test-token"}


def test_the_legend_follows_the_colouring(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "legend")
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 0))
    steerer = Peer(live_server.view_url, "steerer", live_server.token, "legend")
    first = steerer.expect(p.State, where=lambda m: m.legend is not None)
    assert first.legend is not None and first.legend.color_by == "element"
    labels = {e.label for e in first.legend.entries}
    assert labels == {e.capitalize() for e in topo.elements}
    steerer.send(p.SetRenderParams(params={"color_by": "chain"}))
    chain = steerer.expect(p.State, where=lambda m: m.legend and m.legend.color_by == "chain")
    assert [e.label for e in chain.legend.entries] == sorted(set(topo.chain_ids))  # type: ignore[union-attr]
    sim.close()
    steerer.close()


def test_tracked_atoms_follow_the_frames(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "track")
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 0))
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "track")
    viewer.expect(p.Image, 60)
    viewer.send(p.View(track=[2, 5]))
    now = viewer.expect(p.Tracked)
    assert now.atoms == [2, 5] and np.allclose(now.positions, pos[[2, 5]], atol=1e-4)
    moved = pos + np.float32(3.0)
    time.sleep(0.15)
    sim.send(frame(moved, 7))
    later = viewer.expect(p.Tracked, where=lambda m: m.step == 7)
    assert np.allclose(later.positions, moved[[2, 5]], atol=1e-4)
    viewer.send_raw(p.encode(p.View(seq=99, track=[500])))
    err = viewer.expect(p.Error, where=lambda m: m.ref == 99)
    assert err.path == "view.track"
    sim.close()
    viewer.close()


def test_atoms_tracked_before_the_simulation_sent_its_topology_are_followed(
    live_server: LiveServer,
) -> None:
    """A viewer that asks to track atoms before the topology has come (a replay still
    starting) was refused ("atom index out of range [0, 0)") and never heard of them again."""
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "early")
    viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "early")
    viewer.send(p.View(seq=5, width=64, height=48, track=[2, 5, 400]))
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 3))
    now = viewer.expect(p.Tracked, 60, where=lambda m: m.step == 3)
    assert now.atoms == [2, 5]  # 400 is past the topology's atoms: left out
    assert np.allclose(now.positions, pos[[2, 5]], atol=1e-4)
    sim.close()
    viewer.close()


def test_a_recording_of_the_live_session_is_a_movie_of_its_frames(live_server: LiveServer) -> None:
    sim = Peer(live_server.ws_url, "simulation", live_server.token, "film")
    topo, pos = molecule(12)
    sim.send(topo)
    sim.send(frame(pos, 0))
    watcher = Peer(live_server.view_url, "viewer", live_server.viewer_token, "film")
    watcher.expect(p.Image, 60)
    with httpx.Client(base_url=live_server.url, timeout=60) as c:
        r = c.post(
            "/api/sessions/film/movies",
            headers=AUTH,
            data={"width": "64", "height": "48", "max_frames": "100"},
        )
        assert r.status_code == 202, r.text
        job = r.json()["id"]

        def recorded() -> int:
            done: int = c.get(f"/api/jobs/{job}", headers=AUTH).json()["progress"]["done"]
            return done

        for step in range(1, 6):  # one frame at a time: each is recorded before the next
            sim.send(frame(pos + np.float32(0.2 * step), step))
            deadline = time.monotonic() + 30
            while recorded() < step:
                assert time.monotonic() < deadline
                time.sleep(0.05)
        assert c.delete(f"/api/jobs/{job}", headers=AUTH).json()["finishing"]
        while (info := c.get(f"/api/jobs/{job}", headers=AUTH).json())["state"] == "running":
            time.sleep(0.1)
        assert info["state"] == "done" and info["session"] == "film", info
        assert info["partial"] is False and info["warning"] is None  # every frame it was sent
        movie = c.get(f"/api/jobs/{job}/result", headers=AUTH)
        assert movie.status_code == 200 and movie.headers["content-type"] == "video/mp4", movie.text
        import av

        with av.open(Path(_write(movie.content))) as container:
            frames = sum(1 for _ in container.decode(video=0))
        assert frames == info["progress"]["done"] >= 5
        r = c.post("/api/sessions/nobody/movies", headers=AUTH, data={})
        assert r.status_code == 404
    sim.close()
    watcher.close()


def _write(data: bytes) -> str:
    import tempfile

    with tempfile.NamedTemporaryFile(suffix=".mp4", delete=False) as fh:
        fh.write(data)
        return fh.name


def test_files_opened_in_the_browser_become_a_replay_session(live_server: LiveServer) -> None:
    with httpx.Client(base_url=live_server.url, timeout=120) as c:
        with open(PSF, "rb") as top, open(DCD, "rb") as traj:
            r = c.post(
                "/api/replays",
                headers=AUTH,
                files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                data={"fps": "20"},
            )
        assert r.status_code == 201, r.text
        opened = r.json()
        assert opened["session"] == "replay-adk" and opened["n_frames"] == 98
        deadline = time.monotonic() + 60  # the child connects once it has read the files
        while c.get("/api/sessions/replay-adk", headers=AUTH).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        viewer = Peer(live_server.view_url, "viewer", live_server.viewer_token, "replay-adk")
        state = viewer.expect(p.State, 60, where=lambda m: m.engine is not None)
        assert state.engine is not None and state.engine.kind == "replay"
        assert state.engine.n_frames == 98
        viewer.expect(p.Image, 60)
        assert (live_server.settings.state_dir / "data" / "opened").is_dir()
        with open(PSF, "rb") as top, open(DCD, "rb") as traj:
            again = c.post(
                "/api/replays",
                headers=AUTH,
                files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
            )
        # the same files again play beside the first, under a fresh name
        assert again.status_code == 201, again.text
        assert again.json()["session"] == "replay-adk-2"
        with open(PSF, "rb") as top:
            named = c.post(
                "/api/replays",
                headers=AUTH,
                files=[("topology", ("adk.psf", top))],
                data={"session": "replay-adk"},
            )
        assert named.status_code == 409
        assert "'replay-adk'" in named.json()["detail"] and "adk.psf" in named.json()["detail"]
        bad = c.post("/api/replays", headers=AUTH, files={"topology": ("x.pdb", b"junk\n")})
        assert bad.status_code == 422 and "x.pdb" in bad.json()["detail"]
        assert "0-x.pdb" not in bad.json()["detail"]  # the user's file name, not the server's
        listed = c.get("/api/replays", headers=AUTH).json()
        assert [r["session"] for r in listed] == ["replay-adk", "replay-adk-2"]
        assert all(r["running"] for r in listed)
        assert c.delete("/api/replays/replay-adk", headers=AUTH).status_code == 200
        assert c.delete("/api/replays/replay-adk-2", headers=AUTH).status_code == 200
        assert not c.get("/api/replays", headers=AUTH).json()[0]["running"]
        viewer.close()


def test_a_structure_opens_alone_and_a_refusal_is_a_sentence(live_server: LiveServer) -> None:
    """What the dashboard's Open files sends for one structure file (no trajectory field),
    and a form that gives text where a file belongs."""
    with httpx.Client(base_url=live_server.url, timeout=120) as c:
        with open(PDB_small, "rb") as top:
            alone = c.post("/api/replays", headers=AUTH, files=[("topology", ("adk.pdb", top))])
        assert alone.status_code == 201, alone.text
        assert alone.json()["session"] == "replay-adk" and alone.json()["n_frames"] == 1
        with open(PSF, "rb") as top:
            lone = c.post("/api/replays", headers=AUTH, files=[("topology", ("adk.psf", top))])
        assert lone.status_code == 422 and lone.json()["detail"].startswith("adk.psf has no coord")
        with open(PDB_small, "rb") as top:
            text = c.post(
                "/api/replays",
                headers=AUTH,
                files=[("topology", ("adk.pdb", top))],
                data={"trajectory": "[]"},
            )
        assert text.status_code == 422
        assert text.json()["detail"] == "trajectory.0: expected a file, got the text '[]'"
        assert c.delete("/api/replays/replay-adk", headers=AUTH).status_code == 200


def test_a_body_that_is_not_json_is_named_so(live_server: LiveServer) -> None:
    """Malformed JSON had answered `4: jSON decode error` (an offset as if it were a field)."""
    with httpx.Client(base_url=live_server.url, timeout=30) as c:
        bad = c.post(
            "/api/sessions/default/recordings",
            headers={**AUTH, "Content-Type": "application/json"},
            content=b"[1,2",
        )
    assert bad.status_code == 422
    detail = bad.json()["detail"]
    assert detail.startswith("the body is not valid JSON at character 4"), detail
