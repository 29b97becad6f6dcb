"""What the server starts ends with it: replays and file readers, whether the server stops in
order or is killed with `kill -9` (`server.supervisor`)."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import httpx
import pytest

from server.supervisor import descendants
from tests.server.processes import TOKEN, ServerProcess, command_line, wait_gone

pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import DCD, PSF

AUTH = {"Authorization": f"Bearer {TOKEN}"}


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
