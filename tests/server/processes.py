"""The server as its own process, for tests that kill it or that it must survive."""

from __future__ import annotations

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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class ServerProcess:
    """`scalesteer serve` on the CPU device in a child process, with fixed tokens."""

    def __init__(self, state_dir: Path, *extra: str, port: int | None = None) -> None:
        self.state_dir = state_dir
        self.extra = extra
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
        with open(self.log, "ab") as out:
            self.process = subprocess.Popen(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
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
        return ServerProcess(self.state_dir, *self.extra, port=self.port)
