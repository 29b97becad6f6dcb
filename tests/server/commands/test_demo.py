"""`scalesteer demo` as a user runs it: a real OpenMM villin simulation behind a real server."""

from __future__ import annotations

import contextlib
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

import protocol as p
from server.commands.villin import MD_NICE
from server.supervisor import descendants
from tests.server.peers import Peer
from tests.server.processes import command_line, wait_gone

ROOT = Path(__file__).resolve().parents[3]
pytest.importorskip("openmm")


def _interruptible() -> None:
    """Ctrl-C's signal as a terminal delivers it. A child inherits an ignored SIGINT, and
    Python then raises no KeyboardInterrupt for it: run late in the whole suite, the demo
    inherited one and ran on after the test's Ctrl-C (alone the test passed)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _thread_nices(pid: int) -> dict[str, int]:
    """The nice value of each thread of `pid`, by name (the main thread by its id)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        stat = (task / "stat").read_text()
        nice = int(stat[stat.rfind(")") + 2 :].split()[16])
        name = task.name if int(task.name) == pid else (task / "comm").read_text().strip()
        out[name] = nice
    return out


def _small_job(port: int, token: str) -> dict[str, object]:
    """A three-frame job of the demo's server, once it has ended."""
    from MDAnalysisTests.datafiles import PDB_small

    url = f"http://127.0.0.1:{port}"
    auth = {"Authorization": f"Bearer {token}"}
    with httpx.Client(base_url=url, headers=auth, timeout=60) as c:
        assert c.get("/healthz").json()["batch"] == {"engine": "local"}
        with open(PDB_small, "rb") as pdb:
            r = c.post(
                "/api/jobs",
                files={"topology": ("small.pdb", pdb)},
                data={"width": "32", "height": "24", "output": "zip"},
            )
        assert r.status_code == 202, r.text
        deadline = time.monotonic() + 120
        while (info := c.get(f"/api/jobs/{r.json()['id']}").json())["state"] in (
            "queued",
            "running",
        ):
            assert time.monotonic() < deadline, info
            time.sleep(0.2)
        return dict(info)


@pytest.mark.slow
def test_demo_serves_frames_and_takes_steering(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "server.commands.cli",
            "demo",
            "--port",
            "0",
            "--no-browser",
            "--duration",
            "240",
            "--state-dir",
            str(tmp_path),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=_interruptible,
    )
    # the demo's output is read for as long as it runs, as a terminal would: a pipe left
    # unread fills up (64 KiB) and blocks the demo on its next print, at the latest on
    # "stopping..." after Ctrl-C
    lines: queue.Queue[str] = queue.Queue()
    output: list[str] = []

    def drain() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        url = None
        deadline = time.monotonic() + 180
        while url is None and time.monotonic() < deadline:
            try:
                line = lines.get(timeout=1.0)
            except queue.Empty:
                if proc.poll() is not None:
                    break
                continue
            output.append(line)
            m = re.search(r"dashboard:\s+http://127\.0\.0\.1:(\d+)/\?token=(\S+)", line)
            if m:
                url = (int(m.group(1)), m.group(2))
        assert url is not None, "".join(output)
        port, token = url
        steerer = Peer(f"ws://127.0.0.1:{port}/ws/view", "steerer", token)
        state = steerer.expect(
            p.State, 120, where=lambda m: m.sim is not None and m.sim.n_atoms > 0
        )
        assert state.sim is not None and state.sim.n_atoms == 582
        first = steerer.expect(p.Image, 180, where=lambda m: m.step is not None and m.step > 0)
        later = steerer.expect(
            p.Image, 180, where=lambda m: m.step is not None and m.step > first.step
        )
        assert later.width > 0 and later.data[:2] == b"\xff\xd8"
        # on the CPU the simulation leaves the renderer room: frames paced by its speed (every
        # 50 steps had come 2-4 times a second on two cores, and the page showed no more), in
        # a process of its own (OpenMM holds the interpreter lock while it steps) that runs at
        # a priority below the server's
        steps = set()
        while len(steps) < 6:
            got = steerer.expect(p.State, 60, where=lambda m: m.sim is not None and m.sim.step)
            assert got.sim is not None
            steps.add(got.sim.step)
        assert any(s % 50 for s in steps), steps
        (simulation,) = [
            q
            for q in descendants(proc.pid)
            if "commands.villin" in command_line(q) and "supervisor" not in command_line(q)
        ]
        nice = _thread_nices(proc.pid)
        assert nice["gpu_0"] == nice["uvicorn"] == nice[str(proc.pid)], nice
        assert _thread_nices(simulation)[str(simulation)] == nice[str(proc.pid)] + MD_NICE
        seq = steerer.send(p.SimParams(temperature_K=450.0))
        ack = steerer.expect(p.ParamsAck, 120, where=lambda m: m.ref == seq)
        assert ack.ok and ack.step is not None and ack.step >= first.step
        steerer.close()
        # a job renders in the demo's own process: Ray had started by itself for a 45-frame
        # movie, and two of its processes outlived the demo
        assert _small_job(port, token)["state"] == "done"
        started = descendants(proc.pid)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(timeout=10)
        while not lines.empty():
            output.append(lines.get_nowait())
        if proc.stdout is not None:
            proc.stdout.close()
    assert proc.returncode == 0, "".join(output[-40:])
    left = wait_gone(started)  # nothing the demo started outlives it
    assert not left, [command_line(pid) for pid in left]


@pytest.mark.slow
@pytest.mark.parametrize(
    "after",
    ["preparing the villin headpiece", "Ctrl-C stops the demo"],
    ids=["starting", "running"],
)
def test_sigterm_stops_the_demo_as_ctrl_c_does(tmp_path: Path, after: str) -> None:
    """`docker stop` and process managers send SIGTERM: the demo stops in order (its
    simulation and server closed, exit status 0), not killed half-way, whether it comes
    while the system is still being built or once the demo runs."""
    args = ["demo", "--port", "0", "--no-browser", "--duration", "240", "--device", "cpu"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.commands.cli", *args, "--state-dir", str(tmp_path)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out: list[str] = []
    assert proc.stdout is not None
    try:
        for line in proc.stdout:
            out.append(line)
            if after in line:
                break
        if after == "Ctrl-C stops the demo":  # and a render of minutes holds its device
            m = re.search(r"dashboard:\s+http://127\.0\.0\.1:(\d+)/\?token=(\S+)", "".join(out))
            assert m is not None, "".join(out)
            _start_a_long_render(int(m.group(1)), m.group(2))
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=60)
        out.append(rest)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, "".join(out[-40:])
    assert "stopping..." in "".join(out)


def _start_a_long_render(port: int, token: str) -> None:
    """A REST render that holds the demo's device for minutes (the geodesic density of
    adenylate kinase in volume at 1920x1080 on the CPU device), running once this returns:
    the demo's stop must not wait for it."""
    from MDAnalysisTests.datafiles import PDB

    url = f"http://127.0.0.1:{port}"
    auth = {"Authorization": f"Bearer {token}"}

    def render() -> None:
        params = '{"mode": "volume", "sigma_A": 3.3, "scale_space": "geodesic"}'
        with open(PDB, "rb") as f, contextlib.suppress(httpx.HTTPError):
            httpx.post(
                f"{url}/api/render",
                headers=auth,
                files={"file": ("adk.pdb", f)},
                data={"width": "1920", "height": "1080", "params": params},
                timeout=600,
            )

    threading.Thread(target=render, daemon=True).start()
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        health = httpx.get(f"{url}/healthz", timeout=5).json()
        if any(r["busy_s"] > 2.0 for r in health["render"]):
            return
        time.sleep(0.2)
    pytest.fail(f"the render did not start: {health}")


def test_demo_on_a_taken_port_says_how_to_pick_another(
    capsys: pytest.CaptureFixture[str],
) -> None:
    import socket

    from server.commands.demo import main

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["--port", str(port), "--no-browser", "--state-dir", "/nonexistent"]) == 2
    err = capsys.readouterr().err
    assert f"port {port} on 127.0.0.1 is in use" in err
    assert f"make demo PORT={port + 1}" in err and f"--port {port + 1}" in err


def test_a_token_that_begins_with_a_dash_reaches_the_simulation() -> None:
    """Tokens are URL-safe base64, so one in 64 begins with "-": passed as `--token VALUE`,
    argparse took it for an option and the demo's simulation (or a notebook's own server)
    did not start."""
    import argparse

    from server.commands.demo import _simulation_command
    from server.commands.villin import build_parser
    from server.settings import ServerSettings

    settings = ServerSettings(token="-Xy_secret", port=8123)
    command = _simulation_command(argparse.Namespace(platform=None, interval=None), settings)
    args = build_parser().parse_args(command[3:])
    assert args.token == "-Xy_secret"


def test_a_local_server_starts_with_tokens_that_begin_with_a_dash(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import scalesteer.local as local

    tokens = iter(["-server_token_value", "-viewer_token_value"])
    monkeypatch.setattr(local.secrets, "token_urlsafe", lambda _n: next(tokens))
    server = local.LocalServer(device="cpu", extra=("--set", "warm_up_render=0"))
    try:
        assert server.alive() and server.token == "-server_token_value"
        answer = httpx.get(f"{server.url}/api/sessions", params={"token": server.token})
        assert answer.status_code == 200, answer.text
    finally:
        server.stop()
