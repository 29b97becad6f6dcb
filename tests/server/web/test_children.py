"""What the server starts ends with it: replays, file readers and Ray, whether the server stops
in order or is killed with `kill -9` (`server.supervisor`); and jobs render in the server's own
process unless Ray is asked for or a cluster is configured."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import httpx
import pytest

import protocol as p
from server.supervisor import descendants
from tests.conftest import LiveServer
from tests.server.peers import Peer
from tests.server.processes import TOKEN, ServerProcess, command_line, running, wait_gone

pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import DCD, PSF

AUTH = {"Authorization": f"Bearer {TOKEN}"}
AUTH_LIVE = {"Authorization": "Bearer test-token"}


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["stopped", "killed"])
def test_a_replay_ends_with_its_server(tmp_path: Path, sig: signal.Signals) -> None:
    """A replay child outlived a `kill -9` of its server, reconnected to the next one and could
    be neither listed nor stopped; now nothing the server started outlives it."""
    server = ServerProcess(tmp_path / "state")
    try:
        with httpx.Client(base_url=server.url, timeout=120) as c, open(PSF, "rb") as top:
            with open(DCD, "rb") as traj:
                r = c.post(
                    "/api/replays",
                    headers=AUTH,
                    files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                    data={"fps": "5", "loop": "true"},
                )
            assert r.status_code == 201, r.text
            deadline = time.monotonic() + 60  # the child connects once it has read the files
            while c.get("/api/sessions/replay-adk", headers=AUTH).status_code != 200:
                assert time.monotonic() < deadline, "the replay did not connect"
                time.sleep(0.1)
        tree = descendants(server.process.pid)
        assert any("simulation_adapters.replay" in command_line(pid) for pid in tree), tree
    finally:
        server.stop(sig)
    left = wait_gone(tree)
    assert not left, [command_line(pid) for pid in left]


def test_jobs_render_here_unless_ray_is_asked_for(tmp_path: Path) -> None:
    """Ray started by itself for any job (a 45-frame movie on a laptop: load 41 on 2 cores,
    two processes left behind); with neither `--batch-engine ray` nor a cluster configured, a
    job renders in the server's own process and the server starts nothing for it."""
    env = {k: v for k, v in os.environ.items() if not k.endswith("RAY_ADDRESS")}
    server = ServerProcess(tmp_path / "state", "--batch-engine", "auto", env=env)
    try:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            assert c.get("/healthz").json()["batch"] == {"engine": "local"}
            with open(PSF, "rb") as top, open(DCD, "rb") as traj:
                r = c.post(
                    "/api/jobs",
                    headers=AUTH,
                    files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                    data={"width": "32", "height": "24", "output": "zip", "stop": "3"},
                )
            assert r.status_code == 202, r.text
            deadline = time.monotonic() + 60
            while (info := c.get(f"/api/jobs/{r.json()['id']}", headers=AUTH).json())[
                "state"
            ] not in ("done", "failed"):
                assert time.monotonic() < deadline, info
                time.sleep(0.1)
            assert info["state"] == "done", info
        # the file readers (one spare waiting for the next file) and nothing else
        started = [command_line(pid) for pid in running(descendants(server.process.pid))]
        assert started and all("structures.isolated" in line for line in started), started
    finally:
        server.stop()


def test_a_replay_that_dies_tells_its_viewers_why(live_server: LiveServer) -> None:
    """A replay child that ends on its own with a failure (here killed; a damaged trajectory
    or a crash of a reader alike) is said to the session's viewers and in the server's log;
    their dashboard had only shown the simulation as gone."""
    with httpx.Client(base_url=live_server.url, timeout=120) as c, open(PSF, "rb") as top:
        with open(DCD, "rb") as traj:
            r = c.post(
                "/api/replays",
                headers=AUTH_LIVE,
                files=[("topology", ("adk.psf", top)), ("trajectory", ("adk.dcd", traj))],
                data={"fps": "5", "loop": "true"},
            )
        assert r.status_code == 201, r.text
        name = r.json()["session"]
        deadline = time.monotonic() + 60
        while c.get(f"/api/sessions/{name}", headers=AUTH_LIVE).status_code != 200:
            assert time.monotonic() < deadline, "the replay did not connect"
            time.sleep(0.1)
        viewer = Peer(live_server.view_url, "viewer", live_server.token, name)
        try:
            # the replay itself, under its supervisor: the supervisor dies of the same signal
            supervisor = live_server.app_state.replays.processes[name].process.process
            (child,) = [
                pid
                for pid in descendants(supervisor.pid)
                if "simulation_adapters.replay" in command_line(pid)
            ]
            os.kill(child, signal.SIGKILL)
            event = viewer.expect(p.Event, 30, where=lambda m: m.code == "replay_failed")
            assert event.level == "error" and "killed by SIGKILL" in event.message, event
            assert "atoms," not in event.message  # not the line it started with
            # a viewer who opens the session afterwards is told too
            late = Peer(live_server.view_url, "viewer", live_server.token, name)
            try:
                told = late.expect(p.Event, 30, where=lambda m: m.code == "replay_failed")
                assert told.message == event.message
            finally:
                late.close()
            session = live_server.app_state.sessions.get(name)
            assert session is not None and session.stopped_why is not None
            sim = Peer(live_server.ws_url, "simulation", live_server.token, name)
            try:  # a simulation that connects again ends the story
                sim.expect(p.State, 30)
                assert session.stopped_why is None
            finally:
                sim.close()
            listed = c.get("/api/replays", headers=AUTH_LIVE).json()
            assert any(x["session"] == name and x["exit_code"] == -9 for x in listed), listed
            one = c.get(f"/api/replays/{name}", headers=AUTH_LIVE).json()
            assert "killed by SIGKILL" in one["last_words"], one
        finally:
            viewer.close()
            c.delete(f"/api/replays/{name}", headers=AUTH_LIVE)
