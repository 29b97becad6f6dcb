"""The server as its own process, for tests that kill it or that it must survive."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]
TOKEN, VIEWER_TOKEN = "test-token", "viewer-token"


def command_line(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def running(pids: list[int]) -> list[int]:
    """Those of `pids` still running (a zombie has ended)."""
    out = []
    for pid in pids:
        try:
            stat = Path(f"/proc/{pid}/stat").read_bytes()
        except OSError:
            continue
        if stat[stat.rfind(b")") + 2 :].split()[0] != b"Z":
            out.append(pid)
    return out


def wait_gone(pids: list[int], timeout: float = 15.0) -> list[int]:
    """Wait for `pids` to end; those still running at the deadline."""
    deadline = time.monotonic() + timeout
    while (left := running(pids)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return [pid for pid in left if command_line(pid)]


def listening_sockets(pids: list[int]) -> set[tuple[str, int]]:
    """The TCP (address, port) pairs `pids` listen on, from /proc: IPv4 addresses dotted,
    IPv6 ones as /proc writes them (32 hex digits)."""
    inodes: dict[str, tuple[str, int]] = {}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError):
            for line in Path(table).read_text().splitlines()[1:]:
                fields = line.split()
                if fields[3] == "0A":  # LISTEN
                    host, port = fields[1].rsplit(":", 1)
                    if len(host) == 8:  # IPv4, little-endian
                        host = ".".join(str(b) for b in reversed(bytes.fromhex(host)))
                    inodes[fields[9]] = (host, int(port, 16))
    found = set()
    for pid in pids:
        with contextlib.suppress(OSError):
            for fd in os.listdir(f"/proc/{pid}/fd"):
                with contextlib.suppress(OSError):
                    target = os.readlink(f"/proc/{pid}/fd/{fd}")
                    if target.startswith("socket:[") and target[8:-1] in inodes:
                        found.add(inodes[target[8:-1]])
    return found


LOOPBACK = {
    "127.0.0.1",
    "00000000000000000000000001000000",  # ::1 as /proc/net/tcp6 writes it
    "0000000000000000FFFF00000100007F",  # ::ffff:127.0.0.1
}
"""Loopback listening addresses, as `listening_sockets` gives them."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class ServerProcess:
    """`scalesteer serve` on the CPU device in a child process, with fixed tokens."""

    def __init__(
        self,
        state_dir: Path,
        *extra: str,
        port: int | None = None,
        env: dict[str, str] | None = None,
        warm: bool = False,
    ) -> None:
        """`warm`: start as `scalesteer serve` does by default, with a warm-up render and a
        selection worker started ahead (off: the suite's many servers spare the 2-core
        machine that second each)."""
        self.state_dir = state_dir
        self.extra = extra
        self.warm = warm
        self.env = env
        self.port = port or free_port()
        self.log = state_dir.parent / f"server-{self.port}.log"
        state_dir.mkdir(parents=True, exist_ok=True)
        command = [
            sys.executable, "-m", "server.commands.cli", "serve",
            "--port", str(self.port), "--device", "cpu",
            "--token", TOKEN, "--viewer-token", VIEWER_TOKEN,
            "--state-dir", str(state_dir), "--log-level", "warning",
            "--batch-engine", "local", *extra,
        ]  # fmt: skip
        if not warm:
            command += ["--set", "warm_up_render=0", "--set", "selection_prestart=0"]
        with open(self.log, "ab") as out:
            self.process = subprocess.Popen(
                command, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + 90
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"the server exited: {self.log.read_text()[-2000:]}")
            try:
                if httpx.get(f"{self.url}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("the server did not start")
            time.sleep(0.2)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/ws/sim"

    @property
    def view_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/ws/view"

    def alive(self) -> bool:
        return self.process.poll() is None

    def rss_bytes(self) -> int:
        """Resident memory of the server process (not of its file-reading children)."""
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        return 0

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
        if self.alive():
            os.kill(self.process.pid, sig)
        return self.process.wait(timeout)

    def restart(self) -> ServerProcess:
        """A new server on the same port and state directory (this one must be stopped)."""
        return ServerProcess(
            self.state_dir, *self.extra, port=self.port, env=self.env, warm=self.warm
        )
