"""A render server of the notebook's own: `scalesteer serve` started from Python.

`connect()` without a URL starts one here, on a free loopback port with a fresh random token
and a temporary state directory, under the server's supervisor (`server/supervisor.py`): the
supervisor holds the read end of a pipe whose write end only this process holds, so when this
process ends (normally, by an exception, or killed with `kill -9` as a restarted kernel is),
the kernel closes the pipe and the supervisor ends the server and removes the state directory.
Nothing started here outlives the Python process that started it.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import math
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

from scalesteer.errors import ServerStartError

ROOT = Path(__file__).resolve().parents[1]
START_TIMEOUT_S = 90.0
STOP_GRACE_S = 40.0
"""The supervisor's grace when the server stops, at the default `close_wait_s` (10 s): the
server alone has half of it (5 s for open requests, `close_wait_s` for renders on its devices,
docs/server.md "Stopping", then its recordings and jobs closed), what is still running the
other half, then SIGKILL. The supervisor's default of 5 s gave the server 2.5 s, and could
leave a recording interrupted. `stop_grace_s` sizes it for the server's own settings."""


def stop_grace_s(extra: tuple[str, ...]) -> float:
    """The supervisor's grace for a server started with `extra`: twice what its own stop may
    take (10 s beside `close_wait_s`), so that a `--set close_wait_s=...` larger than the
    default is not cut short. The setting is read as the server reads it (`--set NAME=VALUE`
    or `--set=NAME=VALUE`, `-` in the name as `_`); a value it would refuse is its to name."""
    pairs = [b for a, b in itertools.pairwise(extra) if a == "--set"]
    pairs += [a.removeprefix("--set=") for a in extra if a.startswith("--set=")]
    wait_s = 10.0
    for pair in pairs:
        name, _, value = pair.partition("=")
        if name.strip().replace("-", "_") == "close_wait_s":
            with contextlib.suppress(ValueError):
                if math.isfinite(given := float(value)):
                    wait_s = max(wait_s, given)
    return max(STOP_GRACE_S, 2 * (wait_s + 10.0))


def free_port(host: str = "127.0.0.1") -> int:
    """A port nobody listens on now (another process may take it before the server does:
    `LocalServer` tries again on a new one)."""
    with socket.socket() as s:
        s.bind((host, 0))
        port: int = s.getsockname()[1]
        return port


def _exit_text(code: int) -> str:
    """`Popen.returncode` in words: a negative one is the signal that ended the process."""
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
    return f"exit code {code}"


class LocalServer:
    """`scalesteer serve` on 127.0.0.1 in a child process that ends with this one.

    `device`: `auto` (a CUDA GPU when there is one), `cpu` or `cuda:N`. `state_dir`: where
    recordings, jobs and steering logs go; default a temporary directory removed with the
    server. `extra`: more `scalesteer serve` options (`--set NAME=VALUE`, ...)."""

    def __init__(
        self,
        device: str = "auto",
        *,
        state_dir: str | os.PathLike[str] | None = None,
        extra: tuple[str, ...] = (),
        timeout: float = START_TIMEOUT_S,
    ) -> None:
        self.device = device
        self.token = secrets.token_urlsafe(24)
        self.viewer_token = secrets.token_urlsafe(24)
        self._temporary = state_dir is None
        self.state_dir = Path(
            tempfile.mkdtemp(prefix="scalesteer-") if state_dir is None else state_dir
        )
        if self._temporary:  # beside the folder, which the supervisor removes when it ends
            handle, log_name = tempfile.mkstemp(prefix="scalesteer-", suffix=".log")
            os.close(handle)
            self.log_path = Path(log_name)
        else:
            self.log_path = self.state_dir / "server.log"
        self._lock = threading.Lock()
        self.grace_s = stop_grace_s(extra)
        self._lifeline = -1
        self.process: subprocess.Popen[bytes] | None = None
        self.port = 0
        last = ""
        for _attempt in range(3):  # a port taken between the probe and the bind: another one
            self.port = free_port()
            self._spawn(extra)
            try:
                self._wait_ready(timeout)
                break
            except ServerStartError as exc:
                last = str(exc)
                self.stop()
                if "address already in use" not in last.lower():
                    raise
        else:
            raise ServerStartError(last)
        atexit.register(self.stop)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _spawn(self, extra: tuple[str, ...]) -> None:
        read_end, lifeline = os.pipe()  # both ends non-inheritable: only the supervisor gets one
        command = [
            sys.executable, "-m", "server.commands.cli", "serve",
            "--host", "127.0.0.1", "--port", str(self.port), "--device", self.device,
            # NAME=VALUE: a token may begin with "-", which argparse would take for an option
            f"--token={self.token}", f"--viewer-token={self.viewer_token}",
            "--state-dir", str(self.state_dir), "--log-level", "warning", *extra,
        ]  # fmt: skip
        supervisor = [sys.executable, "-m", "server.supervisor", "--lifeline", str(read_end)]
        supervisor += ["--grace", str(self.grace_s)]
        if self._temporary:
            supervisor += ["--remove", str(self.state_dir)]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        self.state_dir.mkdir(parents=True, exist_ok=True)
        try:
            with open(self.log_path, "ab") as log:
                self.process = subprocess.Popen(
                    [*supervisor, "--", *command],
                    pass_fds=(read_end,),
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    env=env,
                    cwd=ROOT,
                    start_new_session=True,  # a Ctrl-C in the notebook's terminal is not its
                )
        except BaseException:
            os.close(lifeline)
            raise
        finally:
            os.close(read_end)
        self._lifeline = lifeline

    def _wait_ready(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while True:
            assert self.process is not None
            code = self.process.poll()
            if code is not None:
                raise ServerStartError(
                    f"the scalesteer server exited ({_exit_text(code)}):\n{self.log_tail()}"
                )
            try:
                with urllib.request.urlopen(f"{self.url}/healthz", timeout=2) as answer:
                    if answer.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                pass
            if time.monotonic() > deadline:
                raise ServerStartError(
                    f"the scalesteer server did not answer within {timeout:.0f} s:\n"
                    f"{self.log_tail()}"
                )
            time.sleep(0.1)

    def log_tail(self, chars: int = 2000) -> str:
        """The end of the server's log (its output goes there, not into the notebook)."""
        with contextlib.suppress(OSError):
            return self.log_path.read_text(errors="replace")[-chars:]
        return ""

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def answers(self, timeout: float = 5.0) -> bool:
        """Alive and answering its health check (its process can outlive a killed server for
        as long as the supervisor ends what the server left)."""
        if not self.alive():
            return False
        try:
            with urllib.request.urlopen(f"{self.url}/healthz", timeout=timeout) as answer:
                return bool(answer.status == 200)
        except (urllib.error.URLError, OSError):
            return False

    def stop(self, timeout: float | None = None) -> None:
        """End the server (and what it started) and wait for it (by default its grace and
        10 s more); idempotent."""
        if timeout is None:
            timeout = self.grace_s + 10.0
        with self._lock:
            if self._lifeline >= 0:
                os.close(self._lifeline)  # the supervisor sees it close and ends the tree
                self._lifeline = -1
            process = self.process
        if process is not None and process.poll() is None:
            try:
                process.wait(timeout)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        with contextlib.suppress(Exception):
            atexit.unregister(self.stop)
        if self._temporary:
            with contextlib.suppress(OSError):
                self.log_path.unlink()

    def __repr__(self) -> str:
        state = "running" if self.alive() else "stopped"
        return f"LocalServer({self.url}, device={self.device!r}, {state})"
